"""Single-image estimates corrected by a reference renderer of the scene (analysis by synthesis).

Every profile model of :mod:`.single_image` — the dipoles and the Monte Carlo half-space table — predicts the
radiance of patch j as a sum over the other patches of a *flat, semi-infinite* profile R(|x_j - x_k|). On a
body whose size is comparable to the diffusion length the light does not behave like that: at a convex edge of
a cube, light that would diffuse on through the half-space beyond the edge leaves through the neighbouring face
instead. Measured on Monte Carlo frames of the seed's Table-1 material (marble-R, a 20 mm cube, one point
light; ``benchmarks/mc_single_image.py``): the table's prediction at the true parameters is right to 0.6 % more
than 5 mm from an edge but ~6 % off within 1 mm of one, and because nearly all the information about
sigma_s' sits near the edges (diffusion length ~8.7 mm), the table fit misses sigma_s' by -37 % and sigma_a by
-50 %.

This module removes that bias with a *reference renderer* that simulates the measurement — full light
transport in the known geometry, the same camera and the same sampling of the image at the patches — and a
multiplicative defect correction (a fixed-point iteration, as in analysis-by-synthesis inverse rendering;
Gkioulekas et al. 2013, "Inverse volume rendering with material dictionaries", ACM TOG 32(6), use Monte
Carlo renderings in the same role):

1. fit the fast model (``base_model``, default ``"mc-table"``): parameters p_0 = F(start);
2. render the reference at the current point p_i: radiance Q(p_i) and its standard error per observed patch; the
   fast model's prediction M(p_i); the correction kappa_i = Q(p_i) / M(p_i) per patch and channel, averaged over
   the neighbouring patches within ``smooth_spacings`` patch spacings whose normals differ by less than 25 deg
   (inverse-variance weights: the edge deficit varies over millimetres, the Monte Carlo noise from patch to
   patch);
3. refit the fast model to the corrected observations l / kappa_i (their standard error grows by kappa's):
   F(p_i). The next render point is p_i + lambda (F(p_i) - p_i) in log parameters (a relaxed Picard step),
   lambda = 1 per parameter, halved (down to 1/4) whenever that parameter's step reverses sign: the map
   overshoots on cubes (slope about -0.4 to -1 in sigma_s', a 2-cycle without relaxation).

Stop when the last refit is close to the fixed point in every parameter: its estimated distance, |G| |1 + s| / |s|
for the step G = F(p_i) - p_i and the secant slope s = (G_i - G_{i-1}) / (p_i - p_{i-1}) of G along the path
(|G| after the first render; the error estimate of Aitken's delta-squared process, s clipped to [-2, -0.1]), is
below ``rel_tol`` or below a quarter of the refit's standard error (its 95 % half-width / 1.96; in log for a
two-sided interval, in sigma_a itself for a one-sided profile interval [0, hi], whose log-width is infinite:
such a parameter used to count as settled at once) — or after ``max_iterations`` renders; the result is the last
refit. The former rule compared |G| itself with a quarter of the half-width; on a map of slope 0.6 the refit is
then still 1.5 steps from the fixed point, and it stopped a 4096-spp skin1 pyramid (below) at +16 % whose
fixed point is +4 %. Every render uses the same ``seed`` (common random numbers, a sample-average
approximation): the reference is then one fixed realisation, the iteration converges to its fixed point instead
of wandering with fresh noise, and that realisation's noise enters the refit's intervals through the corrected
standard errors.

If the observations are Q(p_true) plus noise, p_true is a fixed point up to that noise: kappa(p_true) makes the
fast model exact there. Measured on the 20 mm marble-R cube at 128 x 128 px (``benchmarks/mc_single_image.py``,
128-spp references of 17-28 s each on 2 shared cores): sigma_s' -36.8 % -> +18.8 % -> -1.5 % -> 0.0 %, sigma_a
-50 % -> -23 % -> -8.7 % -> -5.5 %, settled after 3 renders (secant slopes of G of about -1.2 in sigma_s', where the map overshoots,
and -0.8 in sigma_a put the last refit ~1 % from the fixed point); the former stopping rule rendered once more
(+1.0 %, -4.2 %).

How far the noise moves the fixed point depends on the scene. Linearised, F(p) - p = (M'^+ Q') (p* - p) +
noise, with M' and Q' the sensitivities of the fast model and of the reference to log p: the slope of the map is
dF/dp = I - M'^+ Q', and the fixed point is off by (M'^+ Q')^-1 times the refit's noise. Where the reference
responds to a parameter as the fast model does, that factor is 1; where it responds less, the iteration is slow
and the fixed point noisy. Measured on the 14 mm skin1-R pyramid under a sky map (64 x 64 px,
``tests/simulators/test_mc_frames_single_image.py``; forward differences of 8 % in log p at the truth, 4096-spp
frame, 1024-spp references): dF/dp = [[1.0, -0.4], [1.0, -0.4]] in (log sigma_s', log sigma_a) (entries 0.97-1.06
and -0.31 to -0.42 over 3 frame and 2 reference seeds) —
the refits move along the ridge of nearly constant albedo, where the map's slope is 0.6, and the fixed-point
error in log sigma_s' is ~3.5 G_s - G_a ~ 2 G_s for the refit's error G at the truth (G_a ~ 1.5 G_s along the
ridge), more once it is nonlinear. The standard deviation of G_s at the truth is ~0.05 from a 256-spp frame's
noise (3 frame seeds) and 0.08 from a 128-spp reference's (8 reference seeds; 0.03 at 1024 spp). Fixed points
reached (sigma_s' error, frame seeds 1, 2, 3; steps of seed 1):

| frame / reference spp | sigma_s' at the end | renders | seed 1 path |
|---|---|---|---|
| 256 / 128 | -42, -35, -56 % | 8, 8 (not settled), 7 | +24, +7.9, -6.0, -16, -26, -33, -37, -41, -42 % |
| 256 / 1024 | -1.6, +13.5, -29 % (still drifting) | 5, 4, 8 | +24, +21, +11, +4.0, +0.4, -1.6 % |
| 4096 / 1024 | +3.5, 0.0, +4.7 % | 6, 5, 5 | +30, +26, +16, +11, +6.3, +3.9, +3.5 % |

So the iteration converges there; at 256-spp frames the scene does not hold sigma_s' to 10 %. The refit's 95 %
interval (0.26-1.27 of the truth at the end of the 256/128 run, seed 1) is computed from M', not Q', and is too narrow by
the factor above along the ridge. The reported intervals are therefore widened to the fixed point's
(:func:`_propagate_intervals`): by max(1, 1/|s|) per parameter, s the last secant slope of G along the path
(slope 0.6 of the map: x2.5; on a synthetic reference of half the fast model's sensitivity the widened interval
matches the spread of the fixed point over noise seeds, tests/estimation/test_model_correction.py), the refit's
own intervals kept in ``extra["interval_propagation"]``. Also measured there and rejected: an Anderson /
multisecant step (type II, memory 2, capped at the larger of the Picard step and the refit's half-width)
extrapolated through the non-identified sigma_a of a marble pyramid under a point light to +98 % and ended 17-24 % off (3 of 3 seeds; the
Picard iteration: within 4 %); a per-parameter secant step diverged on the 4096-spp skin1 pyramid (-75 %), whose
first refit moves sigma_a by +22 points and sigma_s' by -3. A smoothing radius of kappa of 3 patch spacings
instead of 1.5 shifts G_s at the truth by +11 points (it blurs the edge deficit); equal instead of inverse-variance
smoothing weights, dropping kappa's variance from the refit's noise or a second-order (Jensen) correction of
1 / kappa move it by less than 1.5 points.

What this is not: a remedy for an unknown or wrong geometry (the reference uses the geometry the estimator is
given), nor free — each iteration is one full render. The result reports the fast model's bias *in this
scene* (``extra["model_bias"]``: the radiance ratio fast model / reference per patch — median, 5th and 95th percentiles
and the rms of its log), which is the honest measure of how wrong
the flat model was here, beside the table-level bias of :func:`estimation.single_image.model_bias`.

The reference renderer is any callable ``reference(sigma_s_prime_per_mm (C,), sigma_a_per_mm (C,), eta, seed)
-> (radiance (m or K, C), stderr (m or K, C))`` in the units of the observations (NaN where not observed);
``rig.mc_reference`` builds one from ``simulators.mc`` (this package imports nothing else of ours).
"""
from __future__ import annotations

