"""The per-window relief fit as it was before the batched search (estimation.relief at c0e436a), kept verbatim as
the reference the batched :func:`estimation.relief.fit_relief_windows` is tested against
(tests/estimation/test_relief.py::test_batched_equals_per_window). Test-only code: one window and one channel at a
time, complex FFTs, 48 inverse FFTs per component."""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy import stats

from estimation.relief_windows import _mtf_table
from estimation.relief import (_N_GRID, RELIEF_PARAMS, ReliefFit, _alpha_from_rd, _derived_interval,
                               _window_origins, exit_normalization, normal_noise_rad, parameters_from_l_prime)
from estimation.dipole import reduced_albedo_from_total_reflectance  # noqa: I001

Array = np.ndarray


def _fit_one(Dn: Array, Tn: Array, comps: tuple[int, int], pixel_mm: float, alpha: float, eta: float,
             l_grid: Array, margin_px: int, fdr: str, confidence: float, model: str = "dipole-jensen"
             ) -> tuple[float, float, float, bool, bool]:
    """(l' best, lo, hi, lo_at_bound, hi_at_bound) for one channel of one window (arrays without NaN)."""
    h, w = Tn.shape[:2]
    win = np.zeros((h, w))
    win[margin_px:h - margin_px, margin_px:w - margin_px] = np.outer(np.hanning(h - 2 * margin_px),
                                                                      np.hanning(w - 2 * margin_px))
    ph, pw = h // 2, w // 2
    spectra = [np.fft.fft2(np.pad(Tn[..., c] - Tn[..., c].mean(), ((ph, ph), (pw, pw)), mode="reflect"))
               for c in comps]
    H2, W2 = spectra[0].shape
    ky = 2 * np.pi * np.fft.fftfreq(H2, d=pixel_mm)
    kx = 2 * np.pi * np.fft.fftfreq(W2, d=pixel_mm)
    kk = np.sqrt(ky[:, None] ** 2 + kx[None, :] ** 2)
    data = [Dn[..., c] - Dn[..., c].mean() for c in comps]
    xs, ms = _mtf_table(alpha, eta, fdr, model)
    cost = np.empty(l_grid.size)
    for i, lp in enumerate(l_grid):
        M = np.interp(kk * lp, xs, ms)
        tot = 0.0
        for spec, dat in zip(spectra, data):
            pred = np.real(np.fft.ifft2(M * spec))[ph:ph + h, pw:pw + w]
            tot += float(np.sum((win * (dat - (pred - pred.mean()))) ** 2))
        cost[i] = tot
    k = int(np.argmin(cost))
    ll = np.log(l_grid)
    best = ll[k]
    cmin = cost[k]
    if 0 < k < l_grid.size - 1:      # parabola through the three grid points around the minimum
        y0, y1, y2 = cost[k - 1], cost[k], cost[k + 1]
        den = y0 - 2 * y1 + y2
        if den > 0:
            off = 0.5 * (y0 - y2) / den
            best = ll[k] + off * (ll[1] - ll[0])
            cmin = y1 - 0.25 * (y0 - y2) * off
    W2s, W4s = float(np.sum(win ** 2)), float(np.sum(win ** 4))
    s2 = max(cmin, 0.0) / (len(comps) * W2s)                   # residual variance per pixel and component
    thr = cmin + stats.chi2.ppf(confidence, 1) * s2 * W4s / W2s * len(comps)
    inside = np.nonzero(cost <= max(thr, cost[k]))[0]
    i0, i1 = int(inside.min()), int(inside.max())
    lo = l_grid[max(i0 - 1, 0)] if i0 > 0 else l_grid[0]         # the next grid point out: conservative
    hi = l_grid[min(i1 + 1, l_grid.size - 1)]
    return float(np.exp(best)), float(lo), float(hi), i0 == 0, i1 == l_grid.size - 1


