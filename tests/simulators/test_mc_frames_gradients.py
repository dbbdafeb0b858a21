"""The gradient estimators on Monte Carlo frames (issue 8, item 5), and the Monte Carlo / dipole brightness ratio.

Frames: ``render_gradient_capture(..., render_mode="mc")`` -- the same rig (362 LEDs at 1 m, ideal full/x/y/z
drive), the same camera, the subsurface light by Monte Carlo random walks (``simulators.mc_capture``; the lit
LEDs as a distant piecewise-constant radiance map, all patterns with the same seed). Sensor noise is off
(``noise=False``, expected values of the 14-bit sensor) so that the only noise is the Monte Carlo error, which
is what the tolerances are tied to. Truth: sigma_s', sigma_a of science.md sec. 2 (marble, skin1), eta 1.3;
"R_table" is the total diffuse reflectance of the Monte Carlo table (estimation.mc_table, the renderer's own
physics), "R_jensen" the dipole's.

Two effects the estimators do not model show up as *biases* and are asserted as measured (value +- several
standard deviations across Monte Carlo seeds), not hidden by wide tolerances:

1. exit normalization: the estimators convert radiance to exitance with Jensen's F_t(eta, w_o)/pi, which
   integrates to c = 1 - 2 FM1 = 0.939 at eta 1.3; transport gives ~F_t/(pi c) (docs/monte-carlo.md): +6.5 %;
2. curvature: a 10 mm sphere returns much more light than a half-space of the same material (light that would
   diffuse away or deep into a half-space comes back out of a convex body; the dipole summed over the sphere's
   surface at chord distances is the half-space profile truncated at 2 r, i.e. less, not more). Measured with the
   renderer under uniform light, skin1-R (l_d = 3.7 mm): sphere / half-space radiance 1.31 at r = 10 mm, 1.05 at
   50 mm, 1.01 at 300 mm.

Numbers and times: see each test's docstring and docs/monte-carlo.md sec. 4.
"""
from __future__ import annotations

import os
import time

import numpy as np
import pytest

from drivers.contracts import Polarization
from estimation.camera import PinholeCamera
from estimation.diffusion import estimate_sphere, fit_relief
from estimation.dipole import total_diffuse_reflectance
from estimation.gradient_correction import estimate_sphere_with_reference
from estimation.gradients import LedRig, albedo_scale_from_radiometry, build_response_lut, compute_maps
from estimation.mc_table import default_table
from rig.acquire.geometry import led_layout
from rig.estimate.reference.mc_reference import GradientsMonteCarloReference
from simulators.camera import SensorModel
from simulators.mc_capture import MCSettings, led_environment, relief_mesh
from simulators.scene import BumpySlabObject, SphereObject, render_gradient_capture, render_object

ETA = 1.3
MATERIALS = {  # science.md sec. 2 (reduced sigma_s', sigma_a in 1/mm)
    "marble": ((2.19, 2.62, 3.00), (0.0021, 0.0041, 0.0071)),
    "skin1": ((0.74, 0.88, 1.01), (0.032, 0.17, 0.48)),
}
SENSOR = SensorModel(gain_dn_per_unit=4.5e7, black_level_dn=512, white_level_dn=16383, read_noise_dn=2.0,
                     electrons_per_dn=1.5)
RADIUS_MM = 10.0
SEED = int(os.environ.get("SSSRIG_MC_SEED", "0"))   # the measured spreads below come from seeds 0-2


def truth(name: str):
    ssp, sa = (np.asarray(x, float) for x in MATERIALS[name])
    r_tab = np.asarray(default_table().total_reflectance(ssp / (ssp + sa), ETA), float)
    return ssp, sa, r_tab, total_diffuse_reflectance(ssp, sa, ETA)


@pytest.fixture(scope="module")
def rig():
    pos, _ = led_layout(6, 1000.0, -60.0)
    inten = np.full((len(pos), 3), 1000.0)
    leds = LedRig.from_positions(pos, inten)
    patterns = {name: leds.pattern_values(name)[:, 0] for name in ("full", "x", "y", "z")}  # ideal drive values
    # the Monte Carlo frames see the LEDs as distant (no near field): the LUT of a surface at the origin
    lut = build_response_lut(leds, eta=ETA, size=33)
    return pos, inten, patterns, leds, lut


