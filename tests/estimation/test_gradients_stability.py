"""Stability of the gradient maps and the diffusion estimates (issue 5, item 7): dark channels, saturated
highlights, grazing angles, n_z -> 0, flat regions, noise, complements vs full-on frames.

Rule checked everywhere: a number is reported (finite) exactly where the masks say "known"; NaN means unknown and
appears only where a mask says so; nothing is ever inf (except the documented l_d, <r^2> = inf when sigma_a is
censored at 0, which these scenes do not produce). Frames come from the simulator
(``simulators.scene.render_gradient_capture``: spheres and slabs under the default rig's 362 LEDs at 1 m, both
polarizations, 14-bit Poisson-Gaussian noise of the simulated camera).
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from estimation.camera import PinholeCamera
from estimation.diffusion import (calibrate_k, curvature_sq_from_normals, diffusion_seed, estimate_diffusion,
                                  estimate_sphere, summarize)
from estimation.dipole import total_diffuse_reflectance
from estimation.gradients import GradientMaps, LedRig, albedo_scale_from_radiometry, build_response_lut, compute_maps
from rig.acquire.geometry import led_layout
from simulators.camera import SensorModel
from simulators.scene import BumpySlabObject, SphereObject, render_gradient_capture

ETA = 1.3
MARBLE = ((2.19, 2.62, 3.00), (0.0021, 0.0041, 0.0071))
KETCHUP = ((0.18, 0.07, 0.03), (0.061, 0.97, 1.45))
SKIN2 = ((1.09, 1.59, 1.79), (0.013, 0.070, 0.145))
SENSOR = SensorModel(gain_dn_per_unit=4.5e7, black_level_dn=512, white_level_dn=16383, read_noise_dn=2.0,
                     electrons_per_dn=1.5)
ALL = ("full", "x", "y", "z", "x_c", "y_c", "z_c")


@pytest.fixture(scope="module")
def rig():
    pos, _ = led_layout(6, 1000.0, -60.0)
    inten = np.full((len(pos), 3), 1000.0)
    leds = LedRig.from_positions(pos, inten)
    patterns = {name: leds.pattern_values(name)[:, 0] for name in ALL}  # the ideal drive values
    return pos, inten, patterns, leds, build_response_lut(leds, eta=ETA, size=33, surface_radius_mm=10.0)


def camera(size: int = 48) -> PinholeCamera:
    return PinholeCamera.looking_at(width_px=size, height_px=size, fx_px=1000.0 * size / 48,
                                    position_mm=(0.0, -400.0, 0.0), target_mm=(0.0, 0.0, 0.0))


def sphere_capture(rig, material, *, patterns=ALL, exposure_s=0.02, seed=0, polarizations=("cross", "parallel")):
    pos, inten, pats, leds, lut = rig
    obj = SphereObject((0.0, 0.0, 0.0), 10.0, material[0], material[1], ETA, tessellation=3)
    return render_gradient_capture(obj, camera(), pos, inten, {p: pats[p] for p in patterns},
                                   polarizations=polarizations, exposure_s=exposure_s, sensor=SENSOR,
                                   rng=np.random.default_rng(seed))


def maps_from(cap, rig, patterns, *, parallel=True, lut=None, geometry=True, **kw):
    pos, inten, pats, leds, lut0 = rig
    frames = {k: v for k, v in cap.frames.items()
              if (k[0] == "ambient" or k[0] in patterns) and (parallel or k[1] == "cross")}
    scale = albedo_scale_from_radiometry([cap.value_per_radiance] * 3, leds, eta=ETA)
    return compute_maps(frames, albedo_scale=scale, lut=lut or lut0, eta=ETA,
                        view_dirs=np.nan_to_num(cap.view_dirs),
                        geometry_normals=np.nan_to_num(cap.normals) if geometry else None, object_mask=cap.hit,
                        **kw)


def assert_nan_exactly_where_unknown(maps: GradientMaps) -> None:
    unk = maps.unknown
    for arr in (maps.albedo, maps.diffuse_vectors, maps.diffuse_normals):
        assert not np.isinf(arr).any()
        nan = np.isnan(arr) if arr.ndim == 3 else np.isnan(arr).any(-1)
        assert np.array_equal(nan, unk)
    assert np.isfinite(maps.diffuse_vectors[~unk]).all()
    if maps.consistency is not None:
        assert np.array_equal(np.isnan(maps.consistency), unk)


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    c = np.sum(a * b, -1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


@pytest.fixture(scope="module")
def marble(rig):
    """All seven patterns, both polarizations, noisy: the shared scene of several tests."""
    return sphere_capture(rig, MARBLE, seed=1)


# ---------------------------------------------------------------------------------------------------------------
def test_complements_and_full_on_give_the_same_maps(rig, marble) -> None:
    """(full, x, y, z), (x, y, z, x_c, y_c, z_c) and all seven frames describe the same surface: the maps agree
    within the noise. Bias: the median difference of albedo and |v|/tau must lie within 3 standard errors of a
    median (1.25 x robust SD / sqrt(n), from the differences themselves) + 2e-4; the mean diffuse normals within
    0.2 deg (measured <= 0.08 deg); per pixel, the RMS angle (noise of the other frames, ~1.5 deg) below 3 deg."""
    a = maps_from(marble, rig, ("full", "x", "y", "z"))
    b = maps_from(marble, rig, ("x", "y", "z", "x_c", "y_c", "z_c"))
    c = maps_from(marble, rig, ALL)
    for m in (a, b, c):
        assert_nan_exactly_where_unknown(m)
    known = ~a.unknown & ~b.unknown & ~c.unknown
    assert known[..., 0].sum() > 1200

    def unbiased(d: np.ndarray) -> bool:
        se = 1.2533 * 1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(d.size)
        return abs(float(np.median(d))) < 3 * se + 2e-4

    for m in (b, c):
        for ch in range(3):
            k = known[..., ch]
            assert unbiased(m.albedo[..., ch][k] / a.albedo[..., ch][k] - 1)
            assert unbiased(m.diffuse_length()[..., ch][k] - a.diffuse_length()[..., ch][k])
            na, nb = a.diffuse_normals[..., ch, :][k], m.diffuse_normals[..., ch, :][k]
            assert np.degrees(np.linalg.norm(np.mean(nb - na, axis=0))) < 0.2
            assert np.sqrt(np.mean(angle_deg(nb, na) ** 2)) < 3.0
    # the sum of a gradient and its complement is the full-on frame: the LED-mode residual is at the noise level
    assert np.nanmedian(c.consistency) < 0.02
    sa, sb = (estimate_sphere(m, radius_mm=10.0, true_normals=marble.normals).summary for m in (a, b))
    lo = np.maximum(sa.params["D_mm"].interval[:, 0], sb.params["D_mm"].interval[:, 0])
    hi = np.minimum(sa.params["D_mm"].interval[:, 1], sb.params["D_mm"].interval[:, 1])
    assert np.all(lo <= hi)  # overlapping intervals
    np.testing.assert_allclose(sa.value("D_mm"), sb.value("D_mm"), rtol=0.05)


def test_noise_never_leaks_nan_or_inf(rig, marble) -> None:
    """Noisy frames include negative values after black and ambient subtraction in the background: the
    background is masked, every known pixel is finite, the diffusion maps are NaN exactly where unknown."""
    m = maps_from(marble, rig, ALL)
    assert_nan_exactly_where_unknown(m)
    assert m.masks.background[~marble.hit].all() and not m.masks.background[ndimage.binary_erosion(marble.hit)].any()
    assert (marble.frames[("ambient", "cross")][~marble.hit] < 0).any()  # noise around the black level
    dm = estimate_sphere(m, radius_mm=10.0, true_normals=marble.normals).maps
    for f in ("D_mm", "sigma_a_per_mm", "sigma_s_prime_per_mm", "alpha_prime", "l_prime_mm", "R_d", "l_d_mm",
              "r2_mm2", "shortening", "albedo"):
        arr = getattr(dm, f)
        assert not np.isinf(arr).any() and np.array_equal(np.isnan(arr), dm.unknown), f
    assert (~dm.unknown).sum() > 3000


def test_dark_channels_are_unknown(rig) -> None:
    """Ketchup (R_d 0.164 / 0.006 / 0.002): green and blue give < 1 % of white under the full-on pattern ->
    dark, unknown, NaN (never a ratio of two noise values); red is estimated normally."""
    cap = sphere_capture(rig, KETCHUP, patterns=("full", "x", "y", "z"), polarizations=("cross",), seed=2)
    m = maps_from(cap, rig, ALL, parallel=False)
    assert_nan_exactly_where_unknown(m)
    obj = cap.hit & ~m.masks.background
    assert m.masks.dark[..., 1:][obj].all() and not m.masks.dark[..., 0][ndimage.binary_erosion(obj, iterations=2)].any()
    assert np.isnan(m.albedo[..., 1:]).all() and np.isnan(m.diffuse_vectors[..., 1:, :]).all()
    est = estimate_sphere(m, radius_mm=10.0, true_normals=cap.normals)
    s = est.summary
    assert s.status[0] == "ok" and s.status[1:] == ("unknown", "unknown") and (s.n_pixels[1:] == 0).all()
    assert np.isnan(s.value("D_mm")[1:]).all() and np.isnan(est.maps.D_mm[..., 1:]).all()
    assert s.value("R_d")[0] == pytest.approx(total_diffuse_reflectance(0.18, 0.061, ETA), rel=0.01)


def test_saturated_highlights_are_masked(rig) -> None:
    """The point-LED highlights of the parallel frames clip at the white level (and, with a longer exposure, the
    brightest diffuse pixels of some channels): exactly those pixel-channels are 'saturated' and unknown; the rest
    of the sphere keeps its values (albedo as in an unsaturated cross-polarized capture within 0.5 %)."""
    hot = sphere_capture(rig, MARBLE, patterns=("full", "x", "y", "z"), exposure_s=0.028, seed=3)
    ref = sphere_capture(rig, MARBLE, patterns=("full", "x", "y", "z"), exposure_s=0.014, seed=4,
                         polarizations=("cross",))
    m = maps_from(hot, rig, ALL)
    assert_nan_exactly_where_unknown(m)
    clipped = np.zeros(hot.hit.shape + (3,), bool)
    for k, f in hot.frames.items():
        clipped |= f >= 0.98
    assert clipped.any() and np.array_equal(m.masks.saturated, clipped)
    assert m.unknown[clipped].all() and np.isnan(m.albedo[clipped]).all()
    r = maps_from(ref, rig, ALL, parallel=False)
    assert not r.masks.saturated.any()
    both = ~m.unknown & ~r.unknown
    for c in range(3):
        assert np.median(m.albedo[..., c][both[..., c]] / r.albedo[..., c][both[..., c]] - 1) == \
            pytest.approx(0, abs=5e-3)
    # a saturated channel does not take the others with it
    only_red = clipped[..., 0] & ~clipped[..., 1] & ~clipped[..., 2]
    if only_red.any():
        assert (~m.unknown[..., 1][only_red]).any()


def test_grazing_pixels_are_masked_and_the_exit_fresnel_stays_bounded(rig, marble) -> None:
    """n.v < cos 70 deg is masked (the exit transmittance F_t(n.v) -> 0 there, dividing by it would explode);
    just inside (55-70 deg) the albedo is still right within 1 % (median) and finite everywhere."""
    m = maps_from(marble, rig, ("full", "x", "y", "z"))
    cosv = np.sum(np.nan_to_num(marble.normals) * np.nan_to_num(marble.view_dirs), -1)
    graz = marble.hit & (cosv < np.cos(np.radians(70.0)) - 1e-6)
    assert graz.sum() > 100 and m.masks.grazing[graz].all() and np.isnan(m.albedo[graz]).all()
    near = marble.hit & (cosv >= np.cos(np.radians(70.0))) & (cosv < np.cos(np.radians(55.0)))
    near &= ~m.unknown[..., 0]
    assert near.sum() > 100
    est = estimate_sphere(m, radius_mm=10.0, true_normals=marble.normals)
    ref = est.summary.value("albedo")
    for c in range(3):
        assert np.isfinite(m.albedo[..., c][near]).all()
        assert np.median(m.albedo[..., c][near]) == pytest.approx(ref[c], rel=0.01)
    assert est.maps.unknown[graz].all()


def test_seed_estimate_with_nz_to_zero_is_unknown_not_huge(rig, marble) -> None:
    """The seed's D = k R_d/|n_z| with n_z taken along the view direction (no normals given): towards the limb the
    diffuse normal turns away from the camera and n_z -> 0. Pixels with |n_z| < nz_floor are unknown; every
    reported D is finite and at most k R_d / nz_floor."""
    m = maps_from(marble, rig, ("full", "x", "y", "z"), grazing_deg=89.0)  # keep the limb to reach n_z -> 0
    cal = calibrate_k(m, 1.0 / (3.0 * (np.array(MARBLE[0]) + np.array(MARBLE[1]))),
                      region=ndimage.binary_erosion(marble.hit, iterations=2))
    seed = diffusion_seed(m, cal.k_mm, cal.provenance, nz_floor=0.05)
    nz = np.abs(seed.n_z)
    small = ~m.unknown & (np.abs(np.sum(m.diffuse_vectors * marble.view_dirs[..., None, :], -1)) / m.tau_ratio
                          < 0.05)
    assert small.any() and seed.unknown[small].all() and np.isnan(seed.D_mm[small]).all()
    assert not np.isinf(seed.D_mm).any() and np.array_equal(np.isnan(seed.D_mm), seed.unknown)
    assert np.all(nz[~seed.unknown] >= 0.05)
    bound = cal.k_mm * m.albedo / 0.05
    assert np.all(seed.D_mm[~seed.unknown] <= bound[~seed.unknown] * (1 + 1e-5))


def test_flat_regions_give_unknown_diffusion(rig) -> None:
    """A flat slab (no relief) under the LEDs: the maps are fine (albedo = half-space R_d, diffuse normals = the
    plane normal), but a flat region carries no information about a length (science.md sec. 4): the curvature
    from the normal map is 0, every diffusion value is unknown (NaN) and the summary says so."""
    pos, inten, pats, leds, _ = rig
    ssp, sa = SKIN2
    cam = PinholeCamera.looking_at(width_px=40, height_px=40, fx_px=2000.0 / 0.25, position_mm=(0.0, -2000.0, 0.0),
                                   target_mm=(0.0, 0.0, 0.0))
    slab = BumpySlabObject((0.0, 0.0, 0.0), ssp, sa, ETA, extent_mm=40.0, patch_mm=0.4, rms_slope=0.0)
    cap = render_gradient_capture(slab, cam, pos, inten, {p: pats[p] for p in ("full", "x", "y", "z")},
                                  polarizations=("cross",), exposure_s=0.02, sensor=SENSOR,
                                  rng=np.random.default_rng(5))
    m = maps_from(cap, rig, ALL, parallel=False, lut=build_response_lut(leds, eta=ETA, size=33))
    assert_nan_exactly_where_unknown(m)
    assert not m.unknown.any()
    np.testing.assert_allclose(np.median(m.albedo.reshape(-1, 3), 0), total_diffuse_reflectance(ssp, sa, ETA),
                               rtol=0.01)
    mean_n = np.mean(m.diffuse_normals.reshape(-1, 3, 3), axis=0)  # per-pixel noise ~1-2 deg averages out
    assert np.all(angle_deg(mean_n, np.array([0.0, -1.0, 0.0])) < 0.3)
    k2 = curvature_sq_from_normals(cap.normals, cap.points_mm)
    assert np.nanmax(np.abs(k2)) < 1e-9
    dm = estimate_diffusion(m, cap.normals, curvature_sq_per_mm2=k2)
    assert dm.unknown.all() and np.isnan(dm.D_mm).all() and np.isnan(dm.sigma_a_per_mm).all()
    assert summarize(dm).status == ("unknown",) * 3
    with pytest.raises(ValueError):
        estimate_diffusion(m, cap.normals)  # no geometry at all: refuse rather than invent a length