def fit_relief_windows_per_window(diffuse_normals: ArrayLike, true_normals: ArrayLike, albedo: ArrayLike, pixel_mm: float,
                       eta: float, *, window_px: int = 64, stride_px: int | None = None,
                       valid: ArrayLike | None = None, min_valid_fraction: float = 0.9,
                       margin_px: int | None = None, confidence: float = 0.95, model_bias_rel: float = 0.3,
                       albedo_rel_uncertainty: float = 0.1, weak_ratio: float = 4.0, min_relief_snr: float = 2.0,
                       min_relief_rad: float = 2e-3, fdr: str = "fit", exit_norm: float | None = None,
                       model: str = "dipole-jensen") -> ReliefFit:
    """Fit l' per window and channel from the blur of ``diffuse_normals`` (H, W, 3 channels, 3 xyz) against
    ``true_normals`` (H, W, 3) (known geometry, or the specular normals of the same capture); ``albedo``
    (H, W, 3) is R_d (exit Fresnel divided out, as :func:`estimation.gradients.compute_maps` reports it);
    ``pixel_mm`` the pixel footprint on the surface; ``exit_norm``: the factor applied to the map's R_d before
    inverting alpha' (default :func:`exit_normalization` (eta); 1.0: the map's R_d as is); ``valid`` (H, W) or (H, W, 3) usable pixels (NaN pixels are
    never used; a window needs ``min_valid_fraction`` of them, the rest are filled with the window mean).

    Windows of ``window_px`` (>= 16) every ``stride_px`` (default: ``window_px``, non-overlapping) with a Hann
    weight inside ``margin_px`` (default window/4) of the edge: a diffuse normal depends on the relief within a few
    l_d, which the window must contain (margin >~ 2 l_d). See the module docstring for the interval and status.
    """
    # kept as given (float32 maps, memory maps or derived maps that compute a slice on access): each window is
    # read once and cast to float64, so a 24 MP capture never holds a full (H, W, 3, 3) copy
    Dn = diffuse_normals if hasattr(diffuse_normals, "__getitem__") and hasattr(diffuse_normals, "shape") \
        else np.asarray(diffuse_normals)
    Tn = np.asarray(true_normals)
    alb = np.asarray(albedo)
    H, W = Tn.shape[:2]
    if Tn.shape != (H, W, 3) or Dn.shape != (H, W, 3, 3) or alb.shape != (H, W, 3):
        raise ValueError("need diffuse_normals (H, W, 3, 3), true_normals (H, W, 3) and albedo (H, W, 3)")
    if int(window_px) < 16:
        raise ValueError(f"window_px must be >= 16, got {window_px}")
    if not pixel_mm > 0 or not np.isfinite(pixel_mm):
        raise ValueError(f"pixel_mm must be a finite number > 0, got {pixel_mm}")
    win_px = int(window_px)
    stride = win_px if stride_px is None else int(stride_px)
    if stride < 1:
        raise ValueError(f"stride_px must be >= 1, got {stride_px}")
    margin = win_px // 4 if margin_px is None else int(margin_px)
    if not 0 <= 2 * margin < win_px - 2:
        raise ValueError("margin_px leaves no pixels")
    v = np.ones((H, W, 3), bool) if valid is None else np.asarray(valid, dtype=bool)
    if v.ndim == 2:
        v = np.repeat(v[..., None], 3, axis=-1)
    finite_t = np.isfinite(Tn).all(-1)
    c_exit = exit_normalization(eta) if exit_norm is None else float(exit_norm)
    l_grid = np.exp(np.linspace(np.log(pixel_mm / 4.0), np.log(2.0 * win_px * pixel_mm), _N_GRID))
    rows, cols = _window_origins(H, win_px, stride), _window_origins(W, win_px, stride)
    ny, nx = len(rows), len(cols)
    if ny == 0 or nx == 0:
        raise ValueError(f"window_px {win_px} is larger than the map ({W} x {H} px)")
    vals = {k: np.full((ny, nx, 3), np.nan) for k in RELIEF_PARAMS}
    ints = {k: np.full((ny, nx, 3, 2), np.nan) for k in RELIEF_PARAMS}
    status = np.full((ny, nx, 3), "unknown", dtype="<U7")
    rms = np.full((ny, nx), np.nan)
    noise = np.full((ny, nx), np.nan)
    dnoise = np.full((ny, nx, 3), np.nan)
    full_lo, full_hi = l_grid[0], l_grid[-1]
    for i, r0 in enumerate(rows):
        for j, c0 in enumerate(cols):
            sl = (slice(r0, r0 + win_px), slice(c0, c0 + win_px))
            t = Tn[sl].astype(np.float64)
            ok_t = finite_t[sl]
            if ok_t.mean() < min_valid_fraction:
                continue
            t = np.where(ok_t[..., None], t, np.nanmean(t[ok_t], axis=0))
            comps = tuple(int(c) for c in np.argsort(t.reshape(-1, 3).var(axis=0))[-2:])
            sig_n = normal_noise_rad(t, comps)
            tot_var = sum(float(np.var(t[..., c])) for c in comps)
            rel_rms = float(np.sqrt(max(tot_var - 2 * sig_n ** 2, 0.0)))
            rms[i, j], noise[i, j] = rel_rms, sig_n
            relief_ok = rel_rms >= max(min_relief_snr * np.sqrt(2.0) * sig_n, min_relief_rad)
            dn_win = np.asarray(Dn[sl], dtype=np.float64)
            for c in range(3):
                d = dn_win[..., c, :]
                a_w = alb[sl][..., c].astype(np.float64)
                ok = ok_t & v[sl][..., c] & np.isfinite(d).all(-1) & np.isfinite(a_w)
                # unknown defaults: the whole searched range as interval
                a_med = c_exit * float(np.median(a_w[ok])) if ok.any() else float("nan")
                if ok.mean() < min_valid_fraction or not (0 < a_med < 1):
                    _put_unknown(ints, i, j, c, full_lo, full_hi, a_med, eta, fdr)
                    continue
                dn = d / np.linalg.norm(d, axis=-1, keepdims=True)
                dn = np.where(ok[..., None], dn, np.nanmean(dn[ok], axis=0))
                dnoise[i, j, c] = normal_noise_rad(dn, comps)
                alpha = _alpha_from_rd(a_med, eta, fdr, model)
                if not relief_ok:
                    _put_unknown(ints, i, j, c, full_lo, full_hi, a_med, eta, fdr)
                    continue
                best, lo, hi, lo_b, hi_b = _fit_one(dn, t, comps, pixel_mm, alpha, eta, l_grid, margin, fdr,
                                                    confidence, model)
                lo_w, hi_w = lo / (1.0 + model_bias_rel), hi * (1.0 + model_bias_rel)
                a_lo = _alpha_from_rd(a_med / (1 + albedo_rel_uncertainty), eta, fdr, model)
                a_hi = _alpha_from_rd(min(a_med * (1 + albedo_rel_uncertainty), 0.999), eta, fdr, model)
                point = parameters_from_l_prime(alpha, best)
                iv = _derived_interval(alpha, a_lo, a_hi, lo_w, hi_w)
                for k in RELIEF_PARAMS:
                    vals[k][i, j, c] = float(point[k])
                    ints[k][i, j, c] = iv[k]
                weak = lo_b or hi_b or hi / lo > weak_ratio
                status[i, j, c] = "weak" if weak else "ok"
    origins = np.array([[(r, c) for c in cols] for r in rows], dtype=np.int64).reshape(ny, nx, 2)
    prov = {"window_px": win_px, "stride_px": stride, "margin_px": margin, "pixel_mm": float(pixel_mm),
            "confidence": confidence, "model_bias_rel": model_bias_rel,
            "albedo_rel_uncertainty": albedo_rel_uncertainty, "weak_ratio": weak_ratio,
            "min_relief_snr": min_relief_snr, "min_relief_rad": min_relief_rad, "eta": eta, "fdr": fdr,
            "exit_normalization": c_exit,
            "method": "relief blur, profile likelihood per window (estimation.relief)"}
    return ReliefFit(win_px, stride, float(pixel_mm), origins, vals, ints, status, rms, noise, dnoise,
                     (float(full_lo), float(full_hi)), prov)


def _put_unknown(ints: dict[str, Array], i: int, j: int, c: int, l_lo: float, l_hi: float, a_med: float,
                 eta: float, fdr: str) -> None:
    """An unknown window-channel: NaN value, interval = the whole searched l' range (albedo 0-1 if unusable)."""
    if 0 < a_med < 1:
        al = float(reduced_albedo_from_total_reflectance(a_med, eta, fdr=fdr))
        iv = _derived_interval(al, al, al, l_lo, l_hi)
    else:
        iv = {k: (0.0, float("inf")) for k in RELIEF_PARAMS}
    for k in RELIEF_PARAMS:
        ints[k][i, j, c] = iv[k]
