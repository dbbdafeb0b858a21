"""The single-image method on Monte Carlo frames of other scenes than the cube under a point light (issue 8 item 5).

Scenes (64 x 64 px pinhole camera from the corner direction of benchmarks/mc_single_image.py, estimator patches
<= 1.5 mm, 3 x 3 window means at the patch centres, MC standard error as noise_sigma, eta 1.3 unless stated):

- ``cube-env``: the 20 mm analytic ``Box`` under a sky-like lat-long map (32 x 64, <= the estimators' max_size so
  both sides see the same map): dim sky 0.15 + 0.1 cos(theta) above the horizon, 0.03 below, plus a broad "sun"
  lobe 1.5 max(0, w.s)^3 towards s ~ (0.6, -0.6, 0.55): every face gets a different irradiance;
- ``pyramid-env``: a square pyramid (20 mm base, 14 mm high, trimesh -> ``simulators.mc.Mesh``; a refracting
  mesh at eta 1.3 is supported under distant light) under the same map;
- ``pyramid-point``: the same pyramid at eta = 1.0 under the benchmark's point light (the eta = 1.3 version,
  point lights refracted through a convex mesh, is tests/simulators/test_mc_frames_pyramid_point_eta.py).

Materials (science.md sec. 2): marble-R (2.19, 0.002 /mm; l_d 8.5 mm, as large as the object) and skin1-R
(0.74, 0.032 /mm; l_d 3.7 mm). Frames: seed ``SSSRIG_MC_SEED`` (default 1); references: seed 1000 for every
render (common random numbers), at most ``MAX_ITERATIONS`` = 6 renders (the iteration stops earlier once the
last refit is estimated within a quarter of its standard error of the fixed point; estimation.model_correction).

Each case asserts
1. the plain mc-table fit's bias (sign and rough size) as measured across frame seeds 1-3 (the flat half-space
   sum is wrong near edges; under distant light a flat face is uniformly lit, so edges carry all the information
   about sigma_s'); bounds are the measured range widened by ~10 points;
2. the reference-corrected fit (estimate_with_reference + MonteCarloReference of the same shape, camera, lights)
   meets the acceptance: sigma_s' within 10 %, sigma_a within 50 % or flagged non-identifiable with a 95 %
   interval containing the truth.

Measured (seeds 1, 2, 3; frame spp / reference spp as in CASES; errors sigma_s', sigma_a; renders used):

| case | plain mc-table | mc-table+reference | renders | s/seed |
|---|---|---|---|---|
| cube-env marble-R (128/64) | -32/-49, -37/-58, -35/-49 | -4.2/+7.9, -6.2/-2.5, -5.4/+14 % | 2, 2, 2 | 14 |
| cube-env skin1-R (256/128) | +30/-14, +25/-17, +27/-15 | +2.0/+2.4, -5.5/-3.0, -0.3/+1.2 | 3, 4, 3 | 9 |
| pyramid-env marble-R (256/128) | -48/-99, -47/-99, -47/-99 (flagged) | -2.5, -2.5, -4.4; sigma_a -43/-36/-45 % flagged, CI 0-0.0041 (seed 1) holds 0.002 | 3, 3, 3 | 5 |
| pyramid-env skin1-R (256/128) | +24/-2, +34/+7, +19/-8 | FAILS: -37/-47, -29/-37, -53/-70 (not settled) | 6, 6, 6 | 8 |
| pyramid-env skin1-R (4096/1024) | +30/+3, +29/+2, +30/+3 | +3.5/+3.5, 0.0/-0.4, +4.7/+4.9 | 6, 5, 5 | 24 |
| pyramid-point eta 1 skin1-R (256/128) | -65/-100 (3 seeds) | +2.9/+12, +2.7/+12, +1.1/+8.3 | 4, 4, 4 | 4 |
| pyramid-point eta 1 marble-R (256/128) | -50/-100 | +2.4, +3.6, +0.7; sigma_a +80/+121/+47 % flagged, CI holds truth | 4, 4, 4 | 8 |

Before the stopping rule counted the distance still to go (it compared the last step itself with a quarter of the
95 % half-width, a one-sided sigma_a interval as infinitely wide) and with at most 4 renders, the same runs gave
-1.2/+16, -6.2/-2.5, -3.9/+23 (cube-env marble); +2.0/+2.4, -5.1/-4.4, -0.3/+1.2 (cube-env skin1); +2.1, +6.9,
+6.2 with sigma_a -70/-61/-63 % after 2 renders, stopped by the one-sided sigma_a interval (pyramid-env marble);
-26, -13, -41 % (pyramid-env skin1, the last two "converged"); the pyramid-point cases as now.

At lower spp the reference iteration is noise-limited: cube-env skin1-R at 128/64 spp diverged for seed 2
(sigma_s' +33 %), pyramid-point at 64/32 stopped at +15..+20 % after 4 renders; at 1024/256 spp the same cases
give +4 %/+4 % and -2..+4 %. Hence 256-spp frames and 128-spp references for all but the marble cube (whose
6144-patch fits dominate the time; 128/64 passes there).

Formerly a failure: pyramid-env skin1-R. Not Monte Carlo noise (same at 1024/256 spp) and not the reference:
estimate_single_image(model="mc-table", method="direct") fed its OWN noise-free prediction at the truth returned
sigma_s' -66 %, sigma_a at its lower bound (0.25, 3e-6 /mm: rms residual 2.2 % where the truth has 0) -- a local
minimum of the direct fit, reached from the best point of its start grid. The fit now also starts from every
local minimum of that grid (and the reference loop passes its current iterate as a start), which finds the truth
(residual 4e-16). ``test_fast_fit_recovers_its_own_prediction`` keeps it so.

Known failure (xfail, strict): pyramid-env skin1-R at 256/128 spp. The iteration converges, but to a fixed point
far from the truth: with 8 renders sigma_s' ends at -42, -35, -56 % (seeds 1-3; seed 1 by step: +24, +7.9, -6.0,
-16, -26, -33, -37, -41, -42 %). The fixed point itself is off, not the iteration: on a grid of render points
(sigma_s' 0.5-1.4x, sigma_a 0.8-1.25x the truth; frame seed 1, reference seed 1000) the refit's sigma_s' is below
the rendered one everywhere (by 3-27 %), so no fixed point lies in that box; Newton's method on F(p) - p (forward
differences, 5 iterations) ends at -1 to -62 % for 256/128 spp (3 frame x 2 reference seeds; half of the runs
without reaching |F(p) - p| < 1 %: at 128 spp F is rough on the scale of its 8 % difference steps) and at +5, +1,
+6, -1 % for 4096/1024 spp (seeds 1, 2, 3, and 3 with another reference seed). The
scene holds sigma_s' weakly (370 patches, l_d 3.7 mm, a uniformly lit face per side): the map's slope at the truth
is [[1.0, -0.4], [1.0, -0.4]] in log (sigma_s', sigma_a), so the refits slide along the ridge of nearly constant
albedo and the fixed point is off by about twice the refit's error at the truth, whose standard deviation is ~0.05
(256-spp frame noise) plus 0.08 (128-spp reference noise; 0.03 at 1024 spp) in log sigma_s'. At 256/1024 spp the
iteration gives -1.6, +13.5, -29 %; at 4096/1024 (the ``pyramid-env-skin1-4096`` case) it passes for all three
seeds. Secant steps (Anderson, per-parameter) were tried and are worse (estimation.model_correction docstring).
"""
from __future__ import annotations

