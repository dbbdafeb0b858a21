"""The reference loop's intervals and objective (:mod:`estimation.model_correction`): the robust objective, the
widening of the refit's intervals by the derivative noise, along a non-converged path or by the secant slope of a
derivative-free one, and the renders read as likelihood samples (a flat or misfitting likelihood: the search range).
"""
from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["RESOLVED_OBJECTIVE", "FLAT_SPAN", "MISFIT_CHI2", "SECANT_SLOPE_BOUNDS"]

Array = NDArray[np.float64]

#: predicted changes of the objective below this (chi-square units of the normalized residuals) are not resolved:
#: such a step is accepted without the ratio test (Monte Carlo noise along the step dominates it)
RESOLVED_OBJECTIVE: float = 2.0
#: rendered points consistent with the data (objective within RESOLVED_OBJECTIVE of the best) spanning more than
#: this factor in a parameter: its likelihood is flat, the parameter not bounded (:func:`_flat_likelihood`)
FLAT_SPAN: float = 2.0
#: with a stated noise level, the best render's chi-square per observation above this: no rendered point fits
MISFIT_CHI2: float = 2.0
#: secant slope bounds of the derivative-free path (interval widening only)
SECANT_SLOPE_BOUNDS: tuple[float, float] = (-2.0, -0.1)
_ASSUMED_SLOPE = -0.5


def _huber_sum(z: Array, k: float = 2.5) -> Array:
    """Sum over rows of the Huber loss of z (m, C), NaN rows skipped: (C,)."""
    a = np.abs(z)
    loss = np.where(a <= k, 0.5 * a ** 2, k * a - 0.5 * k * k)
    return np.nansum(np.where(np.isfinite(loss), loss, np.nan), axis=0)


def _secant_slope(x_prev: Array, g_prev: Array, x: Array, g: Array) -> Array:
    """Secant slope (g - g_prev) / (x - x_prev) of G = F(x) - x (clipped to SECANT_SLOPE_BOUNDS); NaN where the two
    points coincide. 1 + s is the slope of the map, and the refit F(x) = x + G is |G| |1 + s| / |s| from the fixed
    point (Aitken's error estimate; Ortega & Rheinboldt 2000, sec. 12.1)."""
    dx = x - x_prev
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = (g - g_prev) / dx
    slope = np.where(np.isfinite(slope), slope, np.nan)
    return np.where(np.abs(dx) > 1e-9, np.clip(slope, *SECANT_SLOPE_BOUNDS), np.nan)


def _widen(ci: Array | None, est: Array, factor: Array) -> Array | None:
    """95 % intervals (C, 2) widened by ``factor`` (C,): in log for a two-sided interval, linearly about the estimate
    for a one-sided one [0, hi] (its lower end stays 0)."""
    if ci is None:
        return None
    c = np.array(ci, dtype=np.float64).reshape(-1, 2)
    e = np.asarray(est, dtype=np.float64).reshape(-1)
    two = np.isfinite(c[:, 0]) & (c[:, 0] > 0) & np.isfinite(c[:, 1]) & (e > 0)
    with np.errstate(all="ignore"):
        lo2 = e * (c[:, 0] / e) ** factor
        hi2 = e * (c[:, 1] / e) ** factor
    hi1 = e + factor * (c[:, 1] - e)
    out = c.copy()
    out[two, 0], out[two, 1] = lo2[two], hi2[two]
    one = ~two & np.isfinite(c[:, 1])
    out[one, 1] = np.maximum(hi1[one], c[one, 1])
    return out


def _hull(a: Array, b: Array | None) -> Array:
    """Elementwise hull of two interval arrays (C, 2) (non-finite ends of ``b`` ignored)."""
    if b is None:
        return a
    bb = np.asarray(b, dtype=np.float64).reshape(-1, 2)
    out = np.array(a, dtype=np.float64).reshape(-1, 2)
    out[:, 0] = np.where(np.isfinite(bb[:, 0]), np.minimum(out[:, 0], bb[:, 0]), out[:, 0])
    out[:, 1] = np.where(np.isfinite(bb[:, 1]), np.maximum(out[:, 1], bb[:, 1]), out[:, 1])
    return out


