"""Sample-count levels of the reference loop (issue 19: "adaptive sample counts that stop when the correction's noise
is below the fit's"): which level of a Monte Carlo reference renderer with ``spp_levels`` the loop of
:func:`estimation.model_correction.estimate_with_reference` renders at, and when it escalates to the top level.

The render's noise, carried to the parameters through the weighted least-squares fit, is compared with the fit's own
standard errors (:func:`_noise_matched_level`); the loop renders at the cheapest level whose noise is at most
:data:`RENDER_NOISE_FRACTION` of them, converges at :data:`FINAL_SPP_FRACTION` of the top at least, and where it has
not converged within its budget continues with :data:`TOP_SPP_RENDERS` renders at the top level (the zoo, docs/
model-error.md, "Fewer and smaller renders (issue 19, acceptance line 2)").
"""
from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .reference_intervals import _widen
from .single_image import MAX_OK_INTERVAL_RATIO

__all__ = ["RENDER_NOISE_FRACTION", "FINAL_SPP_FRACTION", "TOP_SPP_RENDERS", "wide_ahead"]

Array = NDArray[np.float64]

#: a reference with sample-count levels (issue 19): after its first render, at the cheapest level, the loop renders at
#: the cheapest level whose noise, carried to the parameters (sd ~ 1/sqrt(spp)), is at most this fraction of the plain
#: fit's standard error, every channel and parameter: it then adds at most 1 + 0.5^2 = 1.25x to their variance
#: (~12 % to an interval, which carries it: the refits weigh the correction's variance)
RENDER_NOISE_FRACTION: float = 0.5
#: re-checked after every refit (the refit's errors; never lowered) up to the final level, the first of at least this
#: fraction of the top spp, where the loop converges and ends (cheap renders' bias: zoo z09, z27, z18; issue 19)
FINAL_SPP_FRACTION: float = 0.5
#: where the loop has not converged within its budget on cheaper renders, it continues with up to this many renders
#: at the top level before the ridge line search: the noise rule bounds a cheap render's variance, not the offset its
#: fixed seed's realization gives the fixed point (zoo, adaptive vs legacy on the same frames: z27 -12.9 % vs +4.3 %
#: after five renders at 16 spp, z11 +10.8 % vs +4.2 %, its line search started from +79 % instead of +33 %)
TOP_SPP_RENDERS: int = 3


def _noise_matched_level(reference: Any, q: Array, se: Array, jac: Array, metric: Array, se_fit: Array,
                         spp0: float | None = None) -> tuple[int, float]:
    """The cheapest sample-count level of ``reference`` whose render noise, carried to the parameters, is at most
    :data:`RENDER_NOISE_FRACTION` of the fit's standard errors ``se_fit`` (C, 2; log parameters, the plain fit's).

    The render's per-patch standard errors ``se`` (m, C) at ``reference.current_spp`` enter the weighted
    least-squares solution through the model's Jacobian ``jac`` (m, C, 2) with weights 1 / ``metric``^2: its
    covariance is A^-1 (J^T W S W J) A^-1, A = J^T W J (the sandwich of a linear fit; Seber & Wild, Nonlinear
    Regression, 1989, sec. 2.1); it scales as 1 / spp. Parameters whose ``se_fit`` is not finite are left out;
    none left: the top level. ``spp0``: the sample count ``se`` was rendered at (default ``reference.current_spp``).
    Returns (level, the largest ratio render sd / fit se at the rendered spp)."""
    n_ch = q.shape[1]
    ratios = []
    for c in range(n_ch):
        ok = np.isfinite(q[:, c]) & np.isfinite(se[:, c]) & np.isfinite(metric[:, c]) & (metric[:, c] > 0) \
            & np.all(np.isfinite(jac[:, c]), axis=1)
        if ok.sum() < 3:
            continue
        j = jac[ok, c]
        w = 1.0 / metric[ok, c] ** 2
        a = (j * w[:, None]).T @ j
        b = (j * (w ** 2 * se[ok, c] ** 2)[:, None]).T @ j
        try:
            a_inv = np.linalg.inv(a)
        except np.linalg.LinAlgError:
            continue
        sd = np.sqrt(np.maximum(np.diag(a_inv @ b @ a_inv), 0.0))
        for k in range(2):
            if np.isfinite(se_fit[c, k]) and se_fit[c, k] > 0 and np.isfinite(sd[k]):
                ratios.append(sd[k] / se_fit[c, k])
    levels = [int(x) for x in reference.spp_levels]
    if not ratios:
        return len(levels) - 1, float("nan")
    r = float(max(ratios))
    spp0 = float(reference.current_spp if spp0 is None else spp0)
    for i, n in enumerate(levels):
        if r * np.sqrt(spp0 / n) <= RENDER_NOISE_FRACTION:
            return i, r
    return len(levels) - 1, r


def wide_ahead(ci_per_mm: ArrayLike | None, log_estimate: ArrayLike, factor: ArrayLike,
               max_ratio: float | None = None) -> NDArray[np.bool_]:
    """Per channel: would the refit's sigma_s' interval ``ci_per_mm`` (C, 2), widened by ``factor`` (C,) about the
    estimate exp(``log_estimate``) as the loop's end widens it (:func:`estimation.reference_intervals._widen`), be
    wider than ``max_ratio`` (hi / lo; default :data:`estimation.single_image.MAX_OK_INTERVAL_RATIO`, the "ok" line
    of :func:`estimation.single_image.parameter_status`)? No interval, or none bounded: True."""
    ratio_max = MAX_OK_INTERVAL_RATIO if max_ratio is None else float(max_ratio)
    est = np.exp(np.asarray(log_estimate, dtype=np.float64).reshape(-1))
    ci = _widen(None if ci_per_mm is None else np.asarray(ci_per_mm, dtype=np.float64), est,
                np.asarray(factor, dtype=np.float64).reshape(-1))
    if ci is None:
        return np.ones(est.shape, bool)
    with np.errstate(all="ignore"):
        return ~((ci[:, 0] > 0) & (ci[:, 1] <= ratio_max * ci[:, 0]))


def _to_top_level(reference: Any, level_info: dict[str, Any] | None, iteration: int, why: str) -> bool:
    """Set ``reference`` to its top sample-count level for :data:`TOP_SPP_RENDERS` renders and note it in
    ``level_info`` (the estimate's ``extra["sample_count_levels"]``). Returns True (the loop's "escalated" flag)."""
    reference.set_level(int(reference.n_levels) - 1)
    if level_info is not None:
        level_info.update(chosen_spp=int(reference.current_spp), top_level_renders_from=iteration + 1,
                          top_level_why=why)
    return True