import functools
import os
import time

import numpy as np
import pytest
import trimesh

from estimation.camera import PinholeCamera
from estimation.model_correction import estimate_with_reference
from estimation.single_image import EnvironmentMap, PointLights, estimate_single_image, patches_from_mesh, \
    predict_radiance
from rig.estimate.pixel_map import pixel_faces, sample_at_points
from rig.estimate.reference.mc_reference import MonteCarloReference

MATERIALS = {"marble-R": (2.19, 0.002), "skin1-R": (0.74, 0.032)}   # science.md sec. 2 (marble: seed truth)
TOL_SSP, TOL_SA = 0.10, 0.50
SIZE, PATCH_MM, EDGE_MM = 64, 1.5, 20.0
CAMERA_MM = (250.0, -300.0, 220.0)
LIGHT_MM = (350.0, -600.0, 500.0)
REFERENCE_SEED = 1000
SEED = int(os.environ.get("SSSRIG_MC_SEED", "1"))   # the measured ranges come from seeds 1-3

# name: shape, light, material, eta, frame spp, reference spp, plain (sigma_s' lo, hi), plain (sigma_a lo, hi)
CASES = {
    "cube-env-marble": ("cube", "env", "marble-R", 1.3, 128, 64, (-0.45, -0.25), (-0.70, -0.35)),
    "cube-env-skin1": ("cube", "env", "skin1-R", 1.3, 256, 128, (0.15, 0.40), (-0.27, -0.05)),
    "pyramid-env-marble": ("pyramid", "env", "marble-R", 1.3, 256, 128, (-0.58, -0.38), (-1.0, -0.90)),
    "pyramid-env-skin1": ("pyramid", "env", "skin1-R", 1.3, 256, 128, (0.17, 0.41), (-0.10, 0.15)),
    "pyramid-env-skin1-4096": ("pyramid", "env", "skin1-R", 1.3, 4096, 1024, (0.17, 0.41), (-0.10, 0.15)),
    "pyramid-point-eta1-skin1": ("pyramid", "point", "skin1-R", 1.0, 256, 128, (-0.75, -0.55), (-1.0, -0.90)),
    "pyramid-point-eta1-marble": ("pyramid", "point", "marble-R", 1.0, 256, 128, (-0.60, -0.40), (-1.0, -0.90)),
}
#: cases left out of CI unless SSSRIG_SLOW_MC=1 (a 4096-spp frame and 1024-spp references: ~95 s)
SLOW_CASES = {"pyramid-env-skin1-4096"}
SLOW = os.environ.get("SSSRIG_SLOW_MC") == "1"
#: the reference loop runs in CI on this case only (an index-matched pyramid under a point light, ~25-40 s); the
#: others' loops take 1-3 min each (measured in a loaded two-worker run: cube-env-marble 181 s, cube-env-skin1 176 s,
#: pyramid-env-marble 111 s, pyramid-point-eta1-skin1 81 s; pyramid-env-skin1 40 s + its acceptance run once the
#: stop rule of issue 15 runs the loop on) and the CI subset of the scene zoo (tests/rig/test_scene_zoo.py) asserts
#: the same rules through the user path, sky-lit pyramids included; SSSRIG_SLOW_MC=1 runs every case. Their plain
#: fits (the frames) run in CI.
REFERENCE_CI_CASES = {"pyramid-point-eta1-marble"}
#: accuracy (not honesty) cases that fail, measured; pyramid-env-marble is not strict: its loop ends at -3.9 % with
#: one numba thread and -11.0 % with two (summation order; weak with a covering interval either way)
KNOWN_FLAKY = {"pyramid-env-marble": "the loop ends at -3.9 % (1 numba thread) or -11.0 % (2 threads): chaotic in "
                                     "floating-point summation order; weak with a covering interval either way"}