import inspect
import time
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scipy.sparse import csr_matrix
from scipy.spatial import cKDTree

from .single_image import (Lights, Patches, SingleImageResult, estimate_single_image, predict_radiance,
                           sigma_a_verdict)

__all__ = ["ReferenceRenderer", "ReferenceStep", "estimate_with_reference"]

Array = NDArray[np.float64]


class ReferenceRenderer(Protocol):
    """Radiance of the observed patches under full light transport, with its standard error."""

    def __call__(self, sigma_s_prime_per_mm: Array, sigma_a_per_mm: Array, eta: float, seed: int
                 ) -> tuple[Array, Array]:
        """(radiance, stderr), each (m, C) over the visible patches or (K, C) over all patches; NaN where the
        reference has no value (the patch is then left out of the refit)."""
        ...


@dataclass(frozen=True)
class ReferenceStep:
    """One iteration: the parameters fitted after it and what the correction looked like."""

    iteration: int
    sigma_s_prime_per_mm: list[float]
    sigma_a_per_mm: list[float]
    render_seconds: float
    fit_seconds: float
    kappa_median: list[float]
    kappa_p05: list[float]
    kappa_p95: list[float]
    kappa_rel_stderr_median: list[float]
    change: float  # max relative change of the parameters in this step
    # the point the reference was rendered at in this step (empty for step 0, the base fit)
    rendered_sigma_s_prime_per_mm: list[float] = field(default_factory=list)
    rendered_sigma_a_per_mm: list[float] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def _visible_rows(values: ArrayLike, name: str, patches: Patches, n_ch: int) -> Array:
    a = np.asarray(values, dtype=np.float64)
    if a.ndim == 1:
        a = a[:, None]
    vis = patches.visible_index
    k_all = patches.centers_mm.shape[0]
    if a.ndim != 2 or a.shape[0] not in (vis.size, k_all):
        raise ValueError(f"{name} has shape {np.shape(values)}; expected ({vis.size}, C) visible patches or "
                         f"({k_all}, C) patches")
    if a.shape[0] == k_all and k_all != vis.size:
        a = a[vis]
    if a.shape[1] not in (1, n_ch):
        raise ValueError(f"{name} has {a.shape[1]} channels; expected 1 or {n_ch}")
    return np.array(np.broadcast_to(a, (a.shape[0], n_ch)))


