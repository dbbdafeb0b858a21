"""Tests for estimation.gradients: synthesize gradient frames of a sphere of known normals and recover the maps.

Oracles: the continuous closed forms of Ma et al. 2007 / science.md sec. 3 (v = (tau1/tau0) n, tau1/tau0 = 0.685
at eta 1.3), and a direct per-LED sum for a flat (unblurred) Fresnel-Lambertian surface.
"""
from __future__ import annotations

import enum

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import SphericalVoronoi

from estimation.fresnel import fresnel_transmittance
from estimation.gradients import (GRADIENT_PATTERNS, LedRig, albedo_scale_from_lambertian,
                                  albedo_scale_from_radiometry, build_response_lut, compute_maps, frame_key,
                                  oct_decode, oct_encode, tau_ratio)

ETA = 1.3


# ---------------------------------------------------------------------------------------------------------------
# synthetic scenes
# ---------------------------------------------------------------------------------------------------------------
def geodesic(freq: int) -> np.ndarray:
    """Vertices of a frequency-``freq`` geodesic icosphere (10 freq^2 + 2 unit vectors)."""
    t = (1 + 5 ** 0.5) / 2
    V = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
                  [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    F = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
         [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11],
         [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    pts = []
    for a, b, c in F:
        for i in range(freq + 1):
            for j in range(freq + 1 - i):
                pts.append((i * V[a] + j * V[b] + (freq - i - j) * V[c]) / freq)
    P = np.asarray(pts)
    P /= np.linalg.norm(P, axis=1, keepdims=True)
    return np.unique(np.round(P, 9), axis=0)


def solid_angles(d: np.ndarray) -> np.ndarray:
    """Voronoi solid angle of each direction on the unit sphere (sums to 4 pi)."""
    return SphericalVoronoi(d).calculate_areas()


def sphere_normals(size: int, margin: float = 1.08) -> np.ndarray:
    """Orthographic view of a unit sphere from the rig's camera side (-y): (size, size, 3), NaN off the sphere."""
    yy, xx = np.mgrid[0:size, 0:size]
    u = (xx - size / 2 + 0.5) / (size / 2) * margin
    w = -(yy - size / 2 + 0.5) / (size / 2) * margin
    r2 = u * u + w * w
    n = np.full((size, size, 3), np.nan)
    hit = r2 < 1
    n[hit, 0], n[hit, 2], n[hit, 1] = u[hit], w[hit], -np.sqrt(1 - r2[hit])
    return n


VIEW = np.array([0.0, -1.0, 0.0])


def flat_led_frames(n: np.ndarray, leds: LedRig, rho: np.ndarray, *, value_scale: float = 1.0,
                    render_patterns: dict | None = None, ambient: float = 0.0) -> dict:
    """Cross-polarized frames of a flat-response (unblurred) Fresnel-Lambertian surface of R_d = rho, lit by
    ``leds``, in the albedo convention of estimation.gradients with albedo_scale = 1/value_scale."""
    hit = np.isfinite(n).all(-1)
    nn = np.where(hit[..., None], n, 0.0).reshape(-1, 3)
    cos = nn @ leds.directions.T
    k = fresnel_transmittance(ETA, np.clip(cos, 0, 1)) * np.clip(cos, 0, None)
    ref = (fresnel_transmittance(ETA, np.clip(leds.directions @ VIEW, 0, 1)) * np.clip(leds.directions @ VIEW, 0,
                                                                                          None)) @ leds.gains
    ft_out = fresnel_transmittance(ETA, np.clip(-nn[:, 1], 0, 1))
    frames = {"ambient": np.full(n.shape[:2] + (3,), ambient, np.float32)}
    for p in GRADIENT_PATTERNS:
        vals = (render_patterns or {}).get(p, leds.pattern_values(p))
        e = (k @ (leds.gains * vals)) / ref
        img = value_scale * rho * e * ft_out[:, None]
        img = np.where(hit.reshape(-1, 1), img, 0.0).reshape(n.shape[:2] + (3,)) + ambient
        frames[p] = img.astype(np.float32)
    return frames


def continuous_frames(n: np.ndarray, rho: np.ndarray, *, value_scale: float = 1.0) -> dict:
    """Frames under ideal continuous gradients: I_P = rho F_t(n.v) E_P(n)/E_full with E_i = (tau0 + tau1 n_i)/2."""
    tau = tau_ratio(ETA)
    hit = np.isfinite(n).all(-1)
    nn = np.where(hit[..., None], n, 0.0)
    ft_out = fresnel_transmittance(ETA, np.clip(-nn[..., 1], 0, 1))[..., None]
    frames = {"ambient": np.zeros(n.shape[:2] + (3,), np.float32)}
    base = value_scale * rho * ft_out * hit[..., None]
    frames["full"] = base.astype(np.float32)
    for i, a in enumerate("xyz"):
        frames[a] = (base * 0.5 * (1 + tau * nn[..., i:i + 1])).astype(np.float32)
        frames[a + "_c"] = (base * 0.5 * (1 - tau * nn[..., i:i + 1])).astype(np.float32)
    return frames


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    c = np.sum(a * b, axis=-1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
    return np.degrees(np.arccos(np.clip(c, -1, 1)))


@pytest.fixture(scope="module")
def rig() -> tuple[LedRig, object]:
    """~200 LEDs on a geodesic sphere without its bottom cap, uneven gains (10 %), and its response LUT."""
    rng = np.random.default_rng(7)
    d = geodesic(5)
    d = d[d[:, 2] > -0.6]
    gains = (4 * np.pi / len(d)) * (1 + 0.1 * rng.standard_normal((len(d), 3)))
    leds = LedRig(d, gains)
    return leds, build_response_lut(leds, eta=ETA, size=33)


# ---------------------------------------------------------------------------------------------------------------
# conventions and helpers
# ---------------------------------------------------------------------------------------------------------------
def test_tau_ratio_known_values() -> None:
    assert tau_ratio(1.3) == pytest.approx(0.685, abs=5e-4)
    assert tau_ratio(1.5) == pytest.approx(0.688, abs=1e-3)
    assert tau_ratio(1.0) == pytest.approx(2 / 3, abs=1e-9)


def test_frame_key_convention() -> None:
    class Pol(enum.IntEnum):
        CROSS = 2
        PARALLEL = 1

    assert frame_key("x") == ("x", "cross")
    assert frame_key(("z_c", "parallel")) == ("z_c", "parallel")
    assert frame_key(("full", Pol.PARALLEL)) == ("full", "parallel")
    assert frame_key(("ambient", Pol.CROSS)) == ("ambient", "cross")
    for bad in ["q", ("x", "circular"), ("x",), 3]:
        with pytest.raises(ValueError):
            frame_key(bad)


@settings(max_examples=200, deadline=None)
@given(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1))
def test_octahedral_roundtrip(x: float, y: float, z: float) -> None:
    v = np.array([x, y, z])
    if np.linalg.norm(v) < 1e-3:
        return
    v /= np.linalg.norm(v)
    uv = oct_encode(v)
    assert np.all(np.abs(uv) <= 1 + 1e-12)
    np.testing.assert_allclose(oct_decode(uv), v, atol=1e-12)


def test_lut_matches_continuous_limit() -> None:
    """A dense, uniform LED sphere has the ideal affine response a_x = 1/2, b_x = (tau1/tau0)/2 e_x."""
    d = geodesic(14)  # 1962 LEDs
    g = np.repeat(solid_angles(d)[:, None], 3, axis=1)
    lut = build_response_lut(LedRig(d, g), eta=ETA, size=9, smoothing_rad=0.15)
    tau = tau_ratio(ETA)
    c = lut.coeffs  # (size, size, P, 3, 4), normalized by E_full(reference)
    ix, ixc, ifull = lut.patterns.index("x"), lut.patterns.index("x_c"), lut.patterns.index("full")
    np.testing.assert_allclose(c[..., ifull, :, 0], 1.0, atol=6e-3)
    np.testing.assert_allclose(c[..., ifull, :, 1:], 0.0, atol=6e-3)
    np.testing.assert_allclose(c[..., ix, :, 0], 0.5, atol=4e-3)
    np.testing.assert_allclose(c[..., ix, :, 1], tau / 2, atol=4e-3)
    np.testing.assert_allclose(c[..., ixc, :, 1], -tau / 2, atol=4e-3)


# ---------------------------------------------------------------------------------------------------------------
# ideal (continuous) formulas
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("subset", [("full", "x", "y", "z"), ("x", "y", "z", "x_c", "y_c", "z_c"),
                                    ("full", "x", "y_c", "z", "z_c"), GRADIENT_PATTERNS])
def test_ideal_formulas_recover_normals_and_albedo(subset: tuple[str, ...]) -> None:
    n = sphere_normals(48)
    rho = np.array([0.8, 0.5, 0.3])
    fr = continuous_frames(n, rho, value_scale=0.5)
    frames = {"ambient": fr["ambient"], **{p: fr[p] for p in subset}}
    m = compute_maps(frames, albedo_scale=2.0, ideal=True, eta=ETA)
    ok = ~m.unknown
    hit = np.isfinite(n).all(-1)
    cosv = np.where(hit, -n[..., 1], -1)
    assert np.array_equal(ok[..., 0], hit & (cosv >= np.cos(np.radians(70)) - 1e-6)) or \
        abs(int(ok[..., 0].sum()) - int((hit & (cosv >= np.cos(np.radians(70)))).sum())) <= 4
    tau = tau_ratio(ETA)
    for c in range(3):
        v = m.diffuse_vectors[..., c, :][ok[..., c]]
        np.testing.assert_allclose(v, tau * n[ok[..., c]], atol=2e-6)
        np.testing.assert_allclose(m.albedo[..., c][ok[..., c]], rho[c], rtol=2e-5)
    assert np.isnan(m.albedo[~ok]).all() and np.isnan(m.diffuse_normals[~ok]).all()
    assert m.provenance["mode"] == "ideal"


def test_ideal_mode_consistency_map_flags_mismatched_complements() -> None:
    n = sphere_normals(32)
    fr = continuous_frames(n, np.array([0.6, 0.6, 0.6]))
    m = compute_maps(fr, albedo_scale=1.0, ideal=True)
    assert np.nanmax(m.consistency) < 1e-5
    fr["y_c"] = fr["y_c"] * 1.05  # a drifting exposure on one frame
    m2 = compute_maps(fr, albedo_scale=1.0, ideal=True)
    assert np.nanmedian(m2.consistency) > 0.01


def test_exposures_are_normalized() -> None:
    n = sphere_normals(24)
    fr = continuous_frames(n, np.array([0.6, 0.4, 0.2]), value_scale=0.3)
    ref = compute_maps(fr, albedo_scale=1 / 0.3, ideal=True)
    expo = {k: (2.0 if k in ("x", "y_c") else 1.0) for k in fr}
    doubled = {k: v * expo[k] for k, v in fr.items()}
    m = compute_maps(doubled, albedo_scale=1 / 0.3, ideal=True, exposure_s=expo)
    np.testing.assert_allclose(m.diffuse_vectors, ref.diffuse_vectors, atol=1e-6, equal_nan=True)
    np.testing.assert_allclose(m.albedo, ref.albedo, rtol=1e-6, equal_nan=True)
    with pytest.raises(ValueError, match="exposure"):
        compute_maps(doubled, albedo_scale=1.0, ideal=True, exposure_s={"x": 2.0})


def test_tiles_do_not_change_the_result(rig) -> None:
    leds, lut = rig
    n = sphere_normals(40)
    fr = flat_led_frames(n, leds, np.array([0.7, 0.4, 0.2]), value_scale=0.5)
    a = compute_maps(fr, albedo_scale=2.0, lut=lut, tile_rows=256)
    b = compute_maps(fr, albedo_scale=2.0, lut=lut, tile_rows=7)
    np.testing.assert_array_equal(a.unknown, b.unknown)
    np.testing.assert_allclose(a.diffuse_vectors, b.diffuse_vectors, rtol=0, atol=1e-7, equal_nan=True)
    np.testing.assert_allclose(a.albedo, b.albedo, rtol=1e-7, equal_nan=True)


# ---------------------------------------------------------------------------------------------------------------
# discrete LEDs
# ---------------------------------------------------------------------------------------------------------------
def _errors(m, n: np.ndarray, rho: np.ndarray, sel: np.ndarray | None = None):
    ok = ~m.unknown
    if sel is not None:
        ok &= sel[..., None]
    length = m.diffuse_length()
    out = []
    for c in range(3):
        o = ok[..., c]
        out.append((np.max(np.abs(length[..., c][o] - 1)), np.max(angle_deg(m.diffuse_normals[..., c, :][o], n[o])),
                    np.max(np.abs(m.albedo[..., c][o] / rho[c] - 1)), int(o.sum())))
    return out


@pytest.mark.parametrize("subset", [GRADIENT_PATTERNS, ("full", "x", "y", "z"), ("x", "y", "z", "x_c", "y_c", "z_c")])
def test_led_correction_removes_discreteness_bias(rig, subset) -> None:
    leds, lut = rig
    n = sphere_normals(64)
    rho = np.array([0.8, 0.5, 0.3])
    fr = flat_led_frames(n, leds, rho, value_scale=0.5)
    frames = {"ambient": fr["ambient"], **{p: fr[p] for p in subset}}
    up = np.nan_to_num(n[..., 2], nan=-1) > -0.3  # away from the missing bottom cap
    m = compute_maps(frames, albedo_scale=2.0, lut=lut, eta=ETA)
    for dlen, dang, dalb, count in _errors(m, n, rho, up):
        assert count > 1500
        assert dlen < 4e-3 and dang < 0.8 and dalb < 4e-3
    # the same frames through the continuous formulas are visibly biased (uneven gains, missing cap)
    mi = compute_maps(frames, albedo_scale=2.0, ideal=True, eta=ETA)
    dlen_i, dang_i, dalb_i, _ = _errors(mi, n, rho, up)[0]
    assert dlen_i > 0.02 and dalb_i > 0.02


def test_displayed_pattern_values_are_used(rig) -> None:
    """The LUT must be built from what the sphere displayed (here 6-bit quantized drive values)."""
    leds, _ = rig
    q = {p: np.round(leds.pattern_values(p) * 63) / 63 for p in GRADIENT_PATTERNS}
    n = sphere_normals(48)
    rho = np.array([0.6, 0.6, 0.6])
    fr = flat_led_frames(n, leds, rho, render_patterns=q)
    up = np.nan_to_num(n[..., 2], nan=-1) > -0.3
    good = LedRig(leds.directions, leds.gains, patterns=q)
    m_good = compute_maps(fr, albedo_scale=1.0, lut=build_response_lut(good, eta=ETA, size=33))
    m_bad = compute_maps(fr, albedo_scale=1.0, lut=build_response_lut(leds, eta=ETA, size=33))
    e_good = _errors(m_good, n, rho, up)[0]
    e_bad = _errors(m_bad, n, rho, up)[0]
    assert e_good[0] < 4e-3 and e_good[1] < 0.8
    assert e_bad[0] > 2 * e_good[0]


def test_near_field_leds_with_surface_model() -> None:
    """Point LEDs at 1 m around a 10 mm sphere: directions and 1/d^2 change over the object; modelled exactly."""
    d = geodesic(5)
    pos = d * 1000.0
    leds = LedRig.from_positions(pos, np.full((len(d), 3), 1e6))
    rho_mm = 10.0
    n = sphere_normals(48)
    hit = np.isfinite(n).all(-1)
    nn = np.where(hit[..., None], n, 0.0).reshape(-1, 3)
    x = rho_mm * nn
    vec = pos[None] - x[:, None]
    dist2 = np.sum(vec * vec, -1)
    cos = np.einsum("mjk,mk->mj", vec, nn) / np.sqrt(dist2)
    k = fresnel_transmittance(ETA, np.clip(cos, 0, 1)) * np.clip(cos, 0, None) / dist2 * 1e6
    ref = (fresnel_transmittance(ETA, np.clip(d @ VIEW, 0, 1)) * np.clip(d @ VIEW, 0, None)) @ leds.gains
    ft_out = fresnel_transmittance(ETA, np.clip(-nn[:, 1], 0, 1))
    fr = {"ambient": np.zeros((48, 48, 3), np.float32)}
    for p in GRADIENT_PATTERNS:
        e = (k @ leds.pattern_values(p)) / ref
        fr[p] = np.where(hit[..., None], (0.5 * e * ft_out[:, None]).reshape(48, 48, 3), 0).astype(np.float32)
    near = compute_maps(fr, albedo_scale=1.0, leds=leds, lut_size=33, surface_radius_mm=rho_mm)
    far = compute_maps(fr, albedo_scale=1.0, leds=leds, lut_size=33, surface_radius_mm=0.0)
    # inside a uniformly bright sphere the full-on irradiance does not depend on position, but the gradients
    # seen from x != 0 are distorted: |v| grows by ~0.7 % at 10 mm / 1 m, as large as a blue shortening signal
    assert np.nanmax(np.abs(near.albedo[..., 0] / 0.5 - 1)) < 2e-3
    assert np.nanmax(np.abs(near.diffuse_length() - 1)) < 1e-3
    assert np.nanmedian(far.diffuse_length()) - 1 > 5e-3


# ---------------------------------------------------------------------------------------------------------------
# masks and robustness
# ---------------------------------------------------------------------------------------------------------------
def test_masks_dark_saturated_grazing_background_nonfinite(rig) -> None:
    leds, lut = rig
    n = sphere_normals(48)
    rho = np.array([0.164, 0.006, 0.002])  # ketchup at eta 1.3: green and blue are nearly black
    fr = flat_led_frames(n, leds, rho, value_scale=0.5, ambient=0.002)
    fr["x"][24, 24, 0] = 0.99  # saturated red only
    fr["y"][20, 20, 1] = np.nan  # a corrupt value
    obj = np.ones((48, 48), bool)
    obj[:, :3] = False
    m = compute_maps(fr, albedo_scale=2.0, lut=lut, object_mask=obj, dark_threshold=0.01)
    hit = np.isfinite(n).all(-1)
    assert m.masks.background[~hit].all() and m.masks.background[:, :3].all()
    assert m.masks.dark[..., 1:][hit & ~m.masks.background].all()  # green, blue: unknown, never inf
    assert np.isnan(m.albedo[..., 1:]).all() and not np.isinf(m.diffuse_vectors).any()
    assert m.masks.saturated[24, 24, 0] and not m.masks.saturated[24, 24, 1]
    assert m.unknown[24, 24, 0] and np.isnan(m.albedo[24, 24, 0])
    assert m.masks.inconsistent[20, 20, 1]
    cosv = np.where(hit, -np.nan_to_num(n[..., 1]), 1.0)
    graz = hit & ~m.masks.background & (cosv < np.cos(np.radians(70)) - 0.02)
    assert m.masks.grazing[graz].all()
    red_ok = ~m.unknown[..., 0]
    assert red_ok.sum() > 900
    np.testing.assert_allclose(m.albedo[..., 0][red_ok], 0.164, rtol=1e-2)  # incl. normals near the missing cap


def test_noise_is_unbiased_in_median(rig) -> None:
    leds, lut = rig
    n = sphere_normals(64)
    rho = np.array([0.8, 0.5, 0.3])
    fr = flat_led_frames(n, leds, rho, value_scale=0.45, ambient=0.01)
    rng = np.random.default_rng(3)
    e_per_unit = 16383 * 2.0  # 14-bit, 2 e-/DN
    for k, a in fr.items():
        electrons = rng.poisson(np.clip(a, 0, None) * e_per_unit) / e_per_unit
        fr[k] = (electrons + rng.normal(0, 2 / 16383, a.shape)).astype(np.float32)
    up = np.nan_to_num(n[..., 2], nan=-1) > -0.3
    m = compute_maps(fr, albedo_scale=1 / 0.45, lut=lut)
    ok = ~m.unknown & up[..., None]
    length = m.diffuse_length()
    for c in range(3):
        assert np.median(length[..., c][ok[..., c]]) == pytest.approx(1.0, abs=2e-3)
        assert np.median(m.albedo[..., c][ok[..., c]]) == pytest.approx(rho[c], rel=3e-3)
        diff = m.diffuse_normals[..., c, :][ok[..., c]] - n[ok[..., c]]
        assert np.linalg.norm(np.mean(diff, axis=0)) < 3e-3  # per-pixel angular noise is ~2 deg, bias is not


def test_specular_maps_from_parallel_frames() -> None:
    """Parallel = cross + a polarization-preserving mirror-like lobe: specular normal = halfway(r, v)."""
    n = sphere_normals(48)
    hit = np.isfinite(n).all(-1)
    nn = np.where(hit[..., None], n, 0.0)
    fr = continuous_frames(n, np.array([0.5, 0.5, 0.5]), value_scale=0.5)
    r = 2 * np.sum(nn * VIEW, -1, keepdims=True) * nn - VIEW  # mirror direction of the view vector
    rho_s = np.array([0.04, 0.05, 0.06])
    frames = {("ambient", "cross"): fr["ambient"], ("ambient", "parallel"): fr["ambient"]}
    for p in ("full", "x", "y", "z", "x_c", "y_c", "z_c"):
        if p == "full":
            val = np.ones(n.shape[:2])
        else:
            i = "xyz".index(p[0])
            val = 0.5 * (1 - r[..., i]) if p.endswith("_c") else 0.5 * (1 + r[..., i])
        spec = 2 * rho_s * val[..., None] / 2.0 * hit[..., None]  # albedo_scale = 2: S_full = 2 rho_s / scale
        frames[(p, "cross")] = fr[p]
        frames[(p, "parallel")] = (fr[p] + spec).astype(np.float32)
    m = compute_maps(frames, albedo_scale=2.0, ideal=True)
    ok = ~m.specular_unknown & ~m.masks.grazing & hit
    assert ok.sum() > 1000
    assert np.max(angle_deg(m.specular_normals[ok], n[ok])) < 0.05  # float32 frames
    np.testing.assert_allclose(m.specular_albedo[ok], np.broadcast_to(rho_s, (int(ok.sum()), 3)), rtol=1e-4)
    # the diffuse maps are untouched by the parallel frames
    np.testing.assert_allclose(m.diffuse_length()[~m.unknown], 1.0, atol=1e-5)


def test_albedo_scale_helpers_are_consistent(rig) -> None:
    leds, lut = rig
    # a Lambertian reference (R = 0.99) facing the camera at the origin, under the LED sphere
    cos = np.clip(leds.directions @ VIEW, 0, None)
    E_plain = cos @ leds.gains
    E_t = (fresnel_transmittance(ETA, cos) * cos) @ leds.gains
    k = 0.37  # frame units per unit radiance (cross-polarized: half of the depolarized diffuse light)
    signal_ref = k * 0.5 * 0.99 * E_plain / np.pi
    s1 = albedo_scale_from_lambertian(signal_ref, [0.99] * 3, eta=ETA, leds=leds)
    s2 = albedo_scale_from_radiometry([k] * 3, leds, eta=ETA)
    np.testing.assert_allclose(s1, s2, rtol=1e-12)
    # a translucent flat patch of R_d = 0.5 facing the camera gives I = k/2 F_t(1) R_d E_t / pi -> albedo 0.5
    n = sphere_normals(32)
    fr = flat_led_frames(n, leds, np.full(3, 0.5), value_scale=k * 0.5 * E_t[0] / np.pi)
    m = compute_maps(fr, albedo_scale=s2, lut=lut)
    centre = m.albedo[15:17, 15:17, 0]
    np.testing.assert_allclose(centre, 0.5, rtol=2e-3)
    # continuous light: E_t/E = tau0/pi
    s3 = albedo_scale_from_lambertian([1.0] * 3, [1.0] * 3, eta=1.0)
    np.testing.assert_allclose(s3, 1.0, rtol=1e-9)


def test_input_validation() -> None:
    n = sphere_normals(8)
    fr = continuous_frames(n, np.array([0.5, 0.5, 0.5]))
    with pytest.raises(ValueError, match="leds"):
        compute_maps(fr, albedo_scale=1.0)
    no_amb = {k: v for k, v in fr.items() if k != "ambient"}
    with pytest.raises(ValueError, match="ambient"):
        compute_maps(no_amb, albedo_scale=1.0, ideal=True)
    with pytest.raises(ValueError, match="axis"):
        compute_maps({"ambient": fr["ambient"], "x": fr["x"], "y": fr["y"], "full": fr["full"]}, albedo_scale=1.0,
                     ideal=True)
    with pytest.raises(ValueError, match="shape"):
        compute_maps({**fr, "x": fr["x"][:4]}, albedo_scale=1.0, ideal=True)
    with pytest.raises(ValueError, match="albedo_scale"):
        compute_maps(fr, albedo_scale=[1.0, 0.0, 1.0], ideal=True)
    with pytest.raises(ValueError):
        LedRig(np.zeros((3, 3)), np.ones((3, 3)))
    with pytest.raises(ValueError):
        LedRig(np.eye(3), np.ones((3, 3)), patterns={"w": np.ones(3)})


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2 ** 32 - 1), st.booleans())
def test_garbage_frames_give_nan_or_finite_never_inf(seed: int, ideal: bool) -> None:
    """Arbitrary values (negative, zero, NaN, inf, saturated) never raise and never produce inf."""
    rng = np.random.default_rng(seed)
    choices = np.array([0.0, -0.1, 1e-9, 0.3, 0.99, 1.5, np.nan, np.inf, -np.inf])
    frames = {}
    for p in ("ambient",) + GRADIENT_PATTERNS:
        a = rng.uniform(-0.05, 1.0, (6, 5, 3))
        junk = rng.random(a.shape) < 0.3
        a[junk] = rng.choice(choices, size=int(junk.sum()))
        frames[p] = a.astype(np.float32)
    d = geodesic(2)
    m = compute_maps(frames, albedo_scale=1.0, ideal=ideal, leds=None if ideal else LedRig(d, np.ones((len(d), 3))),
                     lut_size=9)
    for arr in (m.albedo, m.diffuse_vectors, m.diffuse_normals):
        assert not np.isinf(arr).any()
        assert np.array_equal(np.isnan(arr).reshape(6, 5, 3, -1).any(-1), m.unknown)