KNOWN_FAILURES = {"pyramid-env-skin1": "at 256/128 spp the fixed point of the reference iteration lies 35-56 % "
                                        "below the truth on this weakly informative scene (module docstring)",
                  "cube-env-skin1": "the trust-region loop of issue 15 ends at +14.7 % after 3 renders (weak, its "
                                    "interval -16..+58 % holds the truth; the earlier fixed-point loop: +2.0 %)",
                  "pyramid-point-eta1-skin1": "the trust-region loop of issue 15 ends at -19.5 %, not converged in 6 "
                                              "renders (weak, its interval holds the truth)"}
MAX_ITERATIONS = 6


def sky_map(rows: int = 32) -> EnvironmentMap:
    h, w = rows, 2 * rows
    th = np.pi * (np.arange(h) + 0.5) / h
    ph = 2 * np.pi * (np.arange(w) + 0.5) / w
    t, p = np.meshgrid(th, ph, indexing="ij")
    d = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)
    sun = np.array([0.6, -0.6, 0.55])
    sun /= np.linalg.norm(sun)
    sky = np.where(d[..., 2] > 0, 0.15 + 0.1 * d[..., 2], 0.03)
    return EnvironmentMap(sky + 1.5 * np.clip(d @ sun, 0, None) ** 3, max_size=64)