def _smoothing_operator(patches: Patches, radius_mm: float, cos_min: float = float(np.cos(np.radians(25.0)))
                        ) -> csr_matrix | None:
    """Row-stochastic (m, m) neighbour-mean operator over the visible patches: patches within ``radius_mm`` whose
    normals differ by less than 25 deg (so a mean never straddles a sharp edge). None when radius_mm <= 0."""
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


def _smooth(op: csr_matrix | None, kappa: Array, kappa_var: Array) -> tuple[Array, Array]:
    """Inverse-variance weighted neighbour mean of kappa (NaN entries skipped) and the variance of that mean."""
    if op is None:
        return kappa, kappa_var
    ok = np.isfinite(kappa) & np.isfinite(kappa_var) & (kappa_var > 0)
    w = np.where(ok, 1.0 / np.where(ok, kappa_var, 1.0), 0.0)
    den = op @ w
    num = op @ (w * np.where(ok, kappa, 0.0))
    have = den > 0
    mean = np.where(have, num / np.where(have, den, 1.0), np.nan)
    var = np.where(have, 1.0 / np.where(have, den, 1.0), np.nan)
    return mean, var


#: the iteration stops when the refit's estimated distance to the fixed point is below this fraction of the
#: refit's own standard error (the 95 % half-width / 1.96) in every parameter, or below ``rel_tol``
SETTLE_SD_FRACTION: float = 0.25
_Z95 = 1.959963984540054
#: secant slope of G assumed where none was measured (map slope 1/2, as the stop rule assumes after one render)
_ASSUMED_SLOPE = -0.5
#: estimate_single_image's default identifiable_ratio (the widened sigma_a interval is judged by the same rule)
_IDENTIFIABLE_RATIO = float(inspect.signature(estimate_single_image).parameters["identifiable_ratio"].default)