def _flat_likelihood(rendered: list[tuple[Array, Array]], obs: Array, scale: Array, ssp_ci: Array, sa_ci: Array,
                     stated: bool) -> tuple[Array, Array, list[str]]:
    """The renders themselves as likelihood samples: every rendered point whose objective (one metric: the last)
    is within RESOLVED_OBJECTIVE of the best render's is consistent with the data. Where those points span more than
    a factor FLAT_SPAN in a parameter, the likelihood is flat on that scale and the local (Jacobian) interval does
    not bound it: the interval becomes the parameter's search range (measured: a 5 mm skimmilk pyramid under a sky,
    renders at 18x and 68x the true sigma_s' fit equally, the Jacobian interval 14.8-153 /mm missed the truth 0.70).
    With a stated noise level the best render must also fit: chi-square per observation above MISFIT_CHI2 says the
    optimum lies among none of the rendered points (same scene: chi2/n 4.6 at both renders, the truth's ~1), and the
    intervals become the search ranges too. Returns the intervals and, per channel, why they were widened ("" where
    not)."""
    n_ch = obs.shape[1]
    out_s = np.array(ssp_ci, dtype=np.float64).reshape(-1, 2)
    out_a = np.array(sa_ci, dtype=np.float64).reshape(-1, 2)
    why = [""] * n_ch
    if not rendered:
        return out_s, out_a, why
    with np.errstate(all="ignore"):
        obj = np.stack([_huber_sum((obs - q) / scale) for _, q in rendered])  # (renders, C)
    pts = np.exp(np.stack([t for t, _ in rendered]))  # (renders, C, 2)
    for c in range(n_ch):
        if not np.isfinite(obj[:, c]).any():  # (no render compared: nothing to read; nanmin would warn)
            continue
        ok = np.isfinite(obj[:, c]) & (obj[:, c] <= np.nanmin(obj[:, c]) + RESOLVED_OBJECTIVE)
        span = pts[ok, c].max(axis=0) / pts[ok, c].min(axis=0) if ok.sum() >= 2 else np.ones(2)
        msg = []
        if span[0] > FLAT_SPAN:
            out_s[c] = (1e-3, 1e3)
            msg.append(f"renders at sigma_s' {pts[ok, c, 0].min():.3g}-{pts[ok, c, 0].max():.3g} /mm fit the data "
                       "equally: sigma_s' not bounded (interval: the search range)")
        if span[0] > FLAT_SPAN or span[1] > FLAT_SPAN:
            out_a[c] = (0.0, 50.0)
            if span[1] > FLAT_SPAN:
                msg.append(f"renders at sigma_a {pts[ok, c, 1].min():.3g}-{pts[ok, c, 1].max():.3g} /mm fit the "
                           "data equally: sigma_a not bounded (interval: the search range)")
        n_rows = int(np.sum(np.isfinite((obs[:, c] - rendered[0][1][:, c]) / scale[:, c])))
        chi2_n = 2.0 * float(np.nanmin(obj[:, c])) / max(n_rows, 1)
        if stated and chi2_n > MISFIT_CHI2 and span[0] <= FLAT_SPAN:
            out_s[c], out_a[c] = (1e-3, 1e3), (0.0, 50.0)
            msg.append(f"the best render fits the observations with chi-square / n = {chi2_n:.3g} (> {MISFIT_CHI2:g}):"
                       " the optimum is not among the rendered points (intervals: the search ranges)")
        why[c] = "; ".join(msg)
    return out_s, out_a, why


def _derivative_noise_factor(corr: Any, metric: Array) -> Array:
    """(C, 2) factors >= 1 by which the intervals widen because the reference's derivatives are Monte Carlo
    estimates: the information the fit used, I_fit = sum w J J^T (J the corrected model's smoothed derivatives), over
    the unbiased estimate of the reference's own, I = sum w (Q' Q'^T - Cov Q') (errors in variables: the noise of
    Q' inflates Q' Q'^T by its variance). Where the derivatives are noise, I is ~0 and the factor infinite: the
    interval spans the parameter's whole range. f_k = sqrt((I^-1)_kk / (I_fit^-1)_kk)."""
    n_ch = corr.q.shape[1]
    out = np.ones((n_ch, 2))
    if corr.dq is None or corr.dq_se is None or corr.jac is None:
        return out
    w = 1.0 / metric ** 2
    for c in range(n_ch):
        ok = np.isfinite(w[:, c]) & np.all(np.isfinite(corr.dq[:, c]), axis=1) & np.all(
            np.isfinite(corr.dq_se[:, c]), axis=1) & np.all(np.isfinite(corr.jac[:, c]), axis=1)
        if ok.sum() < 3:
            continue
        wc = w[ok, c]
        j_fit, j_raw, se = corr.jac[ok, c], corr.dq[ok, c], corr.dq_se[ok, c]
        i_fit = (j_fit * wc[:, None]).T @ j_fit
        i_true = (j_raw * wc[:, None]).T @ j_raw - np.diag(np.sum(wc[:, None] * se ** 2, axis=0))
        try:
            v_fit = np.diag(np.linalg.pinv(i_fit))
            ev = np.linalg.eigvalsh(i_true)
            if ev.min() > 1e-9 * max(ev.max(), 1e-300):
                v_true = np.diag(np.linalg.inv(i_true))
            else:  # the correlation is not resolved: each parameter on its own information (its diagonal)
                d_true, d_fit = np.diag(i_true), np.diag(i_fit)
                v_true = np.where(d_true > 0, 1.0 / np.where(d_true > 0, d_true, 1.0), np.inf)
                v_fit = np.where(d_fit > 0, 1.0 / np.where(d_fit > 0, d_fit, 1.0), np.inf)
        except np.linalg.LinAlgError:
            continue
        with np.errstate(all="ignore"):
            f = np.sqrt(np.where(v_fit > 0, v_true / v_fit, np.inf))
        out[c] = np.where(np.isfinite(f) & (f > 0), np.maximum(f, 1.0), 1e6)
    return out


def _cover(ci: Array | None, points: Array) -> Array | None:
    """Intervals (C, 2) stretched to contain ``points`` (C, P) (linear values) and their mirror images about the
    interval's centre point set (the distance still to go can be as large as the last step)."""
    if ci is None:
        return None
    c = np.array(ci, dtype=np.float64).reshape(-1, 2)
    lo_p, hi_p = np.min(points, axis=1), np.max(points, axis=1)
    span = hi_p / np.maximum(lo_p, 1e-300)
    c[:, 0] = np.where(c[:, 0] > 0, np.minimum(c[:, 0], lo_p / span), c[:, 0])
    c[:, 1] = np.maximum(c[:, 1], hi_p * span)
    return c