def maps_of(cap, rig):
    pos, inten, patterns, leds, lut = rig
    scale = albedo_scale_from_radiometry([cap.value_per_radiance] * 3, leds, eta=ETA)
    return compute_maps(cap.frames, albedo_scale=scale, lut=lut, eta=ETA, view_dirs=np.nan_to_num(cap.view_dirs),
                        geometry_normals=np.nan_to_num(cap.normals), object_mask=cap.hit)


def angle_deg(a, b):
    c = np.sum(a * b, -1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


# ---------------------------------------------------------------------------------------------------------------
# the API
# ---------------------------------------------------------------------------------------------------------------
def test_led_environment_keeps_each_leds_irradiance(rig) -> None:
    """The distant LED map gives every LED's irradiance I/d^2 at the centre (its cell integrates to it) and is
    dark where no LED is near (below the lowest ring)."""
    pos, inten, patterns, leds, _ = rig
    env = led_environment(pos, inten * patterns["z"][:, None], rows=90)
    d, w = env.directions_and_weights()
    total = w.sum(0)
    expected = (inten * patterns["z"][:, None] / 1000.0 ** 2).sum(0)
    np.testing.assert_allclose(total, expected, rtol=1e-9)
    assert np.all(w[d[:, 2] < -0.95] == 0)
    with pytest.raises(ValueError, match="render_mode"):
        render_object(SphereObject((0, 0, 0), 10.0, (1, 1, 1), (0.1, 0.1, 0.1), ETA), sphere_camera(8),
                      pos, inten, Polarization.NONE, render_mode="exact")


def test_relief_mesh_is_closed_and_follows_the_relief() -> None:
    slab = BumpySlabObject((0.0, 0.0, 0.0), (1.0,) * 3, (0.1,) * 3, ETA, extent_mm=10.0, patch_mm=0.25, seed=3)
    m = relief_mesh(slab, 0.25, 4.0)
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    assert m.volume == pytest.approx(10.0 * 10.0 * 4.0, rel=0.01)   # the relief has zero mean height


def sphere_camera(size: int) -> PinholeCamera:
    return PinholeCamera.looking_at(width_px=size, height_px=size, fx_px=size * 20.0, position_mm=(0.0, -400.0, 0.0),
                                    target_mm=(0.0, 0.0, 0.0))


# ---------------------------------------------------------------------------------------------------------------
# item 3: Monte Carlo / fast on a sphere
# ---------------------------------------------------------------------------------------------------------------
# median over pixels with n.v >= 0.5 of MC / fast radiance, full pattern, 10 mm sphere; measured seeds 0-2
MC_OVER_FAST = {"marble": (1.179, 1.175, 1.173), "skin1": (1.440, 1.235, 1.095)}
MC_OVER_FAST_TOL = {"marble": (0.01, 0.01, 0.01), "skin1": (0.02, 0.035, 0.04)}


@pytest.mark.parametrize("name", sorted(MATERIALS))
def test_mc_over_fast_on_a_sphere(name: str, rig) -> None:
    """MC / fast radiance on a 10 mm sphere under the full pattern (16 x 16 px, 256 spp). Expected, as a product of
    measured factors: R_table / R_jensen (marble-R 1.008, skin1 1.005 / 0.937 / 0.881) x the exit normalization
    (flat half-space, uniform light, normal view: 1.066-1.071 for these materials, = 1/c within 0.6 %) x the
    curvature gain of a 10 mm sphere (skin1-R 1.31 under uniform light). Measured medians: marble 1.180 / 1.176 /
    1.174 (seeds 0-2 within 0.003), skin1 1.44 / 1.23 / 1.09 (seeds 0-2 spread 0.016 / 0.03 / 0.03: the median
    of skewed per-pixel MC ratios at 3.5-10 % stderr); allowed ~1.3-3x that spread."""
    pos, inten, patterns, _, _ = rig
    ssp, sa, _, _ = truth(name)
    obj = SphereObject((0.0, 0.0, 0.0), RADIUS_MM, tuple(ssp), tuple(sa), ETA, tessellation=4)
    cam = sphere_camera(16)
    fast = render_object(obj, cam, pos, inten, Polarization.NONE, include_specular=False)
    t0 = time.perf_counter()
    mc = render_object(obj, cam, pos, inten, Polarization.NONE, include_specular=False, render_mode="mc",
                       mc=MCSettings(spp=256, seed=SEED))
    seconds = time.perf_counter() - t0
    assert fast.stderr is None and mc.stderr is not None
    pts, hit = obj.intersect(cam)
    cos = np.sum(obj.normals_at(pts[hit]) * cam.view_directions(pts[hit]), -1)
    sel = cos >= 0.5
    ratio = np.median(mc.radiance[hit][sel] / fast.radiance[hit][sel], axis=0)
    rel_se = np.median(mc.stderr[hit][sel] / mc.radiance[hit][sel], axis=0)
    print(f"\n{name}: MC/fast median {np.round(ratio, 4)} (per-pixel MC rel. stderr {np.round(rel_se, 4)}, "
          f"{sel.sum()} px, {seconds:.1f} s)")
    assert np.all(np.abs(ratio - np.array(MC_OVER_FAST[name])) <= np.array(MC_OVER_FAST_TOL[name])), ratio


# ---------------------------------------------------------------------------------------------------------------
# spheres under the gradient patterns
# ---------------------------------------------------------------------------------------------------------------
# measured over seeds 0-2 (32 x 32 px; marble 64 spp, skin1 128 spp): median albedo map / R_table, and D / D_true
ALBEDO_BIAS = {"marble": (1.163, 1.164, 1.160), "skin1": (1.448, 1.330, 1.262)}
ALBEDO_TOL = {"marble": (0.008, 0.008, 0.008), "skin1": (0.01, 0.015, 0.02)}
NORMAL_MAX_DEG = {"marble": 3.0, "skin1": 5.5}
SPP = {"marble": 64, "skin1": 128}


def sphere_mc_capture(name: str, rig):
    """The Monte Carlo gradient capture (full + x, y, z, cross-polarized, 32 x 32 px, sensor noise off) of the
    10 mm sphere of material ``name`` at SPP[name] paths per pixel and seed SEED."""
    ssp, sa, _, _ = truth(name)
    pos, inten, patterns, _, _ = rig
    obj = SphereObject((0.0, 0.0, 0.0), RADIUS_MM, tuple(ssp), tuple(sa), ETA, tessellation=3)
    return render_gradient_capture(obj, sphere_camera(32), pos, inten, patterns, polarizations=("cross",),
                                   exposure_s=0.02, sensor=SENSOR, noise=False, render_mode="mc",
                                   mc=MCSettings(spp=SPP[name], seed=SEED))


@pytest.mark.parametrize("name", sorted(MATERIALS))
def test_sphere_gradients_on_mc_frames(name: str, rig) -> None:
    """10 mm sphere, 32 x 32 px (0.05 rad LED cells), full + x, y, z, cross-polarized; compute_maps (LED mode) and
    estimate_sphere.

    - albedo: the median of the albedo map is R_d x (exit normalization 1.066) x (curvature gain), i.e. biased
      high; asserted at the measured value (marble 1.163 / 1.164 / 1.160 x R_table, skin1 1.448 / 1.330 / 1.262)
      within ~2-3x its spread across seeds 0-2 (<= 0.006 marble, 0.003 / 0.008 / 0.01 skin1). Against the dipole's R_d
      (what the estimator reports): marble +17 %, skin1 +46 / +25 / +10 %.
    - normals: direction unbiased on a sphere (the blur shortens, it does not rotate); the per-pixel MC noise of
      the gradient ratio is large (10-18 deg median at 32 spp: the exit direction of each walk is random), so
      diffuse vectors and true normals are summed in 4 x 4 pixel blocks: measured median block angle 1.6-2.3 deg
      (marble, 64 spp) and 2.6-3.9 deg (skin1, 128 spp; red, l_d = 3.7 mm, highest); allowed 3 / 5.5 deg.
    - D (estimate_sphere inverts (albedo, shortening) with the truncated half-space dipole): REPORTED, and
      asserted finite only. Measured (seeds 0-2): marble D / D_true +4 / -10 / -10 to -16 % (red, green
      albedo censored at 1); skin1 +20 / +99 to +102 / +207 to +221 % -- the curvature gain above is read as a higher albedo. This is a model error of
      the sphere inversion on real transport, not Monte Carlo noise.
    """
    ssp, sa, r_tab, r_jen = truth(name)
    pos, inten, patterns, leds, lut = rig
    t0 = time.perf_counter()
    cap = sphere_mc_capture(name, rig)
    seconds = time.perf_counter() - t0
    assert cap.render_mode == "mc" and cap.led_mode == "distant" and set(cap.diffuse_stderr) == set(patterns)
    maps = maps_of(cap, rig)
    ok = ~maps.unknown
    alb = np.array([np.median(maps.albedo[..., c][ok[..., c]]) for c in range(3)])
    blocks = []
    for c in range(3):
        dv = np.where(ok[..., c, None], maps.diffuse_vectors[..., c, :], 0.0).reshape(8, 4, 8, 4, 3).sum((1, 3))
        tn = np.where(ok[..., c, None], cap.normals, 0.0).reshape(8, 4, 8, 4, 3).sum((1, 3))
        full = ok[..., c].reshape(8, 4, 8, 4).all((1, 3))
        blocks.append(float(np.median(angle_deg(dv[full], tn[full]))))
    est = estimate_sphere(maps, radius_mm=RADIUS_MM, true_normals=cap.normals)
    D = est.summary.value("D_mm")
    D_true = 1.0 / (3.0 * (ssp + sa))
    print(f"\n{name} sphere ({seconds:.1f} s): albedo/R_table {np.round(alb / r_tab, 4)}, albedo/R_jensen "
          f"{np.round(alb / r_jen, 4)}; block normal angle {np.round(blocks, 2)} deg; D {np.round(D, 4)} vs "
          f"{np.round(D_true, 4)} ({np.round(D / D_true - 1, 3)}), status {est.summary.status}")
    assert np.all(np.abs(alb / r_tab - np.array(ALBEDO_BIAS[name])) <= np.array(ALBEDO_TOL[name])), alb / r_tab
    assert max(blocks) <= NORMAL_MAX_DEG[name], blocks
    assert np.all(np.isfinite(D))


# ---------------------------------------------------------------------------------------------------------------
# spheres under the gradient patterns, corrected by a Monte Carlo reference of the known sphere
# ---------------------------------------------------------------------------------------------------------------
REF_SEED_OFFSET = 100   # the reference's realisation is independent of the observation's (a real capture is not
#                         a Monte Carlo render with the reference's seed)
REF_ITERATIONS = 4
# allowed |corrected / true - 1| per channel (R, G, B), from the measured spread over seeds 0-2 (module docstring of
# the test below); the blue channels are dominated by Monte Carlo noise of the blur at these path counts
D_TOL = {"marble": (0.10, 0.10, 0.30), "skin1": (0.06, 0.10, 0.35)}
SSP_TOL = {"marble": (0.10, 0.10, 0.35), "skin1": (0.05, 0.10, 0.45)}
SA_TOL = {"marble": (0.25, 0.15, 0.35), "skin1": (0.05, 0.10, 0.70)}


@pytest.mark.parametrize("name", sorted(MATERIALS))
def test_sphere_gradients_reference_corrected_on_mc_frames(name: str, rig) -> None:
    """The observation of ``test_sphere_gradients_on_mc_frames`` (seed SSSRIG_MC_SEED), corrected by
    ``estimate_sphere_with_reference`` with a ``GradientsMonteCarloReference`` of the same capture (same camera,
    LEDs, patterns, spp, maps and region; seed + 100, common random numbers over the iterations; at most 4 renders).

    Measured (seeds 0-2, corrected / true - 1, R / G / B): see docs/model-error.md, "Gradients on spheres". Red and
    green settle within a few % in D, sigma_s' and sigma_a (skin1) — from +20..+100 % uncorrected; marble's censored
    red/green come back into range. The blue channels' blur is 8-16 x the model's (kappa_blur) and its Monte Carlo
    error 5-10 %, so their D moves by ~+-20 % from seed to seed: asserted with a wide tolerance, and their reported
    interval is wide.
    """
    ssp, sa, _, _ = truth(name)
    pos, inten, patterns, leds, lut = rig
    t0 = time.perf_counter()
    cap = sphere_mc_capture(name, rig)
    ref = GradientsMonteCarloReference(sphere_camera(32), pos, inten, patterns, lambda c: maps_of(c, rig), RADIUS_MM,
                                       spp=SPP[name], exposure_s=0.02, sensor=SENSOR)
    est = ref.estimate(cap)
    t1 = time.perf_counter()
    res = estimate_sphere_with_reference(est.summary, ref, RADIUS_MM, ETA, seed=SEED + REF_SEED_OFFSET,
                                         max_iterations=REF_ITERATIONS, rel_tol=0.02)
    seconds = time.perf_counter() - t1
    D_true = 1.0 / (3.0 * (ssp + sa))
    unc = res.uncorrected
    # the uncorrected start is exactly estimate_sphere's summary
    np.testing.assert_allclose(unc["D_mm"], est.summary.value("D_mm"), rtol=1e-6)
    err = {"D": (unc["D_mm"] / D_true - 1, res.D_mm / D_true - 1),
           "sigma_s'": (unc["sigma_s_prime_per_mm"] / ssp - 1, res.sigma_s_prime_per_mm / ssp - 1),
           "sigma_a": (unc["sigma_a_per_mm"] / sa - 1, res.sigma_a_per_mm / sa - 1)}
    print(f"\n{name} sphere, reference-corrected (observation {t1 - t0:.1f} s, {res.iterations} renders "
          f"{seconds:.1f} s; {res.message}); kappa_albedo {np.round(res.kappa_albedo, 3)}, kappa_blur "
          f"{np.round(res.kappa_blur, 2)}")
    for k, (u, c) in err.items():
        print(f"  {k:8s} uncorrected {np.round(u, 3)} -> corrected {np.round(c, 3)}")
    print(f"  D interval / D_true - 1: {np.round(res.intervals['D_mm'] / D_true[:, None] - 1, 3).tolist()}")
    assert len(ref.renders) == res.iterations <= REF_ITERATIONS
    assert {r["seed"] for r in ref.renders} == {SEED + REF_SEED_OFFSET}
    assert np.all(np.isfinite(res.D_mm)) and not res.censored.any()
    # the correction removes the curvature gain: kappa_albedo is the measured albedo bias over R_d's model value
    assert np.all(res.kappa_albedo > 1.04)
    assert np.all(np.abs(err["D"][1]) <= np.array(D_TOL[name])), err["D"][1]
    assert np.all(np.abs(err["sigma_s'"][1]) <= np.array(SSP_TOL[name])), err["sigma_s'"][1]
    assert np.all(np.abs(err["sigma_a"][1]) <= np.array(SA_TOL[name])), err["sigma_a"][1]
    # and is an improvement where the plain inversion was worst (red/green)
    assert np.all(np.abs(err["D"][1][:2]) < np.abs(err["D"][0][:2]) + 0.02)


# ---------------------------------------------------------------------------------------------------------------
# a slab with fine relief
# ---------------------------------------------------------------------------------------------------------------
SLOW = os.environ.get("SSSRIG_SLOW_MC") == "1"


def slab_capture(rig, n_px: int, px_mm: float, spp: int, name: str = "skin1"):
    pos, inten, patterns, leds, lut = rig
    ssp, sa, _, _ = truth(name)
    cam = PinholeCamera.looking_at(width_px=n_px, height_px=n_px, fx_px=2000.0 / px_mm,
                                   position_mm=(0.0, -2000.0, 0.0), target_mm=(0.0, 0.0, 0.0))
    slab = BumpySlabObject((0.0, 0.0, 0.0), tuple(ssp), tuple(sa), ETA, extent_mm=n_px * px_mm + 22.0,
                           patch_mm=0.25, rms_slope=0.1, wavelengths_mm=(1.5, 6.0), n_waves=48, seed=0)
    return render_gradient_capture(slab, cam, pos, inten, patterns, polarizations=("cross",), exposure_s=0.02,
                                   sensor=SENSOR, noise=False, render_mode="mc",
                                   mc=MCSettings(spp=spp, seed=SEED, relief_step_mm=px_mm))


# albedo map median / R_table on the relief slab, measured seeds 0-2
SLAB_ALBEDO_BIAS = (1.145, 1.06, 1.05)
SLAB_ALBEDO_TOL = (0.02, 0.04, 0.045)


def test_bumpy_slab_albedo_and_normals_on_mc_frames(rig) -> None:
    """skin1 slab with 1.5-6 mm relief (RMS slope 0.1), 24 x 24 px of 0.3 mm, 32 spp: a CI-sized check (the
    relief mesh makes every free flight a BVH query: ~1000x slower per path than the analytic sphere).

    - albedo (median of the map) / R_table. A FLAT half-space (analytic, uniform light, normal view) gives
      1.0706 / 1.0705 / 1.0691 (+-0.003: the exit normalization). The relief slab measures 1.140-1.153 /
      1.04-1.08 / 1.025-1.066 (seeds 0-2): the red channel is ~7 % brighter than flat, reproducibly. Not
      explained yet: the relief's curvature radii (lambda / (2 pi slope) = 2.4-9.5 mm) are comparable to
      skin1-R's l_d = 3.7 mm, and a convex surface of that size returns much more light (the sphere above),
      but the first-order effect of a zero-mean relief should cancel. Asserted at the measured values
      (1.145 / 1.06 / 1.05) within ~1.5x the seed range. Against the dipole's R_d: about +15 / -1 / -7 %.
    - normals: the mean diffuse normal over the window (summed vectors) is the mean true normal within 2.5 deg
      (measured 0.6-1.8 deg; MC noise averages out; the relief tilts single pixels by ~6 deg RMS).
    The relief-blur fit (fit_relief) needs ~100 x more paths: ``SSSRIG_SLOW_MC=1`` runs it."""
    t0 = time.perf_counter()
    cap = slab_capture(rig, 24, 0.3, 32)
    seconds = time.perf_counter() - t0
    _, _, r_tab, r_jen = truth("skin1")
    maps = maps_of(cap, rig)
    ok = ~maps.unknown
    alb = np.array([np.median(maps.albedo[..., c][ok[..., c]]) for c in range(3)])
    mean_ang = [float(angle_deg(np.where(ok[..., c, None], maps.diffuse_vectors[..., c, :], 0).sum((0, 1)),
                                cap.normals[ok[..., c]].sum(0))) for c in range(3)]
    print(f"\nskin1 bumpy slab ({seconds:.1f} s, unknown {ok.size - ok.sum()} of {ok.size}): albedo/R_table "
          f"{np.round(alb / r_tab, 4)}, albedo/R_jensen {np.round(alb / r_jen, 4)}; mean-normal angle "
          f"{np.round(mean_ang, 2)} deg")
    assert np.all(np.abs(alb / r_tab - np.array(SLAB_ALBEDO_BIAS)) <= np.array(SLAB_ALBEDO_TOL)), alb / r_tab
    assert max(mean_ang) <= 2.5


@pytest.mark.skipif(not SLOW, reason="minutes of Monte Carlo on a 10^5-triangle relief; SSSRIG_SLOW_MC=1 runs it")
@pytest.mark.timeout(3600)  # ~8 min on 2 free cores; the suite-wide 300 s would cut it off
def test_bumpy_slab_relief_fit_on_mc_frames_slow(rig) -> None:
    """fit_relief on MC frames (96 x 96 px of 0.15 mm, 128 spp; 3.8 min on 2 free cores, ~8 min shared). Reports
    l' / l'_true; asserted only finite (no CI-sized measurement of its MC spread exists yet). Measured, seed 0:
    l'/l'_true 0.818 / 0.762 / 1.015 (R/G/B; albedo/R_table 1.108 / 1.066 / 1.062): the relief-blur fit on real
    transport reads red and green 18-24 % short; not reference-corrected (the spheres are:
    estimation.gradient_correction)."""
    cap = slab_capture(rig, 96, 0.15, 128)
    ssp, sa, r_tab, _ = truth("skin1")
    maps = maps_of(cap, rig)
    alb = np.median(maps.albedo.reshape(-1, 3), axis=0)
    dn = np.nan_to_num(maps.diffuse_normals.astype(float), nan=0.0)
    l_hat = fit_relief(dn, cap.normals, 0.15, alb, ETA)
    print(f"\nslow slab: l'/l'_true {np.round(l_hat * (ssp + sa), 3)}, albedo/R_table {np.round(alb / r_tab, 4)}")
    assert np.all(np.isfinite(l_hat))


# ---------------------------------------------------------------------------------------------------------------
# issue 16: the sphere summary's intervals, widened by the dipole's shortening bias
# ---------------------------------------------------------------------------------------------------------------
def test_widened_sphere_intervals_cover_monte_carlo_truth(rig) -> None:
    """The sphere summary's intervals against Monte Carlo frames (issue 16): the dipole's shortening bias widened in.

A 5 mm skin1 sphere (science.md sec. 2, eta 1.3; truth D = 0.432 / 0.317 / 0.224 mm) rendered by the project's
Monte Carlo renderer (not the estimator's dipole): 24 x 24 px pinhole, 256 spp, ideal drive of 362 LEDs as a
distant map, the sensor's expected values. Measured (seed 0): plain D 0.764 / 0.532 / 0.489 mm (+77 / +68 / +118 %)
with order-statistic intervals [0.73, 0.81], [0.51, 0.55], [0.46, 0.51] that miss the truth; widened
(estimation.sphere_bias) [0.17, 2.3], [0.14, 0.80], [0.09, 0.64]: covered, G and B "weak", R "censored"."""
    from estimation.sphere_bias import widen_sphere_summary

    pos, inten, patterns, _, _ = rig
    ssp, sa, _, _ = truth("skin1")
    R, n = 5.0, 24
    obj = SphereObject((0.0, 0.0, 0.0), R, tuple(ssp), tuple(sa), ETA, tessellation=4)
    cam = PinholeCamera.looking_at(width_px=n, height_px=n, fx_px=n * 400.0 / (2.4 * R),
                                   position_mm=(0.0, -400.0, 0.0), target_mm=(0.0, 0.0, 0.0))
    cap = render_gradient_capture(obj, cam, pos, inten, patterns, polarizations=("cross",), exposure_s=0.02,
                                  sensor=SENSOR, noise=False, render_mode="mc", mc=MCSettings(spp=256, seed=0))
    plain = estimate_sphere(maps_of(cap, rig), radius_mm=R, true_normals=cap.normals).summary.as_dict()
    wide = widen_sphere_summary(plain, R, ETA)
    D = 1 / (3 * (ssp + sa))
    p_iv, w_iv = np.asarray(plain["D_mm"]["interval"]), np.asarray(wide["D_mm"]["interval"])
    print(f"\nplain D {np.round(plain['D_mm']['value'], 3)} {np.round(p_iv, 3).tolist()}; widened "
          f"{np.round(w_iv, 3).tolist()} {wide['status']}; truth {np.round(D, 3)}")
    assert not ((p_iv[:, 0] <= D) & (D <= p_iv[:, 1])).any()       # the bias is real: plain intervals miss
    assert ((w_iv[:, 0] <= D) & (D <= w_iv[:, 1])).all()            # the widened ones cover
    assert np.allclose(wide["D_mm"]["value"], plain["D_mm"]["value"])
    assert wide["status"][1:] == ["weak", "weak"]
    assert wide["model_shortening_bias"]["plain_intervals"]["D_mm"] == plain["D_mm"]["interval"]