# ---------------------------------------------------------------------------------------------------------------
# large frames: memory maps in, memory maps out, bounded working memory
# ---------------------------------------------------------------------------------------------------------------
def test_memory_mapped_outputs_equal_in_memory_results(rig, tmp_path) -> None:
    """Frames as .npy memory maps, outputs written tile by tile into memory maps (out_dir): the same numbers as the
    in-RAM path, readable back from the files; a float32 view_dirs map is kept by reference, not copied."""
    leds, lut = rig
    n = sphere_normals(40)
    fr = flat_led_frames(n, leds, np.array([0.7, 0.4, 0.2]), value_scale=0.5, ambient=0.003)
    mm = {}
    for k, a in fr.items():
        mm[k] = np.lib.format.open_memmap(tmp_path / f"in_{k}.npy", "w+", np.float32, a.shape)
        mm[k][...] = a
    view = np.lib.format.open_memmap(tmp_path / "view.npy", "w+", np.float32, (40, 40, 3))
    view[...] = VIEW
    ram = compute_maps(fr, albedo_scale=2.0, lut=lut, view_dirs=np.array(view), tile_rows=9)
    out = compute_maps(mm, albedo_scale=2.0, lut=lut, view_dirs=view, tile_rows=9, out_dir=tmp_path / "maps")
    for name in ("albedo", "diffuse_vectors", "consistency"):
        a, b = getattr(ram, name), getattr(out, name)
        assert isinstance(b, np.memmap)
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(np.load(tmp_path / "maps" / f"{name}.npy"), a)
    # diffuse_normals is derived on access (not written), bit-identical to normalizing the stored vectors
    assert not (tmp_path / "maps" / "diffuse_normals.npy").exists()
    assert "diffuse_normals" in out.provenance["derived"] and "diffuse_vectors" in out.provenance["stored"]
    np.testing.assert_array_equal(np.asarray(ram.diffuse_normals), np.asarray(out.diffuse_normals))
    v = np.asarray(out.diffuse_vectors)
    with np.errstate(invalid="ignore"):
        np.testing.assert_array_equal(np.asarray(out.diffuse_normals),
                                      v / np.sqrt(v[..., 0] ** 2 + v[..., 1] ** 2 + v[..., 2] ** 2)[..., None])
    # partial reads select first, then normalize: every key form gives the same as the full map
    full = np.asarray(out.diffuse_normals)
    k = ~out.unknown[..., 1]
    for key in ((..., 1, slice(None)), (slice(3, 9),), (slice(None), slice(None), 2, 0), (k,), (5, 7, 1),
                (..., 2)):
        np.testing.assert_array_equal(out.diffuse_normals[key], full[key])
    np.testing.assert_array_equal(ram.unknown, out.unknown)
    assert np.load(tmp_path / "maps" / "mask_background.npy").shape == (40, 40)
    assert out.view_dirs is view and out.provenance["storage"].startswith("memory maps")
    # the default view direction is a zero-stride view, not a frame-sized copy
    assert ram.view_dirs.strides[:2] == (0, 0) or np.shares_memory(ram.view_dirs, view) is False