def pyramid_mesh(base_mm: float = EDGE_MM, height_mm: float = 0.7 * EDGE_MM) -> trimesh.Trimesh:
    a, z0 = base_mm / 2, -height_mm / 3        # centroid at the origin
    v = np.array([[-a, -a, z0], [a, -a, z0], [a, a, z0], [-a, a, z0], [0, 0, z0 + height_mm]])
    f = np.array([[0, 2, 1], [0, 3, 2], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    m = trimesh.Trimesh(v, f, process=False)
    if m.volume < 0:
        m.invert()
    return m


@functools.lru_cache(maxsize=None)
def setup(shape_kind: str, light_kind: str):
    """Camera, MC shape, lights, patches and the pixels a mesh face covers."""
    from simulators.mc import Box, Mesh

    dist = float(np.linalg.norm(CAMERA_MM))
    cam = PinholeCamera.looking_at(width_px=SIZE, height_px=SIZE, fx_px=SIZE * dist / (1.9 * EDGE_MM),
                                   position_mm=CAMERA_MM, target_mm=(0.0, 0.0, 0.0))
    if shape_kind == "cube":
        mesh, h = trimesh.creation.box(extents=(EDGE_MM,) * 3), EDGE_MM / 2
        shape = Box((-h, -h, -h), (h, h, h))
    else:
        mesh = pyramid_mesh()
        assert mesh.is_watertight and mesh.is_convex   # EnvironmentMap irradiance has no shadowing
        shape = Mesh(mesh)
    light = sky_map() if light_kind == "env" else PointLights(np.array([LIGHT_MM]), np.array([[1.0e6]]))
    v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=PATCH_MM)
    sub = trimesh.Trimesh(v, f, process=False)
    return cam, shape, light, patches_from_mesh(sub, cam), pixel_faces(sub, cam) >= 0


@functools.lru_cache(maxsize=None)
def case(name: str):
    """(setup, truth, eta, observations, their standard error, frame seconds) of a case's MC frame."""
    from simulators.mc import Medium, render

    shape_kind, light_kind, mat, eta, spp = CASES[name][:5]
    cam, shape, light, pat, valid_px = su = setup(shape_kind, light_kind)
    truth = MATERIALS[mat]
    img = render(shape, [Medium.from_reduced(*truth, eta=eta)], cam, light, spp=spp, seed=SEED)
    obs, sig = sample_at_points(img.radiance, img.stderr ** 2, (valid_px & img.mask)[..., None], cam,
                                pat.centers_mm)
    obs[~pat.visible] = np.nan
    sig[~pat.visible] = np.nan
    assert img.truncated_fraction == 0
    return su, truth, eta, obs, sig, img.seconds


def errors(r, truth):
    s, a = float(r.sigma_s_prime_per_mm[0]), float(r.sigma_a_per_mm[0])
    lo, hi = (float(x) for x in r.sigma_a_ci_per_mm[0])
    return s / truth[0] - 1, a / truth[1] - 1, (lo, hi), bool(r.sigma_a_identifiable_per_channel[0])


def _marks(n: str) -> list:
    marks = []
    if n in KNOWN_FAILURES:
        marks.append(pytest.mark.xfail(strict=True, reason=KNOWN_FAILURES[n]))
    if n in KNOWN_FLAKY:
        marks.append(pytest.mark.xfail(strict=False, reason=KNOWN_FLAKY[n]))
    if n in SLOW_CASES:
        marks.append(pytest.mark.skipif(not SLOW, reason="minutes of Monte Carlo; SSSRIG_SLOW_MC=1 runs it"))
    return marks


def _reference_marks(n: str) -> list:
    """_marks, and outside REFERENCE_CI_CASES the reference loop only with SSSRIG_SLOW_MC=1."""
    marks = _marks(n)
    if n not in REFERENCE_CI_CASES and n not in SLOW_CASES:
        marks.append(pytest.mark.skipif(not SLOW, reason="a 1.5-3 min reference loop; the zoo's CI subset covers "
                                                         "its rules; SSSRIG_SLOW_MC=1 runs it"))
    return marks


@pytest.mark.parametrize("name", [pytest.param(n, marks=_marks(n)[-1:] if n in SLOW_CASES else []) for n in CASES])
def test_plain_mc_table_bias(name):
    (cam, shape, light, pat, _), truth, eta, obs, sig, frame_s = case(name)
    assert np.isfinite(obs[:, 0]).sum() > 300
    t0 = time.perf_counter()
    r = estimate_single_image(obs, pat, light, eta, method="direct", model="mc-table", noise_sigma=sig)
    assert r, r.message
    es, ea, ci, ident = errors(r, truth)
    print(f"{name} seed {SEED}: plain mc-table sigma_s' {es:+.1%}, sigma_a {ea:+.1%} (CI {ci[0]:.3g}-{ci[1]:.3g}, "
          f"identifiable {ident}); frame {frame_s:.1f} s, fit {time.perf_counter() - t0:.1f} s")
    (s_lo, s_hi), (a_lo, a_hi) = CASES[name][6:8]
    assert s_lo <= es <= s_hi
    assert a_lo <= ea <= a_hi
    # issue 15 item 4 (eta = 1): the flat model's separable angular factor is wrong at an index-matched boundary
    # (docs/model-error.md); a plain fit there is never reported "ok", and its interval (the search range: no error
    # bound for the flat profile) holds the truth. Before the fix these fits said nothing and their intervals
    # (a few % wide) missed a truth 40-75 % away.
    status, reasons = r.extra["status"], r.extra["status_reasons"][0]
    if eta < 1.1:
        assert status["sigma_s_prime_per_mm"][0] == "weak" and "index-matched" in reasons
    if abs(es) > TOL_SSP:
        lo_s, hi_s = (float(x) for x in r.sigma_s_prime_ci_per_mm[0])
        assert status["sigma_s_prime_per_mm"][0] == "weak" and lo_s <= truth[0] <= hi_s
    if abs(ea) > TOL_SA:
        assert status["sigma_a_per_mm"][0] == "weak" and ci[0] <= truth[1] <= ci[1]


@functools.lru_cache(maxsize=None)
def corrected(name: str):
    """The reference loop's result on a case, its errors and a printed summary (one run per case)."""
    (cam, shape, light, pat, valid_px), truth, eta, obs, sig, _ = case(name)
    ref = MonteCarloReference(shape, cam, light, pat, spp=CASES[name][5], valid_px=valid_px)
    t0 = time.perf_counter()
    r = estimate_with_reference(obs, pat, light, eta, ref, noise_sigma=sig, base_model="mc-table",
                                max_iterations=MAX_ITERATIONS, seed=REFERENCE_SEED)
    assert r, r.message
    es, ea, (lo, hi), ident = errors(r, truth)
    s_lo, s_hi = (float(x) for x in r.sigma_s_prime_ci_per_mm[0])
    status = r.extra["status"]
    path = ", ".join(f"{st['sigma_s_prime_per_mm'][0] / truth[0] - 1:+.1%}" for st in r.extra["reference"])
    print(f"{name} seed {SEED}: mc-table+reference sigma_s' {es:+.1%} ({status['sigma_s_prime_per_mm'][0]}, CI "
          f"{s_lo / truth[0] - 1:+.0%}..{s_hi / truth[0] - 1:+.0%}), sigma_a {ea:+.1%} "
          f"({status['sigma_a_per_mm'][0]}, CI {lo:.3g}-{hi:.3g}, identifiable {ident}), {len(ref.renders)} renders "
          f"(converged {r.extra['converged']}), {time.perf_counter() - t0:.1f} s; sigma_s' by step: {path}")
    assert r.model == "mc-table+reference" and {x["seed"] for x in ref.renders} == {REFERENCE_SEED}
    return r, truth, es, ea


@pytest.mark.parametrize("name", [pytest.param(n, marks=[m for m in _reference_marks(n) if m.name == "skipif"])
                                  for n in CASES])
def test_reference_corrected_is_never_confident_and_wrong(name):
    """Issue 15's rules on every case: sigma_s' within 10 % or weak with a 95 % interval holding the truth; sigma_a
    within 50 % or weak with its interval holding the truth; nothing "ok" more than 25 % off."""
    r, truth, es, ea = corrected(name)
    status = r.extra["status"]
    s_lo, s_hi = (float(x) for x in r.sigma_s_prime_ci_per_mm[0])
    a_lo, a_hi = (float(x) for x in r.sigma_a_ci_per_mm[0])
    assert abs(es) <= TOL_SSP or (status["sigma_s_prime_per_mm"][0] != "ok" and s_lo <= truth[0] <= s_hi)
    assert abs(ea) <= TOL_SA or (status["sigma_a_per_mm"][0] != "ok" and a_lo <= truth[1] <= a_hi)
    assert not (abs(es) > 0.25 and "ok" in (status["sigma_s_prime_per_mm"][0], status["sigma_a_per_mm"][0]))


@pytest.mark.parametrize("name", [pytest.param(n, marks=_reference_marks(n)) for n in CASES])
def test_reference_corrected_acceptance(name):
    """Accuracy: sigma_s' within 10 %, sigma_a within 50 % or not identifiable with a covering interval."""
    r, truth, es, ea = corrected(name)
    lo, hi = (float(x) for x in r.sigma_a_ci_per_mm[0])
    assert abs(es) <= TOL_SSP
    assert abs(ea) <= TOL_SA or (not r.sigma_a_identifiable_per_channel[0] and lo <= truth[1] <= hi)


def test_fast_fit_recovers_its_own_prediction():
    """The former pyramid-env-skin1 failure: noise-free observations equal to the mc-table model at the truth
    (1 % noise_sigma) must be fitted back to the truth (before the grid's local minima became starts: sigma_s'
    -66 %, sigma_a 3e-6 /mm)."""
    (cam, shape, light, pat, _), truth, eta, obs, _, _ = case("pyramid-env-skin1")
    o = np.full_like(obs, np.nan)
    o[pat.visible_index] = predict_radiance(pat, light, eta, *truth, model="mc-table")
    o[~np.isfinite(obs)] = np.nan
    r = estimate_single_image(o, pat, light, eta, method="direct", model="mc-table", noise_sigma=0.01 * o)
    assert r, r.message
    es, ea, _, _ = errors(r, truth)
    print(f"mc-table fit of its own prediction: sigma_s' {es:+.1%}, sigma_a {ea:+.1%}")
    assert abs(es) <= 0.01 and abs(ea) <= 0.01