def _settled(render_log: Array, new_log: Array, channels: NDArray[np.bool_], fit: SingleImageResult,
             rel_tol: float, remaining: Array | None = None) -> bool:
    """True when every parameter's refit is close to the fixed point against the refit's own uncertainty, so the
    iteration error is small beside the data's noise.

    ``render_log`` and ``new_log`` are log (sigma_s', sigma_a), shape (2, C), of the render point p and the refit
    F(p). ``remaining`` (2, C), default 1, is the refit's estimated distance to the fixed point per unit step:
    |1 + s| / |s| for a secant slope s of G = F - p (:func:`_secant_slope`; a map of slope 0.6 leaves 1.5 steps
    to go, one of slope -0.5 a third of one). That distance counts as settled when it is below ``rel_tol``
    (relative) or below :data:`SETTLE_SD_FRACTION` of the parameter's standard error, taken from its 95 %
    interval:

    - a two-sided interval (lo > 0): the distance in log against 0.5 log(hi / lo) / 1.96;
    - a one-sided interval [0, hi] (sigma_a's profile interval when the data cannot tell sigma_a from 0): the
      distance in sigma_a itself against (hi / 2) / 1.96. Its log-width is infinite — under the former rule such
      a parameter counted as settled at once whatever it did — and the Wald interval in log sigma_a is no
      remedy: there the likelihood is flat towards 0 and its curvature at the estimate (possibly at the floor,
      where any log step is tiny against it) says nothing about the interval. The profile interval is a
      statement on the linear scale, and on that scale its width hi is finite;
    - no finite interval: ``rel_tol`` only.
    """
    factor = np.ones_like(render_log) if remaining is None else np.asarray(remaining, dtype=np.float64)
    dist = np.abs(new_log - render_log) * factor
    ok = dist <= np.log1p(rel_tol)
    frac = SETTLE_SD_FRACTION / _Z95
    for row, ci in enumerate((fit.sigma_s_prime_ci_per_mm, fit.sigma_a_ci_per_mm)):
        if ci is None:
            continue
        c = np.asarray(ci, dtype=np.float64).reshape(-1, 2)
        lo, hi = c[:, 0], c[:, 1]
        two_sided = np.isfinite(lo) & np.isfinite(hi) & (lo > 0) & (hi > lo)
        one_sided = np.isfinite(hi) & (hi > 0) & ~(lo > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            half_log = 0.5 * np.log(hi / lo)
            dist_lin = np.abs(np.exp(new_log[row]) - np.exp(render_log[row])) * factor[row]
        ok[row] |= (two_sided & (dist[row] <= frac * half_log)) | (one_sided & (dist_lin <= frac * 0.5 * hi))
    return bool(np.all(ok[:, channels]))


#: bounds of the secant slope s = dG/dp of G(p) = F(p) - p (log parameters), i.e. of the map's slope 1 + s: from
#: -1 (a 2-cycle) to 0.9 (a slow drift, which leaves up to 9 steps to go)
SECANT_SLOPE_BOUNDS: tuple[float, float] = (-2.0, -0.1)


def _secant_slope(x_prev: Array, g_prev: Array, x: Array, g: Array) -> Array:
    """Per-parameter secant slope s = (G_k - G_{k-1}) / (x_k - x_{k-1}) of G(x) = F(x) - x in log parameters,
    clipped to :data:`SECANT_SLOPE_BOUNDS`; NaN where the two render points coincide.

    1 + s is the slope of the map F along the path, and the fixed point lies at x_k - G_k / s, so the refit
    F(x_k) = x_k + G_k is |G_k| |1 + s| / |s| from it (the error estimate behind Aitken's delta-squared process;
    Ortega & Rheinboldt 2000, "Iterative solution of nonlinear equations in several variables", SIAM, sec. 12.1
    on contraction-mapping error bounds)."""
    dx = x - x_prev
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = (g - g_prev) / dx
    slope = np.where(np.isfinite(slope), slope, np.nan)
    return np.where(np.abs(dx) > 1e-9, np.clip(slope, *SECANT_SLOPE_BOUNDS), np.nan)


def _finite_params(r: SingleImageResult) -> tuple[Array, Array, NDArray[np.bool_]]:
    ssp = np.asarray(r.sigma_s_prime_per_mm, dtype=np.float64)
    sa = np.asarray(r.sigma_a_per_mm, dtype=np.float64)
    ok = np.isfinite(ssp) & np.isfinite(sa) & (ssp > 0) & (sa > 0)
    if not ok.any():
        return ssp, sa, ok
    # channels without an estimate are rendered at a stand-in (their correction is not used)
    ssp = np.where(ok, ssp, np.median(ssp[ok]))
    sa = np.where(ok, sa, np.median(sa[ok]))
    return ssp, sa, ok


def _widen(ci: Array | None, est: Array, factor: Array) -> Array | None:
    """95 % intervals (C, 2) about the estimates (C,) widened by ``factor`` (C,): in log for a two-sided interval
    (lo > 0), linearly about the estimate for a one-sided one [0, hi] (its lower end stays 0)."""
    if ci is None:
        return None
    c = np.array(ci, dtype=np.float64).reshape(-1, 2)
    e = np.asarray(est, dtype=np.float64).reshape(-1)
    two = np.isfinite(c[:, 0]) & (c[:, 0] > 0) & np.isfinite(c[:, 1]) & (e > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        lo2 = e * (c[:, 0] / e) ** factor
        hi2 = e * (c[:, 1] / e) ** factor
    hi1 = e + factor * (c[:, 1] - e)
    out = c.copy()
    out[two, 0], out[two, 1] = lo2[two], hi2[two]
    one = ~two & np.isfinite(c[:, 1])
    out[one, 1] = np.maximum(hi1[one], c[one, 1])
    return out


def _propagate_intervals(result: SingleImageResult, slope: Array, identifiable_ratio: float
                         ) -> tuple[SingleImageResult, dict[str, Any]]:
    """Widen the refit's intervals of (sigma_s', sigma_a) to the fixed point's, by the map's slope along the path.

    The refit's intervals come from the fast model's sensitivity M': they describe F(p)'s noise e. The fixed point
    p* = F(p*) moves by (I - dF/dp)^-1 e (module docstring): by 1 / |s| per parameter for the secant slope s of
    G = F - p (``slope`` (2, C), :func:`_secant_slope`), the slope along the path the iteration took — which is
    the direction it converges slowest in, where the amplification is largest (a diagonal, along-path estimate
    of (I - dF/dp)^-1, the one the stop rule uses too). The factor is never below 1 (an overshooting map would
    narrow the interval, which a noisy secant does not justify); where no slope was measured (the iteration
    settled after one render) it is 2, the map slope of 1/2 the stop rule assumes then (:func:`_settled`).
    sigma_a's identifiability is judged again on the widened interval. Returns the widened result and what was
    done (``extra["interval_propagation"]``).
    """
    s = np.asarray(slope, dtype=np.float64)
    known = np.isfinite(s)
    with np.errstate(divide="ignore"):
        factor = np.where(known, np.maximum(1.0, 1.0 / np.abs(np.where(known, s, 1.0))), 1.0 / abs(_ASSUMED_SLOPE))
    ssp = np.asarray(result.sigma_s_prime_per_mm, dtype=np.float64)
    sa = np.asarray(result.sigma_a_per_mm, dtype=np.float64)
    info: dict[str, Any] = {
        "method": "refit intervals x max(1, 1/|s|), s the secant slope of F(p) - p along the path (log parameters;"
                  " s = -1/2 assumed where not measured)",
        "map_slope": np.where(known, 1.0 + s, np.nan).tolist(), "factor": factor.tolist(),
        "refit_sigma_s_prime_ci_per_mm": None if result.sigma_s_prime_ci_per_mm is None
        else np.asarray(result.sigma_s_prime_ci_per_mm).tolist(),
        "refit_sigma_a_ci_per_mm": None if result.sigma_a_ci_per_mm is None
        else np.asarray(result.sigma_a_ci_per_mm).tolist(),
        "slope_known": known.tolist()}
    ssp_ci = _widen(result.sigma_s_prime_ci_per_mm, ssp, factor[0])
    sa_ci = _widen(result.sigma_a_ci_per_mm, sa, factor[1])
    sa_ci_jac = _widen(result.sigma_a_ci_jacobian_per_mm, sa, factor[1])
    ident = list(result.sigma_a_identifiable_per_channel)
    reasons = result.identifiability_reason
    if sa_ci is not None and ident:
        verdicts = [sigma_a_verdict(float(lo), float(hi), identifiable_ratio) for lo, hi in sa_ci]
        ident = [v[0] for v in verdicts]
        reasons = "; ".join(f"channel {c}: {why} (fixed point: the refit's interval widened x{factor[1, c]:.2g})"
                            for c, (_, why) in enumerate(verdicts))
    out = replace(result, sigma_s_prime_ci_per_mm=ssp_ci, sigma_a_ci_per_mm=sa_ci,
                  sigma_a_ci_jacobian_per_mm=sa_ci_jac, sigma_a_identifiable=bool(ident) and all(ident),
                  sigma_a_identifiable_per_channel=tuple(ident), identifiability_reason=reasons)
    return out, info


def estimate_with_reference(observed_radiance: ArrayLike, patches: Patches, lights: Lights, eta: float,
                            reference: ReferenceRenderer, *, noise_sigma: ArrayLike | None = None,
                            base_model: str = "mc-table", max_iterations: int = 4, rel_tol: float = 0.01,
                            seed: int = 1, smooth_spacings: float = 1.5, min_iterations: int = 1,
                            **fit_kwargs: Any) -> SingleImageResult:
    """Fit ``base_model`` and correct it by ``reference`` renders of the scene until the parameters settle.

    ``observed_radiance``, ``noise_sigma``, ``patches``, ``lights``, ``eta`` and ``fit_kwargs`` are those of
    :func:`estimation.single_image.estimate_single_image` (``method`` defaults to "direct"). ``reference`` is
    called at most ``max_iterations`` times (at least ``min_iterations``), always with ``seed`` (common random
    numbers; the module docstring); each refit also starts from the point just rendered (``start_per_mm``). Returns the last fit, with ``model``
    set to ``"<base_model>+reference"`` and ``extra["reference"]`` holding every step (the refit's parameters, the
    point rendered, seconds, the correction's median / 5th / 95th percentile), ``extra["converged"]`` (the last
    refit was estimated close to the fixed point: :func:`_settled`) and ``extra["model_bias"]``, the base
    model's radiance over the reference's at the final parameters. The intervals of sigma_s' and sigma_a are the
    fixed point's: the refit's widened by the map's slope along the path (:func:`_propagate_intervals`;
    ``extra["interval_propagation"]`` keeps the refit's own and the factors); R_d and l_d keep the refit's. A
    failed base fit is returned as it is (falsy, its message prefixed); a reference that returns no usable value raises ``ValueError`` naming it.
    """
    if max_iterations < 1:
        raise ValueError("max_iterations must be >= 1")
    if not 1 <= min_iterations <= max_iterations:
        raise ValueError("min_iterations must lie in [1, max_iterations]")
    if not rel_tol > 0:
        raise ValueError("rel_tol must be > 0")
    if not smooth_spacings >= 0:
        raise ValueError("smooth_spacings must be >= 0")
    if "model" in fit_kwargs:
        raise TypeError("pass the fast model as base_model=, not model=")
    t_all = time.perf_counter()
    eta_f = float(eta)
    obs0 = np.asarray(observed_radiance, dtype=np.float64)
    n_ch = 1 if obs0.ndim == 1 else obs0.shape[1]
    obs = _visible_rows(obs0, "observed_radiance", patches, n_ch)
    sig = None if noise_sigma is None else _visible_rows(noise_sigma, "noise_sigma", patches, n_ch)

    t0 = time.perf_counter()
    result = estimate_single_image(obs, patches, lights, eta_f, model=base_model, noise_sigma=sig, **fit_kwargs)
    if not result:
        return replace(result, message=f"base fit ({base_model}) failed: {result.message}")
    steps = [ReferenceStep(0, np.asarray(result.sigma_s_prime_per_mm).tolist(),
                           np.asarray(result.sigma_a_per_mm).tolist(), 0.0, time.perf_counter() - t0,
                           [1.0] * n_ch, [1.0] * n_ch, [1.0] * n_ch, [0.0] * n_ch, np.inf)]
    spacing = patches.spacing_mm if patches.spacing_mm > 0 else float(np.sqrt(np.median(patches.areas_mm2)))
    smoother = _smoothing_operator(patches, smooth_spacings * spacing)
    converged = False
    kappa_use = np.ones_like(obs)
    render_log: Array | None = None  # log (sigma_s', sigma_a) (2, C) of the next render
    last_step: Array | None = None
    relax = np.ones((2, n_ch))
    prev: tuple[Array, Array] | None = None  # last render point and G = F - x there (log, (2, C))
    last_slope = np.full((2, n_ch), np.nan)  # latest secant slope of G per parameter (interval propagation)
    for it in range(1, max_iterations + 1):
        ssp, sa, ok_ch = _finite_params(result)
        if not ok_ch.any():
            break
        if render_log is not None:
            ssp, sa = np.exp(render_log[0]), np.exp(render_log[1])
        t_r = time.perf_counter()
        ref, ref_se = reference(ssp, sa, eta_f, int(seed))
        render_s = time.perf_counter() - t_r
        ref = _visible_rows(ref, "reference radiance", patches, n_ch)
        ref_se = _visible_rows(ref_se, "reference stderr", patches, n_ch)
        model_l = predict_radiance(patches, lights, eta_f, ssp, sa, model=base_model)
        model_l = np.broadcast_to(model_l, obs.shape)
        good = np.isfinite(ref) & np.isfinite(ref_se) & (ref > 0) & (model_l > 0)
        if not good[:, ok_ch].any():
            raise ValueError(f"reference renderer returned no positive finite radiance at the observed patches "
                             f"(iteration {it}, sigma_s' {ssp.tolist()}, sigma_a {sa.tolist()})")
        safe = np.where(good, model_l, 1.0)
        kappa = np.where(good, ref / safe, np.nan)
        kappa_var = np.where(good, (ref_se / safe) ** 2, np.nan)
        kappa, kappa_var = _smooth(smoother, kappa, kappa_var)
        logp = np.log(np.stack([ssp, sa]))
        kappa_use = np.where(ok_ch[None, :], kappa, 1.0)
        kappa_use_var = np.where(ok_ch[None, :], kappa_var, 0.0)
        corrected = obs / kappa_use
        sig_c = None
        if sig is not None:
            sig_c = np.sqrt((sig / kappa_use) ** 2 + (obs / kappa_use ** 2) ** 2 * kappa_use_var)
        t_f = time.perf_counter()
        new = estimate_single_image(corrected, patches, lights, eta_f, model=base_model, noise_sigma=sig_c,
                                    start_per_mm=np.stack([ssp, sa], axis=1), **fit_kwargs)
        fit_s = time.perf_counter() - t_f
        if not new:
            return replace(new, message=f"refit after reference iteration {it} failed: {new.message}",
                           extra={**new.extra, "reference": [s.as_dict() for s in steps]})
        ssp_n, sa_n, ok_n = _finite_params(new)
        both = ok_ch & ok_n
        step = np.log(np.stack([ssp_n, sa_n])) - logp  # F(p) - p in log parameters
        change = float(np.expm1(np.max(np.abs(step[:, both]), initial=0.0)))
        g_step = np.where(both[None, :], step, 0.0)
        # relaxation against the overshoot of the map p -> F(p) (measured slope -0.4 to -1 in sigma_s' on cubes:
        # a 2-cycle without it): halve a parameter's step factor whenever its step reverses sign, floor 1/4
        if last_step is not None:
            relax = np.where(np.sign(step) * np.sign(last_step) < 0, np.maximum(relax * 0.5, 0.25), relax)
        last_step = step
        render_log = logp + relax * g_step
        # slope of G along the path, per parameter: the refit F(p) is |G| |1 + s| / |s| from the fixed point
        # (1 x |G| while unknown, i.e. a map slope of 1/2 assumed after the first render)
        slope = np.full((2, n_ch), np.nan) if prev is None else _secant_slope(prev[0], prev[1], logp, g_step)
        last_slope = np.where(np.isfinite(slope), slope, last_slope)
        remaining = np.where(np.isfinite(slope), np.abs(1.0 + slope) / np.abs(slope), 1.0)
        prev = (logp, g_step)
        kq = np.where(good, kappa, np.nan)
        steps.append(ReferenceStep(it, np.asarray(new.sigma_s_prime_per_mm).tolist(),
                                   np.asarray(new.sigma_a_per_mm).tolist(), render_s, fit_s,
                                   np.nanmedian(kq, axis=0).tolist(), np.nanpercentile(kq, 5, axis=0).tolist(),
                                   np.nanpercentile(kq, 95, axis=0).tolist(),
                                   np.nanmedian(np.sqrt(kappa_var) / kq, axis=0).tolist(), change,
                                   ssp.tolist(), sa.tolist()))
        result = new
        if it >= min_iterations and _settled(logp, np.log(np.stack([ssp_n, sa_n])), both, new, rel_tol, remaining):
            converged = True
            break
    inv = 1.0 / kappa_use
    fin = np.isfinite(inv) & (inv > 0)
    log_inv = np.where(fin, np.log(np.where(fin, inv, 1.0)), np.nan)
    bias = {"reference": "scene reference renderer (full light transport in the given geometry)",
            "model": base_model,
            "radiance_ratio_median": np.nanmedian(np.where(fin, inv, np.nan), axis=0).tolist(),
            "radiance_ratio_p05": np.nanpercentile(np.where(fin, inv, np.nan), 5, axis=0).tolist(),
            "radiance_ratio_p95": np.nanpercentile(np.where(fin, inv, np.nan), 95, axis=0).tolist(),
            "rms_log_ratio": np.sqrt(np.nanmean(log_inv ** 2, axis=0)).tolist(),
            "table_level": result.extra.get("model_bias")}
    result, propagation = _propagate_intervals(result, last_slope,
                                               float(fit_kwargs.get("identifiable_ratio", _IDENTIFIABLE_RATIO)))
    extra = {**result.extra, "reference": [s.as_dict() for s in steps], "converged": converged,
             "interval_propagation": propagation,
             "reference_iterations": len(steps) - 1, "model_bias": bias, "base_model": base_model,
             "seconds_total": time.perf_counter() - t_all}
    msg = result.message if converged else (f"{result.message}; reference iteration stopped after "
                                            f"{len(steps) - 1} renders with a last change of "
                                            f"{steps[-1].change:.1%} (> rel_tol {rel_tol:.1%})")
    if not np.all(np.isfinite(last_slope)):
        msg += ("; the map's slope was not measured (one render, or a parameter that did not move): its intervals "
                "are the refit's widened x2, the slope the stop rule assumes (min_iterations=2 measures it)")
    return replace(result, model=f"{base_model}+reference", message=msg, extra=extra)
