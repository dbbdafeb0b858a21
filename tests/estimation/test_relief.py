"""estimation.relief: the per-window relief-blur fit with intervals and status (issue 16).

Recovery is checked on Monte Carlo frames (the project's renderer, not the estimator's MTF model): the cached
capture tests/data/relief_skin1 (skin1 relief slab, 64 x 64 px of 0.2 mm, 128 spp; see
tests/rig/test_folder_diffusion.py) reduced by compute_maps here, with its true normals.
"""
from __future__ import annotations


import numpy as np
import pytest

from estimation.gradients import compute_maps
from estimation.relief import (fit_relief_windows, normal_noise_rad, normals_from_height, parameters_from_l_prime,
                               summarize_relief)

from _relief_skin1 import ETA, SA, SSP, load_relief_skin1  # tests/estimation/_relief_skin1.py


@pytest.fixture(scope="module")
def mc_maps():
    cap = load_relief_skin1()
    maps = compute_maps(cap["frames"], albedo_scale=cap["scale"], leds=cap["rig"], eta=ETA, view_dirs=cap["view"])
    return maps, cap["true_normals"]


def test_mc_relief_fit_covers_the_truth(mc_maps) -> None:
    """One 64-px window with the true normals: G / B l_d within 25 % (measured -8 / +21 % through the CLI), every
    interval covers the truth, R is weak (its l_d = 3.7 mm exceeds the 3.2 mm margin)."""
    maps, tn = mc_maps
    fit = fit_relief_windows(np.asarray(maps.diffuse_normals, float), tn, np.asarray(maps.albedo, float), 0.2, ETA,
                             window_px=64, valid=~maps.unknown)
    st = SSP + SA
    truth = parameters_from_l_prime(SSP / st, 1 / st)
    reg = summarize_relief(fit)
    for k in ("l_d_mm", "D_mm", "sigma_a_per_mm", "sigma_s_prime_per_mm"):
        iv = reg.intervals[k]
        assert np.all((iv[:, 0] <= truth[k]) & (truth[k] <= iv[:, 1])), (k, iv, truth[k])
    err = reg.values["l_d_mm"] / truth["l_d_mm"] - 1
    assert np.all(np.abs(err[1:]) < 0.25), err
    assert reg.status[0] == "weak"


def test_no_relief_is_unknown_with_the_whole_range(mc_maps) -> None:
    """The same diffuse maps against flat true normals (plus a little noise): no length information."""
    maps, tn = mc_maps
    rng = np.random.default_rng(0)
    flat = np.zeros_like(tn)
    flat[..., 1] = -1.0
    flat += rng.normal(0.0, 2e-3, flat.shape)
    flat /= np.linalg.norm(flat, axis=-1, keepdims=True)
    fit = fit_relief_windows(np.asarray(maps.diffuse_normals, float), flat, np.asarray(maps.albedo, float), 0.2,
                             ETA, window_px=32)
    assert (fit.status == "unknown").all()
    assert np.isnan(fit.values["D_mm"]).all()
    lo, hi = fit.intervals["l_prime_mm"][..., 0], fit.intervals["l_prime_mm"][..., 1]
    assert np.allclose(lo, fit.l_grid_mm[0]) and np.allclose(hi, fit.l_grid_mm[1])   # the whole searched range
    assert fit.l_grid_mm[1] / fit.l_grid_mm[0] > 200
    reg = summarize_relief(fit)
    assert reg.status == ("unknown",) * 3 and np.isinf(reg.intervals["sigma_a_per_mm"][:, 1]).all()


