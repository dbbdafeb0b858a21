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
   F(p_i). The next render point is p_i + lambda (F(p_i) - p_i) in log parameters, lambda = 1 per parameter,
   halved (down to 1/4) whenever that parameter's step reverses sign: the map overshoots on cubes (slope about
   -0.4 to -1 in sigma_s', a 2-cycle without relaxation).

Stop when every parameter's step |F(p_i) - p_i| is below ``rel_tol`` or below a quarter of the half-width of its
own 95 % interval (the reference noise then moves the estimate less than the data's noise does), or after
``max_iterations`` renders; the result is the last refit. Every render uses the same ``seed`` (common random
numbers, a sample-average approximation): the reference is then one fixed realisation, the iteration converges
to its fixed point instead of wandering with fresh noise, and that realisation's noise enters the refit's
intervals through the corrected standard errors.

If the observations are Q(p_true) plus noise, p_true is a fixed point: kappa(p_true) makes the fast model exact
there. Measured on the 20 mm marble-R cube at 128 x 128 px (``benchmarks/mc_single_image.py``, 128-spp
references of ~16 s each): sigma_s' -36.8 % -> +18.8 % -> -1.5 % -> 0.0 % -> +1.0 %, sigma_a -50 % -> -4.2 %
after 4 renders.

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

import time
from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scipy.sparse import csr_matrix
from scipy.spatial import cKDTree

from .single_image import Lights, Patches, SingleImageResult, estimate_single_image, predict_radiance

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


def _settled(step: Array, channels: NDArray[np.bool_], fit: SingleImageResult, rel_tol: float) -> bool:
    """True when every parameter's last step (log) is below rel_tol or below a quarter of its own 95 % interval's
    half-width (log) — the reference noise then moves the estimate less than the data's noise does."""
    tol = np.full(step.shape, np.log1p(rel_tol))
    for row, ci in enumerate((fit.sigma_s_prime_ci_per_mm, fit.sigma_a_ci_per_mm)):
        if ci is None:
            continue
        c = np.asarray(ci, dtype=np.float64).reshape(-1, 2)
        with np.errstate(divide="ignore", invalid="ignore"):
            half = 0.5 * np.log(c[:, 1] / c[:, 0])
        tol[row] = np.maximum(tol[row], np.where(np.isfinite(half), 0.25 * half, np.inf))
    return bool(np.all(np.abs(step[:, channels]) <= tol[:, channels]))


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


def estimate_with_reference(observed_radiance: ArrayLike, patches: Patches, lights: Lights, eta: float,
                            reference: ReferenceRenderer, *, noise_sigma: ArrayLike | None = None,
                            base_model: str = "mc-table", max_iterations: int = 4, rel_tol: float = 0.01,
                            seed: int = 1, smooth_spacings: float = 1.5, **fit_kwargs: Any) -> SingleImageResult:
    """Fit ``base_model`` and correct it by ``reference`` renders of the scene until the parameters settle.

    ``observed_radiance``, ``noise_sigma``, ``patches``, ``lights``, ``eta`` and ``fit_kwargs`` are those of
    :func:`estimation.single_image.estimate_single_image` (``method`` defaults to "direct"). ``reference`` is
    called at most ``max_iterations`` times, always with ``seed`` (common random numbers; the module docstring);
    each refit also starts from the point just rendered (``start_per_mm``). Returns the last fit, with ``model``
    set to ``"<base_model>+reference"`` and ``extra["reference"]`` holding every step (parameters, seconds,
    the correction's median / 5th / 95th percentile), ``extra["converged"]`` and ``extra["model_bias"]``, the base
    model's radiance over the reference's at the final parameters. A failed base fit is returned as it is
    (falsy, its message prefixed); a reference that returns no usable value raises ``ValueError`` naming it.
    """
    if max_iterations < 1:
        raise ValueError("max_iterations must be >= 1")
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
        # relaxation against the overshoot of the map p -> F(p) (measured slope -0.4 to -1 in sigma_s' on cubes:
        # a 2-cycle without it): halve a parameter's step factor whenever its step reverses sign, floor 1/4
        if last_step is not None:
            relax = np.where(np.sign(step) * np.sign(last_step) < 0, np.maximum(relax * 0.5, 0.25), relax)
        last_step = step
        render_log = logp + relax * np.where(both[None, :], step, 0.0)
        kq = np.where(good, kappa, np.nan)
        steps.append(ReferenceStep(it, np.asarray(new.sigma_s_prime_per_mm).tolist(),
                                   np.asarray(new.sigma_a_per_mm).tolist(), render_s, fit_s,
                                   np.nanmedian(kq, axis=0).tolist(), np.nanpercentile(kq, 5, axis=0).tolist(),
                                   np.nanpercentile(kq, 95, axis=0).tolist(),
                                   np.nanmedian(np.sqrt(kappa_var) / kq, axis=0).tolist(), change))
        result = new
        if _settled(step, both, new, rel_tol):
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
    extra = {**result.extra, "reference": [s.as_dict() for s in steps], "converged": converged,
             "reference_iterations": len(steps) - 1, "model_bias": bias, "base_model": base_model,
             "seconds_total": time.perf_counter() - t_all}
    msg = result.message if converged else (f"{result.message}; reference iteration stopped after "
                                            f"{len(steps) - 1} renders with a last change of "
                                            f"{steps[-1].change:.1%} (> rel_tol {rel_tol:.1%})")
    return replace(result, model=f"{base_model}+reference", message=msg, extra=extra)