def test_working_memory_is_bounded_by_the_tile(rig, tmp_path) -> None:
    """With memory-mapped frames and out_dir, the numpy memory allocated during compute_maps (tracemalloc: numpy
    registers its buffers) stays far below the frame set (92 MB here): blocks of 16384 pixels (~20 MB of
    temporaries with all seven patterns) per worker thread, never a frame-sized array."""
    import tracemalloc

    leds, lut = rig
    H, W = 800, 1200
    small = flat_led_frames(sphere_normals(400), leds, np.array([0.6, 0.5, 0.4]), value_scale=0.5, ambient=0.002)
    mm = {}
    for k, a in small.items():
        mm[k] = np.lib.format.open_memmap(tmp_path / f"{k}.npy", "w+", np.float32, (H, W, 3))
        mm[k][...] = np.tile(a, (2, 3, 1))
    frame_set = len(mm) * H * W * 3 * 4
    compute_maps({k: v[:8] for k, v in mm.items()}, albedo_scale=2.0, lut=lut)  # solve table built and cached
    peaks = {}
    for workers in (1, 2):  # each worker thread holds one block's temporaries
        tracemalloc.start()
        m = compute_maps(mm, albedo_scale=2.0, lut=lut, tile_rows=64, out_dir=tmp_path / "maps", workers=workers)
        peaks[workers] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert (~m.unknown).sum() > 0.5 * H * W
        assert m.provenance["workers"] == workers
    assert peaks[1] < 0.25 * frame_set, (peaks, frame_set)
    assert peaks[2] < 2 * 0.25 * frame_set, (peaks, frame_set)


def test_workers_and_skipping_consistency_do_not_change_the_maps(rig) -> None:
    """Threads over tiles write disjoint rows: any worker count gives identical maps; consistency=False leaves out
    only the diagnostic residual map (what ``rig estimate gradients`` and the benchmark run)."""
    leds, lut = rig
    n = sphere_normals(40)
    fr = flat_led_frames(n, leds, np.array([0.7, 0.4, 0.2]), value_scale=0.5, ambient=0.003)
    a = compute_maps(fr, albedo_scale=2.0, lut=lut, tile_rows=7, workers=1)
    b = compute_maps(fr, albedo_scale=2.0, lut=lut, tile_rows=7, workers=2, consistency=False)
    assert a.consistency is not None and b.consistency is None
    assert "consistency" not in b.provenance["stored"] and b.provenance["workers"] == 2
    for name in ("albedo", "diffuse_vectors"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    np.testing.assert_array_equal(a.unknown, b.unknown)
    with pytest.raises(ValueError, match="workers"):
        compute_maps(fr, albedo_scale=2.0, lut=lut, workers=0)
