"""The direct method's per-channel fit under a noise model: observation weights, a robust loss, the refits.

Noise model of an observation l_j (in the units of the fitted l = pi c L / F_t):

    var_j = sigma_j^2 + (model_error * p_j)^2,

sigma_j the stated per-observation standard deviation (shot + read noise through the sampling window, a per-pixel
standard-error image, Monte Carlo standard errors) and p_j the model's prediction: the second term keeps bright
observations from outweighing the rest by more than the model can be trusted (a relative model error of
``model_error`` rms), the first keeps dim and zero observations finite-weight data — a pixel that reads exactly 0
carries the information "below sigma_j", not an infinitely precise zero. Without a stated sigma the weights are
relative, sd_j = p_j + floor * max p (the model error alone), as before.

Robust loss: Huber on the normalized residuals z_j = (p_j - l_j) / sd_j by iteratively reweighted least squares
(Huber 1981, "Robust statistics", ch. 7; Holland & Welsch 1977): weights min(1, k s / |z_j|) with k =
:data:`HUBER_K` times the residual scale s = 1.4826 median |z| (never below 1 when sigma is stated), so a single
heavy-tailed pixel (a Monte Carlo firefly, a hot pixel, a speck of dust: 70x the 99th percentile is seen in
renders and photographs) cannot steer the fit, while the bulk of the residuals, systematic misfit included, keeps
its weight. Two reweighting passes (the weights settle: measured changes of the parameters < 1e-3 relative
after the second), each a fit without the trust-region polish and the profile scan; the last fit has both.

A warm refit (``box`` and ``start_hint`` given: the reference loop's corrected fit inside its trust region, about
the previous solution; issue 19) skips the first fit: its weights come from the prediction at the hint, every fit
starts from the last one on a local grid (:func:`.fit._fit_channel`'s ``local``), and a reweighting pass is run
only while it changes the weights by more than :data:`WEIGHT_RTOL` (relative, any observation). Measured on z10's
seven refits (docs/model-error.md, "Fewer and smaller renders"): 2-3 fits instead of 4, parameters within
1e-3 of their standard errors of the cold refit's.

Every fit of a channel sees the same system (``matrix``, the QR-reduced direct system), optionally a data slope
(the reference-corrected fit, :class:`.fit._Problem`) and a search box (its trust region).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .fit import _ChannelFit, _fit_channel, _Problem

Array = NDArray[np.float64]

#: Huber threshold in units of the robust residual scale (2.5: only clear outliers lose weight; at Gaussian noise
#: 1.2 % of the data are touched, and the efficiency is > 99 %)
HUBER_K = 2.5
#: relative floor of the data-based weights of the first fit (which only sets the weights of the next): zero and
#: near-zero pixels must not dominate it
FIRST_FIT_FLOOR = 0.05
ROBUST_PASSES = 2
#: a warm refit's reweighting stops once no observation's weight moved by more than this (relative)
WEIGHT_RTOL = 1e-2


@dataclass(frozen=True)
class WeightedFit:
    """A channel's final fit, the prediction there, the final standard deviations and robust weights, and the
    model evaluations spent on the preliminary fits."""

    fit: _ChannelFit
    pred: Array
    sd: Array
    robust_weight: Array
    nfev_extra: int


def huber_weights(z: Array, scale: float, k: float = HUBER_K) -> Array:
    """IRLS weights min(1, k scale / |z|) of the Huber loss (1 where z = 0)."""
    a = np.abs(z)
    thr = k * scale
    return np.where(a > thr, thr / np.where(a > 0, a, 1.0), 1.0)


def robust_scale(z: Array, at_least: float = 0.0) -> float:
    """1.4826 median |z| (the normal-consistent MAD about 0), at least ``at_least``."""
    if z.size == 0:
        return max(at_least, 1.0)
    s = 1.4826 * float(np.median(np.abs(z)))
    return max(s, at_least) if s > 0 else max(at_least, float(np.sqrt(np.mean(z ** 2))) or 1.0)


def _sd(pred: Array, sigma: Array | None, model_error: float, noise_floor: float) -> Array:
    p = np.abs(pred)
    if sigma is None:
        return p + noise_floor * max(float(np.max(p)), 1e-300)
    return np.sqrt(sigma ** 2 + (model_error * p) ** 2)


def fit_direct_channel(vector_fn: Any, matrix: Array, l: Array, sigma: Array | None, *, sa_floor: float,
                       model_error: float, noise_floor: float, robust: bool, profile: bool,
                       start_hint: Array | None, slope: Array | None = None, theta_ref: Array | None = None,
                       box: tuple[Array, Array] | None = None, warm: bool = True) -> WeightedFit:
    """Fit one channel of the direct method: a first fit with data-based weights, then weights from the
    prediction (module docstring), ``robust`` Huber reweighting, and the final fit (profile scan, polish).

    ``matrix`` (m, n) and ``l`` (m,) are the system and data of the observed rows, ``sigma`` (m,) their stated
    standard deviations or None (relative weights), ``slope`` (m, 2) / ``theta_ref`` (2,) an optional data slope
    (:meth:`.fit._Problem.weighted`), ``box`` the search box in log parameters. With ``box`` and a finite
    ``start_hint`` the fit is a warm refit (module docstring) unless ``warm`` is False."""
    known = sigma is not None

    def problem(w: Array) -> _Problem:
        return _Problem.weighted(vector_fn, matrix, l, w, slope, theta_ref)

    def data_now(theta: Array) -> Array:
        if slope is None:
            return l
        # (phi of _Problem, without building and reducing a whole weighted problem for it)
        phi = _Problem(vector_fn, None, l, l.size, l, theta_ref=theta_ref).phi(
            np.asarray(theta, dtype=np.float64)[None, :])[0]
        return l - slope @ phi

    if warm and box is not None and start_hint is not None and np.all(np.isfinite(start_hint)):
        out = _warm_refit(vector_fn, matrix, l, sigma, problem, data_now, sa_floor=sa_floor, model_error=model_error,
                          noise_floor=noise_floor, robust=robust, profile=profile,
                          start_hint=np.asarray(start_hint, dtype=np.float64), box=box)
        if out is not None:
            return out
    floor0 = max(noise_floor, FIRST_FIT_FLOOR)
    sd = _sd(np.abs(l), sigma, model_error, floor0)
    first = _fit_channel(problem(1.0 / sd), sa_floor, profile=False, model_error=model_error, start_hint=start_hint,
                         polish=False, box=box, known_noise=known)
    extra = first.nfev
    h = np.ones_like(l)
    theta = first.theta
    passes = ROBUST_PASSES if robust else 0
    for k in range(passes + 1):
        if not np.all(np.isfinite(theta)):
            break
        pred = matrix @ vector_fn(theta[None, :])[:, 0]
        if np.max(np.abs(pred)) > 0:
            sd = _sd(pred, sigma, model_error, noise_floor)
        if robust:
            z = (pred - data_now(theta)) / sd
            h = huber_weights(z, robust_scale(z, 1.0 if known else 0.0))
        if k == passes:
            break
        mid = _fit_channel(problem(np.sqrt(h) / sd), sa_floor, profile=False, model_error=model_error,
                           start_hint=theta, polish=False, box=box, known_noise=known)
        extra += mid.nfev
        if np.all(np.isfinite(mid.theta)):
            theta = mid.theta
    hint = theta if np.all(np.isfinite(theta)) else start_hint
    final = _fit_channel(problem(np.sqrt(h) / sd), sa_floor, known_noise=known, profile=profile,
                         model_error=model_error, start_hint=hint, box=box)
    pred = (matrix @ vector_fn(final.theta[None, :])[:, 0] if np.all(np.isfinite(final.theta))
            else np.full_like(l, np.nan))
    return WeightedFit(final, pred, sd, h, extra)


def _warm_refit(vector_fn: Any, matrix: Array, l: Array, sigma: Array | None, problem: Any, data_now: Any, *,
                sa_floor: float, model_error: float, noise_floor: float, robust: bool, profile: bool,
                start_hint: Array, box: tuple[Array, Array]) -> WeightedFit | None:
    """:func:`fit_direct_channel` near a known solution (module docstring): weights (noise model and Huber) from the
    prediction at ``start_hint``, fits on the box's local grid from the last solution, reweighted until the weights
    settle (at most ROBUST_PASSES + 1 fits before the final one), the final fit with the profile scan and polish.
    None when the prediction at the hint is not usable (the caller then fits cold)."""
    known = sigma is not None

    def weights_at(theta: Array) -> tuple[Array, Array] | None:
        pred = matrix @ vector_fn(theta[None, :])[:, 0]
        if not (np.all(np.isfinite(pred)) and np.max(np.abs(pred)) > 0):
            return None
        sd = _sd(pred, sigma, model_error, noise_floor)
        h = np.ones_like(l)
        if robust:
            z = (pred - data_now(theta)) / sd
            h = huber_weights(z, robust_scale(z, 1.0 if known else 0.0))
        return sd, h

    theta = start_hint
    got = weights_at(theta)
    if got is None:
        return None
    sd, h = got
    extra = 0
    for _ in range((ROBUST_PASSES if robust else 0) + 1):
        w = np.sqrt(h) / sd
        mid = _fit_channel(problem(w), sa_floor, profile=False, model_error=model_error, start_hint=theta,
                           polish=False, box=box, known_noise=known, local=True)
        extra += mid.nfev
        if not np.all(np.isfinite(mid.theta)):
            break
        theta = mid.theta
        got = weights_at(theta)
        if got is None:
            break
        sd, h = got
        if np.max(np.abs(np.sqrt(h) / sd / w - 1.0)) <= WEIGHT_RTOL:
            break
    final = _fit_channel(problem(np.sqrt(h) / sd), sa_floor, known_noise=known, profile=profile,
                         model_error=model_error, start_hint=theta, box=box, local=True)
    pred = (matrix @ vector_fn(final.theta[None, :])[:, 0] if np.all(np.isfinite(final.theta))
            else np.full_like(l, np.nan))
    return WeightedFit(final, pred, sd, h, extra)
