"""Issue 8 acceptance on Monte Carlo frames: marble-R (sigma_s' 2.19, sigma_a 0.002 /mm, eta 1.3) cube under one
point light, rendered by simulators.mc and fitted by estimate_single_image (benchmarks/mc_single_image.py is the
full-size run; this is the same pipeline at 64 x 64 px, 64 spp, 1 mm patches, ~10 s including numba compile).

Tolerances:
- units: the MC image over predict_radiance(model="mc-table") at the true parameters, median over the patches
  >= 5 mm from a cube edge (~1000 patches; per-window MC error ~4 %, so the median's noise is ~0.2 %), must lie
  in [0.95, 1.05]: the exit-angle model error of the table is a few % (docs/monte-carlo.md sec. 2); a convention
  mismatch (pi, or the exit normalization c = 0.939 at eta 1.3) would be off by >= 6 %.
- the acceptance itself (sigma_s' within 10 %, sigma_a within 50 % or flagged with an interval holding the
  truth) is met by the best model, mc-table corrected by Monte Carlo reference renders of the known box
  (estimation.model_correction, rig.estimate.reference.mc_reference), at this small size with 32-spp references (4 renders of ~1.5 s);
  the fast models alone miss sigma_s' by 25-40 % on this cube (the flat-surface R(d) sum is wrong at its edges,
  where the information about sigma_s' sits) and are only checked against each other here.
  benchmarks/mc_single_image.py prints the full-size verdict.
- the classical dipole's sigma_a error is at least the table model's (reported with the numbers).
"""
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from mc_single_image import ETA, MODELS, REFERENCE_SEED, TOL_SA, TOL_SSP, TRUTH, fit_row, observations, render_frame
from estimation.camera import PinholeCamera
from estimation.single_image import predict_radiance
from rig.estimate.reference.mc_reference import MonteCarloReference

SIZE, SPP, EDGE_MM, PATCH_MM = 64, 64, 20.0, 1.0


@pytest.fixture(scope="module")
def scene():
    frame = render_frame(SIZE, SPP, EDGE_MM, *TRUTH, seed=3, cache=False)
    pat, light, obs, sig, edge, valid = observations(frame, SIZE, EDGE_MM, PATCH_MM)
    return frame, pat, light, obs, sig, edge, valid


@pytest.fixture(scope="module")
def rows(scene):
    _, pat, light, obs, sig, _, _ = scene
    return {m: fit_row(m, obs, sig, pat, light) for m in MODELS}


def test_mc_image_units_match_estimator(scene):
    frame, pat, light, obs, sig, edge, _ = scene
    assert frame["truncated_fraction"] == 0
    vis = pat.visible_index
    ok = np.isfinite(obs[vis, 0]) & (edge[vis] >= 5.0)
    assert ok.sum() > 500
    pred = predict_radiance(pat, light, ETA, TRUTH[0], TRUTH[1], model="mc-table")[:, 0]   # visible rows
    ratio = float(np.median(obs[vis, 0][ok] / pred[ok]))
    print(f"MC / mc-table at truth, >= 5 mm from edges: {ratio:.4f} ({ok.sum()} patches)")
    assert 0.95 <= ratio <= 1.05


def test_classical_dipole_sigma_a_error_not_smaller(rows):
    best, classical = rows["mc-table"], rows["dipole-jensen"]
    assert best["ok"] and classical["ok"]
    print(f"mc-table: sigma_s' {best['err_sigma_s_prime']:+.1%}, sigma_a {best['err_sigma_a']:+.1%}; "
          f"dipole-jensen: sigma_s' {classical['err_sigma_s_prime']:+.1%}, sigma_a {classical['err_sigma_a']:+.1%}")
    assert abs(classical["err_sigma_a"]) >= abs(best["err_sigma_a"])


def test_reference_corrected_model_meets_the_acceptance(scene):
    """Issue 8 acceptance at CI size: sigma_s' within 10 %, sigma_a within 50 % (or flagged with an interval
    holding the truth), from a 64 x 64 px, 64 spp frame (seed 3) with 32-spp reference renders (seed 1000 each)."""
    from mc_single_image import scene as bench_scene
    from simulators.mc import Box

    _, pat, light, obs, sig, _, valid = scene
    cam, _ = bench_scene(SIZE, EDGE_MM)
    h = EDGE_MM / 2
    ref = MonteCarloReference(Box((-h, -h, -h), (h, h, h)), cam, light, pat, spp=32, valid_px=valid)
    row = fit_row("mc-table", obs, sig, pat, light, reference=ref, iterations=4)
    assert row["ok"], row["message"]
    print(f"mc-table+reference: sigma_s' {row['err_sigma_s_prime']:+.1%}, sigma_a {row['err_sigma_a']:+.1%} "
          f"(interval {row['sigma_a_ci']}), {len(ref.renders)} renders, {row['seconds']:.1f} s")
    assert row["model"] == "mc-table+reference" and len(ref.renders) >= 1
    assert {r["seed"] for r in ref.renders} == {REFERENCE_SEED}
    assert abs(row["err_sigma_s_prime"]) <= TOL_SSP
    assert abs(row["err_sigma_a"]) <= TOL_SA or (not row["identifiable"] and row["ci_covers"])