def test_normal_noise_and_height_normals() -> None:
    rng = np.random.default_rng(1)
    y, x = np.mgrid[0:96, 0:96] * 0.1
    h = 0.05 * np.sin(2 * np.pi * x / 3.0)                 # 3 mm period, 0.05 mm amplitude
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])   # orthographic camera looking along +y
    n = normals_from_height(h, 0.1, R)
    assert np.allclose(np.linalg.norm(n, axis=-1), 1.0)
    assert np.allclose(n[..., 1], -1.0, atol=0.02)         # facing the camera (-y)
    slope = 0.05 * 2 * np.pi / 3.0 * np.cos(2 * np.pi * x / 3.0)
    np.testing.assert_allclose(n[2:-2, 2:-2, 0], -slope[2:-2, 2:-2] / np.sqrt(1 + slope[2:-2, 2:-2] ** 2),
                               atol=3e-3)
    noisy = n + rng.normal(0.0, 0.01, n.shape)
    assert normal_noise_rad(noisy, (0, 2)) == pytest.approx(0.01, rel=0.1)   # the relief barely enters


@pytest.mark.parametrize("kw,msg", [({"window_px": 8}, "window_px"), ({"pixel_mm": 0.0}, "pixel_mm"),
                                    ({"stride_px": 0}, "stride_px"), ({"window_px": 200}, "larger than the map")])
def test_bad_arguments(kw, msg) -> None:
    args = {"diffuse_normals": np.zeros((64, 64, 3, 3)), "true_normals": np.zeros((64, 64, 3)),
            "albedo": np.full((64, 64, 3), 0.5), "pixel_mm": 0.1, "eta": ETA}
    args.update(kw)
    with pytest.raises(ValueError, match=msg):
        fit_relief_windows(**args)


def test_exit_normalization_scales_the_albedo_before_inverting() -> None:
    """The map's R_d convention reads R_d / c on a half-space (reciprocity; measured 1.060-1.064 x the Monte Carlo
    table's R_d, benchmarks/relief_albedo.py): the fit inverts alpha' from c x the map's R_d, c(1.3) = 0.9389 = the
    transmitted fraction of uniform light tau0 / pi; exit_norm=1.0 keeps the map's value."""
    from estimation.dipole import reduced_albedo_from_total_reflectance
    from estimation.fresnel import fresnel_transmittance
    from estimation.relief import exit_normalization

    assert exit_normalization(1.3) == pytest.approx(0.9389, abs=2e-4)
    mu = (np.arange(20000) + 0.5) / 20000                 # midpoint rule for int F_t(mu) 2 mu dmu
    assert exit_normalization(1.5) == pytest.approx(float(np.mean(fresnel_transmittance(1.5, mu) * 2 * mu)), rel=1e-4)
    assert exit_normalization(1.0) == pytest.approx(1.0, abs=1e-9)
    y, x = np.mgrid[0:32, 0:32] * 0.25
    h = 0.06 * np.sin(2 * np.pi * x / 2.5) + 0.06 * np.sin(2 * np.pi * y / 2.5)
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    tn = normals_from_height(h, 0.25, R)
    dn = np.repeat(tn[:, :, None, :], 3, axis=2)
    alb = np.full((32, 32, 3), 0.9)
    c = exit_normalization(ETA)
    for norm, rd in ((None, 0.9 * c), (1.0, 0.9)):
        fit = fit_relief_windows(dn, tn, alb, 0.25, ETA, window_px=32, exit_norm=norm)
        want = float(reduced_albedo_from_total_reflectance(rd, ETA))
        np.testing.assert_allclose(fit.values["alpha_prime"][0, 0], want, rtol=1e-9)


def _relief_input(H: int = 128, W: int = 192, px: float = 0.1, seed: int = 0):
    """A relief (two sinusoids) seen head-on; diffuse normals = the true ones blurred per channel (Gaussian,
    6 / 3 / 1.5 px) plus noise; 2 % NaN true normals, a dark corner in blue."""
    from scipy.ndimage import gaussian_filter
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:H, 0:W] * px
    h = 0.05 * np.sin(2 * np.pi * x / 3.0) + 0.04 * np.cos(2 * np.pi * y / 2.2 + 0.3 * x)
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    tn = normals_from_height(h, px, R)
    dn = np.empty((H, W, 3, 3))
    for c, b in enumerate((6.0, 3.0, 1.5)):
        for k in range(3):
            dn[..., c, k] = gaussian_filter(tn[..., k], b, mode="reflect")
        dn[..., c, :] += rng.normal(0, 3e-3, (H, W, 3))
    tn = tn + rng.normal(0, 1e-3, tn.shape)
    tn /= np.linalg.norm(tn, axis=-1, keepdims=True)
    tn[rng.random((H, W)) < 0.02] = np.nan
    alb = np.array([0.6, 0.45, 0.3]) * (1 + 0.02 * rng.standard_normal((H, W, 3)))
    alb[:40, :70, 2] = 0.0
    return dn, tn, alb


