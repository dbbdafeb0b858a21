"""The corrected model of the reference loop, built from one render (:mod:`estimation.model_correction`, step 3).

At a rendered point theta_i the fast model M is corrected to F_i(theta) = kappa M(theta_i + B (theta - theta_i)) + a
+ D phi(theta - theta_i) (the module docstring of :mod:`estimation.model_correction` has the algorithm): per patch a
multiplicative kappa = Q / M where the render has signal, an additive a = Q - M where it has not, both averaged over
neighbouring patches of the same face (:func:`_smoothing_operator`, :func:`_weighted_mean`); the parameter map B
(space mapping, :func:`_parameter_map`) and the derivative correction D (:func:`_adaptive_slope`). Split out of
model_correction.py (which keeps the iteration) by job.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import csr_matrix
from scipy.spatial import cKDTree

from .single_image import Patches

Array = NDArray[np.float64]

#: a patch's reference enters multiplicatively (kappa = Q / M) only when Q exceeds this many standard errors
SIGNAL_SE: float = 5.0

#: the derivative of the correction is averaged over growing neighbourhoods (in patch spacings) until its standard
#: error is below SLOPE_REL_SE of the derivative's magnitude (:func:`_adaptive_slope`)
SLOPE_SMOOTH_SPACINGS: tuple[float, ...] = (1.5, 3.0, 6.0, 12.0)
SLOPE_REL_SE: float = 0.2


@dataclass
class _Correction:
    """The reference at one rendered point and the corrected model built from it (rows = visible patches)."""

    theta: Array      # (C, 2) log parameters rendered
    q: Array          # (m, C)
    q_se: Array       # (m, C)
    kappa: Array      # (m, C) smoothed; 1 on additive rows
    kappa_var: Array
    shift: Array      # (m, C) additive part a (0 on multiplicative rows)
    shift_var: Array
    slope: Array      # (m, C, 2) D = Q' - kappa M' B (0 without derivatives)
    matrix: Array     # (C, 2, 2) the parameter map B (identity without derivatives)
    objective: Array  # (C,) the reference's robust objective at theta
    additive: NDArray[np.bool_]
    dq: Array | None = None     # (m, C, 2) the reference's derivatives as rendered (unsmoothed)
    dq_se: Array | None = None
    jac: Array | None = None    # (m, C, 2) the corrected model's derivatives at theta: kappa M' B + D


def _visible_rows(values: ArrayLike, name: str, patches: Patches, n_ch: int, tail: tuple[int, ...] = ()) -> Array:
    a = np.asarray(values, dtype=np.float64)
    if a.ndim == 1 + len(tail):
        a = a[:, None]
    vis = patches.visible_index
    k_all = patches.centers_mm.shape[0]
    if a.ndim != 2 + len(tail) or a.shape[0] not in (vis.size, k_all) or a.shape[2:] != tail:
        raise ValueError(f"{name} has shape {np.shape(values)}; expected ({vis.size}, C{''.join(f', {t}' for t in tail)})"
                         f" visible patches or ({k_all}, C{''.join(f', {t}' for t in tail)}) patches")
    if a.shape[0] == k_all and k_all != vis.size:
        a = a[vis]
    if a.shape[1] not in (1, n_ch):
        raise ValueError(f"{name} has {a.shape[1]} channels; expected 1 or {n_ch}")
    return np.array(np.broadcast_to(a, (a.shape[0], n_ch) + tail))


def _smoothing_operator(patches: Patches, radius_mm: float, cos_min: float = float(np.cos(np.radians(25.0)))
                        ) -> csr_matrix | None:
    """(m, m) 0/1 neighbour operator over the visible patches (self included): patches within ``radius_mm``
    whose normals differ by less than 25 deg (a mean never straddles a sharp edge). None when radius_mm <= 0."""
    if not radius_mm > 0:
        return None
    vis = patches.visible_index
    x = patches.centers_mm[vis]
    n = patches.normals[vis]
    pairs = cKDTree(x).query_pairs(float(radius_mm), output_type="ndarray")
    keep = np.einsum("ij,ij->i", n[pairs[:, 0]], n[pairs[:, 1]]) >= cos_min
    i = np.concatenate([pairs[keep, 0], pairs[keep, 1], np.arange(vis.size)])
    j = np.concatenate([pairs[keep, 1], pairs[keep, 0], np.arange(vis.size)])
    return csr_matrix((np.ones(i.size), (i, j)), shape=(vis.size, vis.size))


def _weighted_mean(op: csr_matrix | None, value: Array, var: Array, use: NDArray[np.bool_]) -> tuple[Array, Array]:
    """Inverse-variance neighbour mean of ``value`` over the rows where ``use`` (per column) and its variance; rows
    without a usable neighbour get NaN."""
    ok = use & np.isfinite(value) & np.isfinite(var) & (var > 0)
    w = np.where(ok, 1.0 / np.where(ok, var, 1.0), 0.0)
    if op is None:
        den, num = w, w * np.where(ok, value, 0.0)
    else:
        den = op @ w
        num = op @ (w * np.where(ok, value, 0.0))
    have = den > 0
    return np.where(have, num / np.where(have, den, 1.0), np.nan), np.where(have, 1.0 / np.where(have, den, 1.0),
                                                                            np.nan)


def _adaptive_slope(raw: Array, raw_se: Array, scale: Array, smoothers: list[csr_matrix | None]) -> Array:
    """Neighbour means of the correction's derivative ``raw`` (m, C, 2), per patch over the smallest of the
    ``smoothers`` (growing radii) whose mean has a standard error below :data:`SLOPE_REL_SE` x ``scale`` (the
    magnitude of the whole derivative there), else the largest. The score-function derivatives are noisy per patch
    (d/d log sigma_s' ~100-200 % at 128 spp) and their noise, squared in the fit's normal equations, would shorten
    every Gauss-Newton step (regression dilution: measured steps of ~0.6 of the way on an index-matched cube)."""
    out = np.zeros_like(raw)
    done = np.zeros(raw.shape, bool)
    ok = np.isfinite(raw) & np.isfinite(raw_se)
    v = np.where(ok, raw, 0.0)
    v2 = np.where(ok, raw_se ** 2, 0.0)
    for k, op in enumerate(smoothers):
        n_raw = ok.astype(np.float64)
        if op is None:
            cnt, mean_num, var_num = n_raw, v, v2
        else:
            shp = raw.shape
            flat = lambda a: a.reshape(shp[0], -1)  # noqa: E731
            cnt = (op @ flat(n_raw)).reshape(shp)
            mean_num = (op @ flat(v)).reshape(shp)
            var_num = (op @ flat(v2)).reshape(shp)
        have = cnt > 0
        mean = np.where(have, mean_num / np.where(have, cnt, 1.0), 0.0)
        se = np.where(have, np.sqrt(var_num) / np.where(have, cnt, 1.0), np.inf)
        take = ~done & have & ((se <= SLOPE_REL_SE * scale) | (k == len(smoothers) - 1))
        out[take] = mean[take]
        done |= take
    return out


def _parameter_map(dq: Array, dq_se: Array, dm: Array, use: NDArray[np.bool_], weight: Array) -> Array:
    """Per channel the 2 x 2 map B with Q' ~ (kappa M') B over the patches: the reference responds to the parameters
    as the fast model responds to B times them (space mapping; Bandler et al. 1994, "Space mapping technique for
    electromagnetic optimization", IEEE T-MTT 42(12)). Weighted least squares (the derivative noise enters linearly:
    no regression dilution), each column then shrunk towards the identity's by the positive-part James-Stein factor
    1 - tr Var / |B_ls - I|^2 (Var from the derivatives' standard errors, the sandwich of the least squares): a map
    the Monte Carlo derivatives do not resolve (at 32 spp the column of d/d log sigma_s' moved by ~1 between renders)
    stays the fast model's own (B = I, the plain defect correction)."""
    n_ch = dq.shape[1]
    out = np.broadcast_to(np.eye(2), (n_ch, 2, 2)).copy()
    for c in range(n_ch):
        ok = use[:, c] & np.isfinite(weight[:, c]) & np.all(np.isfinite(dm[:, c]), axis=1) & np.all(
            np.isfinite(dq_se[:, c]), axis=1)
        if ok.sum() < 3:
            continue
        w = weight[ok, c]
        x, y, se = dm[ok, c], dq[ok, c], dq_se[ok, c]
        xtx = (x * w[:, None]).T @ x
        lam = 1e-3 * max(float(np.trace(xtx)) / 2.0, 1e-300)
        try:
            inv = np.linalg.inv(xtx + lam * np.eye(2))
        except np.linalg.LinAlgError:
            continue
        b = inv @ ((x * w[:, None]).T @ y + lam * np.eye(2))  # (2 in, 2 out): Q' ~ M' b
        for j in range(2):
            meat = (x * (w * w * se[:, j] ** 2)[:, None]).T @ x
            var_tr = float(np.trace(inv @ meat @ inv))
            dev = b[:, j] - np.eye(2)[:, j]
            dev2 = float(dev @ dev)
            shrink = max(0.0, 1.0 - var_tr / dev2) if dev2 > 0 else 0.0
            b[:, j] = np.eye(2)[:, j] + shrink * dev
        if np.all(np.isfinite(b)):
            out[c] = b  # theta_c = theta_i + B (theta - theta_i), so d(M o P)/d theta = M' B (rows: Q'_row ~ M'_row B)
    return out


def _build(theta: Array, q: Array, se: Array, dq: Array | None, dq_se: Array | None, m: Array, dm: Array,
           smoother: csr_matrix | None, slope_smoothers: list[csr_matrix | None], objective: Array,
           weight: Array) -> _Correction:
    good = np.isfinite(q) & np.isfinite(se) & np.isfinite(m)
    mult = good & (q > SIGNAL_SE * se) & (m > 0) & (q > 0)
    safe_m = np.where(mult, m, 1.0)
    kappa_raw = np.where(mult, q / safe_m, np.nan)
    kvar_raw = np.where(mult, (se / safe_m) ** 2, np.nan)
    # the smoothed corrections are means over ~n neighbours, but neighbours share them: their errors are correlated,
    # so each patch keeps the variance of its own render value (not 1/n of it), which is what the refit's sum over
    # patches sees (with the mean's variance the reference noise entered the intervals ~sqrt(n) = 2.6x too small)
    kappa, _ = _weighted_mean(smoother, kappa_raw, kvar_raw, mult)
    kappa_var = np.where(np.isfinite(kvar_raw), kvar_raw, (se / np.where(m > 0, m, np.inf)) ** 2)
    add = good & ~(mult & np.isfinite(kappa))
    shift, _ = _weighted_mean(smoother, q - m, np.maximum(se, 1e-300) ** 2, add)
    shift_var = se ** 2
    kappa = np.where(add, 1.0, kappa)
    kappa_var = np.where(add, 0.0, kappa_var)
    shift = np.where(add, np.where(np.isfinite(shift), shift, q - m), 0.0)
    shift_var = np.where(add, np.where(np.isfinite(shift_var), shift_var, se ** 2), 0.0)
    n_ch = q.shape[1]
    matrix = np.broadcast_to(np.eye(2), (n_ch, 2, 2)).copy()
    if dq is None or dq_se is None:
        slope = np.zeros(q.shape + (2,))
    else:
        matrix = _parameter_map(dq, dq_se, kappa[..., None] * dm, good & np.all(np.isfinite(dq), axis=2), weight)
        raw = np.where(good[..., None], dq - np.einsum("mck,ckj->mcj", kappa[..., None] * dm, matrix), np.nan)
        # the magnitude the noise is judged against: the derivative as the widest neighbourhood sees it (low noise)
        wide = _adaptive_slope(np.where(good[..., None], dq, np.nan), dq_se, np.zeros_like(dq), slope_smoothers[-1:])
        scale = np.abs(wide)
        scale = np.maximum(scale, 0.05 * np.nanmax(np.where(good[..., None], scale, np.nan), axis=0, keepdims=True))
        slope = _adaptive_slope(raw, dq_se, np.nan_to_num(scale, nan=np.inf), slope_smoothers)
    bad = ~good
    kappa[bad], kappa_var[bad], shift[bad], shift_var[bad] = np.nan, np.nan, np.nan, np.nan
    jac = None if dq is None else np.einsum("mck,ckj->mcj", kappa[..., None] * dm, matrix) + slope
    return _Correction(theta.copy(), q, se, kappa, kappa_var, shift, shift_var, slope, matrix, objective, add & good,
                       dq, dq_se, jac)