def _assert_same_fit(new, old, rtol: float) -> None:
    assert (new.status == old.status).all()
    for k in ("l_prime_mm", "l_d_mm", "D_mm", "sigma_s_prime_per_mm", "sigma_a_per_mm", "alpha_prime"):
        np.testing.assert_allclose(new.values[k], old.values[k], rtol=rtol, equal_nan=True, err_msg=k)
        np.testing.assert_allclose(new.intervals[k], old.intervals[k], rtol=rtol, equal_nan=True, err_msg=k)
    for k in ("relief_rms_rad", "relief_noise_rad", "diffuse_noise_rad"):
        np.testing.assert_array_equal(getattr(new, k), getattr(old, k), err_msg=k)


def test_batched_equals_per_window() -> None:
    """The band-batched fit (real FFTs pruned to the window, MTF at the distinct |k|, vectorized alpha') against
    the one-window-at-a-time fit it replaced (tests/estimation/_relief_per_window_reference.py, verbatim from
    c0e436a): the whole l' grid (search_step=1) and the coarse-to-fine search (default search_step=3) give the
    same status, values and intervals to 1e-12 relative (FFT rounding) -- here 6 windows of 64 px (ok, weak and unknown: a dark
    blue corner) and overlapping 32-px windows inside a region."""
    from _relief_per_window_reference import fit_relief_windows_per_window

    dn, tn, alb = _relief_input()
    old = fit_relief_windows_per_window(dn, tn, alb, 0.1, ETA, window_px=64)
    assert set(np.unique(old.status)) == {"ok", "weak", "unknown"}
    for step in (1, 3):
        _assert_same_fit(fit_relief_windows(dn, tn, alb, 0.1, ETA, window_px=64, search_step=step), old, 1e-12)
    region = np.zeros(tn.shape[:2], bool)
    region[10:120, 20:150] = True
    tn_r = np.where(region[..., None], tn, np.nan)
    old = fit_relief_windows_per_window(dn, tn_r, alb, 0.1, ETA, window_px=32, stride_px=24,
                                        valid=region & np.isfinite(alb).all(-1))
    new = fit_relief_windows(dn.astype(np.float32), tn.astype(np.float32), alb, 0.1, ETA, window_px=32,
                             stride_px=24, region=region)
    new64 = fit_relief_windows(dn, tn, alb, 0.1, ETA, window_px=32, stride_px=24, region=region)
    _assert_same_fit(new64, old, 1e-12)
    assert (new.status == old.status).all()                 # float32 inputs: cast per band, equal to ~1e-6
    np.testing.assert_allclose(new.values["l_prime_mm"], old.values["l_prime_mm"], rtol=1e-4, equal_nan=True)


def test_batched_equals_per_window_on_mc_maps(mc_maps) -> None:
    """The same on Monte Carlo maps (noisy, tests/data/relief_skin1): 32-px windows every 16 px, default search;
    equal to 1e-9 (one window's parabola on a flat cost moves l' by 3e-12 relative: rounding of the FFTs)."""
    from _relief_per_window_reference import fit_relief_windows_per_window

    maps, tn = mc_maps
    dn, alb = np.asarray(maps.diffuse_normals, float), np.asarray(maps.albedo, float)
    kw = {"window_px": 32, "stride_px": 16, "valid": ~maps.unknown}
    old = fit_relief_windows_per_window(dn, tn, alb, 0.2, ETA, **kw)
    _assert_same_fit(fit_relief_windows(dn, tn, alb, 0.2, ETA, **kw), old, 1e-9)
