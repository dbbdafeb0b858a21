"""The public entry points: :func:`estimate_single_image` and :func:`predict_radiance`."""
from __future__ import annotations

import hashlib
import time
from collections import OrderedDict
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..forward import NEAR_FIELD_SPACINGS
from ..fresnel import fresnel_transmittance

from .far_field import (EXACT_PAIR_BUDGET, EXACT_PAIR_BUDGET_BINNED, FAR_FIELD_MODES, FAR_FIELD_THETA,
                        FAR_FIELD_THETA_BINNED, _NODE_RATIO, _cubic_log_basis, _Geometry, _hat_basis, _log_grid,
                        quantization_weights)
from .fit import _LOG_SA_MAX, _LOG_SSP_BOUNDS, _Z95, _ChannelFit, _fit_channel, _Problem, _reduce, _tikhonov
from .validity import flat_model_reasons, parameter_status
from .weights import fit_direct_channel
from .geometry import Lights, Patches, patch_irradiance
from .models import (_binned_profile, _cutoff, _derived_intervals, _disk_batch, _exit_normalization,
                     _profile_batch, _reflectance, check_model, model_bias)
from .results import SingleImageDiagnostics, SingleImageResult, _failure, sigma_a_verdict

Array = NDArray[np.float64]
METHODS: tuple[str, ...] = ("direct", "tikhonov", "pinv")
_COND_SINGULAR = 1.0 / np.finfo(np.float64).eps
#: the binned methods refuse more distance bins than this (memory m x n, Tikhonov O(n^3)): a failure says so
MAX_BINS = 1500


def _direct_system(geo: _Geometry, n_ch: int) -> tuple[list[Array], Array, Array]:
    """The direct method's l = W [G(disk nodes); R(far nodes)] per channel: near rings act on the disk
    integrals G (exact ring integrals, G cubic in log r), far terms on the profile R (cubic in log d);
    both node sets log-spaced by 4 %. Returns (W per channel (m, n), disk nodes, far nodes)."""
    far_nodes = _log_grid(geo.rho, max(geo.d_upper, geo.rho * _NODE_RATIO**4))
    far_w = geo.far_matrices(far_nodes.size, _cubic_log_basis(far_nodes))
    used = np.flatnonzero(np.any(np.stack([np.any(w != 0, axis=0) for w in far_w]), axis=0))
    n_far = int(used.max()) + 1 if used.size else 0
    far_nodes = far_nodes[:n_far]
    pos = np.concatenate([geo.ring_in[geo.ring_in > 0], geo.ring_out[geo.ring_out > 0]])
    disk_nodes = _log_grid(float(pos.min()), float(pos.max())) if pos.size else np.zeros(0)
    near_w = geo.near_disk_matrices(disk_nodes) if disk_nodes.size else [np.zeros((geo.m, 0))] * n_ch
    return [np.hstack([nw, fw[:, :n_far]]) for nw, fw in zip(near_w, far_w)], disk_nodes, far_nodes


#: predict_radiance's direct systems for the last few geometries, keyed by their content: the reference loop
#: (estimation.model_correction) evaluates the fast model at every step on the same patches and light, and the
#: system is most of its cost (measured: 0.35 s of a 0.45 s call on 1,000 patches; 18 builds per loop)
_SYSTEMS: OrderedDict[bytes, tuple[list[Array], Array, Array]] = OrderedDict()
_SYSTEMS_KEPT = 4


def _cached_direct_system(args: tuple[Any, ...], n_ch: int) -> tuple[list[Array], Array, Array]:
    """:func:`_direct_system` of ``_Geometry(*args)``, built once per content (arrays returned read-only)."""
    h = hashlib.blake2b(repr((n_ch,) + tuple(a if not isinstance(a, np.ndarray) else (a.shape, a.dtype.str)
                                              for a in args)).encode(), digest_size=20)
    for a in args:
        if isinstance(a, np.ndarray):
            h.update(np.ascontiguousarray(a).data)
    key = h.digest()
    hit = _SYSTEMS.get(key)
    if hit is not None:
        _SYSTEMS.move_to_end(key)
        return hit
    mats, disk_nodes, far_nodes = _direct_system(_Geometry(*args), n_ch)
    for a in (*mats, disk_nodes, far_nodes):
        a.flags.writeable = False
    _SYSTEMS[key] = (mats, disk_nodes, far_nodes)
    while len(_SYSTEMS) > _SYSTEMS_KEPT:
        _SYSTEMS.popitem(last=False)
    return mats, disk_nodes, far_nodes


def _direct_vector(model: str, eta: float, fdr: str, theta: Array, disk_nodes: Array, far_nodes: Array) -> Array:
    """[G(disk nodes); R(far nodes)] for a batch of log parameters (T, 2): (n, T)."""
    parts = [np.zeros((0, theta.shape[0]))]
    if disk_nodes.size:
        parts.append(_disk_batch(model, eta, fdr, theta, disk_nodes))
    if far_nodes.size:
        parts.append(_profile_batch(model, eta, fdr, theta, far_nodes))
    return np.vstack(parts)


def predict_radiance(patches: Patches, lights: Lights, eta: float, sigma_s_prime_per_mm: ArrayLike,
                     sigma_a_per_mm: ArrayLike, *, model: str = "dipole-jensen", fdr: str = "fit",
                     cutoff_mm: float | None = None, far_field: str = "auto", far_field_theta: float = 0.35
                     ) -> Array:
    """Diffuse radiance L_o (m, C) of the visible patches for given parameters, through the estimator's own
    system (the "direct" method's forward model: exact near-field rings, far field exact or clustered).

    L_o = F_t(eta, w_o)/pi * sum_k R(d_jk) E_t,k A_k (Mukaigawa et al. Eq. 10). For re-rendering a fit and for
    synthesizing large scenes quickly (O(m log K) with ``far_field="clustered"``); an independent forward model
    is :func:`estimation.forward.diffuse_exitance`, which this agrees with to ~1e-5 (exact far field) or to the
    clustering error (see ``far_field_theta`` of :func:`estimate_single_image`).
    """
    check_model(model, eta)
    if far_field not in FAR_FIELD_MODES:
        raise ValueError(f"unknown far_field {far_field!r}; valid: {', '.join(FAR_FIELD_MODES)}")
    eta_f = float(eta)
    vis = patches.visible_index
    e_t = patch_irradiance(patches, lights, eta_f)
    ssp = np.atleast_1d(np.asarray(sigma_s_prime_per_mm, dtype=np.float64))
    sa = np.atleast_1d(np.asarray(sigma_a_per_mm, dtype=np.float64))
    n_ch = max(ssp.size, sa.size, e_t.shape[1])
    ssp, sa = np.broadcast_to(ssp, (n_ch,)), np.broadcast_to(sa, (n_ch,))
    e_t = np.broadcast_to(e_t, (e_t.shape[0], n_ch))
    if vis.size == 0:
        return np.zeros((0, n_ch))
    spacing = patches.spacing_mm
    if not spacing > 0:
        spacing = float(np.sqrt(np.median(patches.areas_mm2[patches.areas_mm2 > 0])))
    c_k = np.ascontiguousarray(e_t * patches.areas_mm2[:, None])
    mats, disk_nodes, far_nodes = _cached_direct_system(
        (patches.centers_mm[vis], patches.centers_mm, patches.areas_mm2, c_k, NEAR_FIELD_SPACINGS * spacing,
         cutoff_mm, far_field, far_field_theta, spacing), n_ch)
    theta = np.log(np.stack([ssp, sa], axis=1))
    v = _direct_vector(model, eta_f, fdr, theta, disk_nodes, far_nodes)  # (n, C)
    l_pred = np.stack([mats[c] @ v[:, c] for c in range(n_ch)], axis=1)
    ft = fresnel_transmittance(eta_f, patches.cos_out[vis])
    return ft[:, None] / (np.pi * _exit_normalization(model, eta_f)) * l_pred


# ---------------------------------------------------------------------------------------------- public entry
#: mapped log parameters are kept inside these bounds (the profile models' range; far outside a trust region a
#: linear map could otherwise ask the table for sigma_a = 1e-40)
_MAP_BOUNDS = (np.array([np.log(1e-4), np.log(1e-9)]), np.array([np.log(1e4), np.log(1e3)]))


def map_parameters(theta: Array, ref_log: Array, matrix: Array) -> Array:
    """log ref + B (theta - log ref) for a batch theta (T, 2), clipped to the models' range."""
    out = ref_log[None, :] + (np.asarray(theta, dtype=np.float64) - ref_log[None, :]) @ np.asarray(matrix).T
    return np.clip(out, *_MAP_BOUNDS)


def _mapped(vector_fn: Any, ref_log: Array, matrix: Array) -> Any:
    def fn(theta: Array) -> Array:
        return vector_fn(map_parameters(theta, ref_log, matrix))
    return fn


def estimate_single_image(observed_radiance: ArrayLike, patches: Patches, lights: Lights, eta: float, *,
                          method: str = "direct", model: str = "dipole-jensen", bin_mm: float = 0.35,
                          cutoff_mm: float | None = None, tolerance: float = 1e-4, noise_sigma: ArrayLike | None = None,
                          noise_floor: float = 1e-3, sigma_a_floor_per_mm: float = 1e-7, monotone: bool = False,
                          regularization: float | None = None, profile_likelihood: bool = True,
                          identifiable_ratio: float = 10.0, model_error: float = 0.02,
                          fdr: str = "fit", far_field: str = "auto", far_field_theta: float | None = None,
                          start_per_mm: ArrayLike | None = None, robust: bool = True,
                          data_slope: ArrayLike | None = None, slope_ref_per_mm: ArrayLike | None = None,
                          search_box_per_mm: ArrayLike | None = None,
                          parameter_map: tuple[ArrayLike, ArrayLike] | None = None
                          ) -> SingleImageResult:
    """Estimate (sigma_s', sigma_a) per channel from one image (Mukaigawa et al. 2009, and better).

    Parameters
    ----------
    observed_radiance : (m,) or (m, C), or (K,) / (K, C)
        Diffuse outgoing radiance L_o of the visible patches (``patches.visible_index`` order), or of all K
        patches (invisible rows ignored). NaN marks masked observations (saturated, specular, dark). A
        cross-polarized frame holds diffuse/2: pass 2x it. Units must match ``lights`` (absolute radiometry).
    patches : :class:`Patches` (e.g. from :func:`patches_from_mesh`): all faces are sources, visible ones observed.
    lights : :class:`PointLights`, :class:`DirectionalLights`, :class:`EnvironmentMap` or E_t per patch (K, C).
    eta : relative index of refraction (fixed input).
    method : "direct" (default), "tikhonov" or "pinv" (published); see the module docstring.
    model : "dipole-jensen", "dipole-better" or "mc-table" (:data:`MODELS_ALL`; the table needs 1 <= eta <= 1.8).
    bin_mm : quantization step of the binned methods (paper: 0.35 mm) and of the diagnostic profile.
    cutoff_mm : ignore pairs farther apart (KD-tree); None uses all pairs (small objects). A note is added
        when the fitted profile still holds more than ``tolerance`` of R_d beyond it.
    noise_sigma : per-observation standard deviation of L_o (same shape as ``observed_radiance``); the residuals
        are then chi-square scaled. Default: relative weights 1/(l_j + noise_floor * max l) and the noise
        variance estimated from the residuals ("direct": the weights are then recomputed once from the first
        fit's prediction instead of the noisy data, which removes the bias of data-dependent weights at high
        noise — measured at 20 % noise: sigma_a 2.5x too large before, within its interval after).
    sigma_a_floor_per_mm : lower bound of sigma_a in the fits and the profile scan.
    monotone, regularization : Tikhonov options (non-increasing R'; fixed lambda instead of GCV).
    identifiable_ratio : sigma_a counts as identifiable when its profile interval is two-sided and
        upper/lower <= this ratio.
    model_error : relative rms of unmodelled error (calibration, geometry, diffusion model; default 2 %). The
        intervals are never tighter than the set of parameters whose best-fit image differs from the optimum
        by less than this rms — without it, noiseless or many-pixel data give intervals that reflect only the
        pixel count, not the (spatially correlated) systematic error. 0 gives purely statistical intervals.
    far_field : how the pairs beyond the near field (2 patch spacings) are summed: "exact" (every pair, cost
        O(m K)), "clustered" (Barnes-Hut source clusters with second-moment pseudo-sources, O(m log K); see
        :class:`_SourceClusters`) or "auto" (exact up to :data:`EXACT_PAIR_BUDGET` pairs — for "pinv" and
        "tikhonov" :data:`EXACT_PAIR_BUDGET_BINNED` — else clustered).
    far_field_theta : opening ratio of the clustered far field (cluster radius / distance). Default (None):
        :data:`FAR_FIELD_THETA` = 0.35 for "direct" (rms error of l 0.02-0.04 % on long profiles, ~0.15 % on short
        ones; 0.5: rms 0.1-0.3 % at ~0.6x the cost), :data:`FAR_FIELD_THETA_BINNED` = 0.2 for the binned methods.
        "auto" sums every pair for the binned methods up to :data:`EXACT_PAIR_BUDGET_BINNED` pairs.
    robust : Huber loss on the normalized residuals of the direct method (:mod:`.weights`: single outliers such
        as Monte Carlo fireflies or hot pixels cannot steer the fit); the binned methods are linear solves and
        take the weights as given.
    data_slope, slope_ref_per_mm : optional (m or K, C, 2) and (C, 2) / (2,): observations that move with the
        parameters, observed - data_slope . phi(theta), phi = r tanh((theta - log slope_ref) / r) per channel in
        log (sigma_s', sigma_a) (:class:`.fit._Problem`; the reference-corrected fit's first-order defect
        correction, :mod:`estimation.model_correction`). "direct" only.
    search_box_per_mm : optional (2, 2) or (C, 2, 2): [[sigma_s'_lo, sigma_a_lo], [sigma_s'_hi, sigma_a_hi]] per
        channel; the optimum is searched inside (a trust region); intervals span the whole range. "direct" only.
    parameter_map : optional (ref_per_mm (2,) or (C, 2), matrix (2, 2) or (C, 2, 2)): the profile model is
        evaluated at the mapped log parameters log ref + B (theta - log ref) instead of theta (space mapping: the
        reference-corrected fit's model of how the scene responds to the parameters, :mod:`estimation.model_correction`);
        the reported parameters, intervals and derived quantities are those of theta. "direct" only.
    start_per_mm : optional (sigma_s', sigma_a) per channel, (2,) or (C, 2): one more start of the fit beside the
        best grid points (e.g. the previous iterate of :func:`estimation.model_correction.estimate_with_reference`).

    Returns a :class:`SingleImageResult` (falsy with ``message`` on failure); ``extra`` records the far-field
    mode, the number of far terms and the seconds spent building the system and fitting. Example: the lead's
    demo path is ``patches_from_mesh(mesh, camera)`` -> ``estimate_single_image(2 * cross_radiance, patches,
    PointLights(led_position[None], led_intensity[None]), eta)``.
    """
    with np.errstate(all="ignore"):  # no numerical warning reaches the user: failures and notes say it
        return _estimate(observed_radiance, patches, lights, eta, method, model, bin_mm, cutoff_mm, tolerance,
                         noise_sigma, noise_floor, sigma_a_floor_per_mm, monotone, regularization, profile_likelihood,
                         identifiable_ratio, model_error, fdr, far_field, far_field_theta, start_per_mm, robust,
                         data_slope, slope_ref_per_mm, search_box_per_mm, parameter_map)


def _estimate(observed_radiance: ArrayLike, patches: Patches, lights: Lights, eta: float, method: str, model: str,
              bin_mm: float, cutoff_mm: float | None, tolerance: float, noise_sigma: ArrayLike | None,
              noise_floor: float, sigma_a_floor_per_mm: float, monotone: bool, regularization: float | None,
              profile_likelihood: bool, identifiable_ratio: float, model_error: float, fdr: str, far_field: str,
              far_field_theta: float | None, start_per_mm: ArrayLike | None, robust: bool,
              data_slope: ArrayLike | None, slope_ref_per_mm: ArrayLike | None, search_box_per_mm: ArrayLike | None,
              parameter_map: tuple[ArrayLike, ArrayLike] | None) -> SingleImageResult:
    t0 = time.perf_counter()
    eta_f = float(eta)
    check_model(model, eta)
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; valid methods: {', '.join(METHODS)}")
    if not bin_mm > 0:
        raise ValueError("bin_mm must be > 0")
    if far_field not in FAR_FIELD_MODES:
        raise ValueError(f"unknown far_field {far_field!r}; valid: {', '.join(FAR_FIELD_MODES)}")
    if far_field_theta is not None and not 0.0 < far_field_theta < 1.0:
        raise ValueError("far_field_theta must lie in (0, 1)")
    vis = patches.visible_index
    k_all = patches.centers_mm.shape[0]
    obs = np.asarray(observed_radiance, dtype=np.float64)
    if obs.ndim == 1:
        obs = obs[:, None]
    sig = None if noise_sigma is None else np.asarray(noise_sigma, dtype=np.float64).reshape(obs.shape)
    if obs.shape[0] == k_all and k_all != vis.size:
        obs = obs[vis]
        sig = None if sig is None else sig[vis]
    if vis.size == 0:
        return _failure("no visible patches (check the camera position, cos_min and occlusion)", method, model,
                        eta_f, t0)
    if obs.shape[0] != vis.size:
        raise ValueError(f"observed_radiance has {obs.shape[0]} rows; expected {vis.size} visible patches or "
                         f"{k_all} patches")
    if not (np.all(np.isfinite(patches.centers_mm)) and np.all(np.isfinite(patches.areas_mm2))
            and np.all(np.isfinite(patches.cos_out))):
        return _failure("patch centres, areas or view cosines are not finite", method, model, eta_f, t0)
    if np.any(patches.areas_mm2 < 0) or not np.any(patches.areas_mm2 > 0):
        return _failure("patch areas must be >= 0 and not all 0", method, model, eta_f, t0)
    e_t = patch_irradiance(patches, lights, eta_f)
    n_ch = max(obs.shape[1], e_t.shape[1])
    if obs.shape[1] not in (1, n_ch) or e_t.shape[1] not in (1, n_ch):
        raise ValueError(f"channel mismatch: observations {obs.shape[1]}, illumination {e_t.shape[1]}")
    obs = np.broadcast_to(obs, (obs.shape[0], n_ch))
    e_t = np.broadcast_to(e_t, (k_all, n_ch))
    if sig is not None:
        sig = np.broadcast_to(sig, obs.shape)
    if not np.all(np.isfinite(e_t)) or np.all(e_t <= 0):
        return _failure("the illumination gives no (finite) irradiance on the object", method, model, eta_f, t0)
    if np.any(e_t < 0):
        return _failure("the irradiance is negative on some patches", method, model, eta_f, t0)
    ft = fresnel_transmittance(eta_f, patches.cos_out[vis])
    valid = np.isfinite(obs) & (ft[:, None] > 1e-6)
    if sig is not None:
        valid &= np.isfinite(sig) & (sig > 0)
    c_exit = _exit_normalization(model, eta_f)
    hints: list[Array | None] = [None] * n_ch
    if start_per_mm is not None:
        st = np.asarray(start_per_mm, dtype=np.float64)
        if st.shape not in ((2,), (n_ch, 2)) or not np.all(np.isfinite(st)) or np.any(st <= 0):
            raise ValueError(f"start_per_mm must be positive finite (sigma_s', sigma_a), shape (2,) or ({n_ch}, 2); "
                             f"got shape {st.shape}")
        hints = list(np.log(np.broadcast_to(st, (n_ch, 2))))
    if (data_slope is not None or search_box_per_mm is not None or parameter_map is not None) and method != "direct":
        raise ValueError("data_slope, search_box_per_mm and parameter_map need method='direct'")
    maps: list[tuple[Array, Array] | None] = [None] * n_ch
    if parameter_map is not None:
        ref_m = np.asarray(parameter_map[0], dtype=np.float64)
        mat_m = np.asarray(parameter_map[1], dtype=np.float64)
        if (ref_m.shape not in ((2,), (n_ch, 2)) or mat_m.shape not in ((2, 2), (n_ch, 2, 2))
                or not np.all(np.isfinite(mat_m)) or not np.all(np.isfinite(ref_m)) or np.any(ref_m <= 0)):
            raise ValueError(f"parameter_map must be (positive ref (2,) or ({n_ch}, 2), finite matrix (2, 2) or "
                             f"({n_ch}, 2, 2))")
        ref_l = np.log(np.broadcast_to(ref_m, (n_ch, 2)))
        mat_b = np.broadcast_to(mat_m, (n_ch, 2, 2))
        maps = [(ref_l[c], mat_b[c]) for c in range(n_ch)]
    slope_obs = ref_log = None
    if data_slope is not None:
        sl = np.asarray(data_slope, dtype=np.float64)
        if sl.ndim == 2:
            sl = sl[:, None, :]
        if sl.shape[0] == k_all and k_all != vis.size:
            sl = sl[vis]
        if sl.ndim != 3 or sl.shape[0] != vis.size or sl.shape[2] != 2 or sl.shape[1] not in (1, n_ch):
            raise ValueError(f"data_slope has shape {np.shape(data_slope)}; expected ({vis.size} or {k_all}, {n_ch}, 2)")
        if slope_ref_per_mm is None:
            raise ValueError("data_slope needs slope_ref_per_mm (the parameters it was taken at)")
        ref = np.asarray(slope_ref_per_mm, dtype=np.float64)
        if ref.shape not in ((2,), (n_ch, 2)) or not np.all(np.isfinite(ref)) or np.any(ref <= 0):
            raise ValueError(f"slope_ref_per_mm must be positive finite, shape (2,) or ({n_ch}, 2)")
        slope_obs = np.broadcast_to(np.nan_to_num(sl), (vis.size, n_ch, 2))
        ref_log = np.log(np.broadcast_to(ref, (n_ch, 2)))
        valid &= np.all(np.isfinite(np.broadcast_to(sl, (vis.size, n_ch, 2))), axis=2)
    boxes: list[tuple[Array, Array] | None] = [None] * n_ch
    if search_box_per_mm is not None:
        bx = np.asarray(search_box_per_mm, dtype=np.float64)
        if bx.shape not in ((2, 2), (n_ch, 2, 2)) or not np.all(bx > 0) or np.any(bx[..., 0, :] >= bx[..., 1, :]):
            raise ValueError(f"search_box_per_mm must be positive [[lo_s, lo_a], [hi_s, hi_a]] with lo < hi, shape (2, 2) "
                             f"or ({n_ch}, 2, 2); got {bx.tolist()}")
        bx = np.log(np.broadcast_to(bx, (n_ch, 2, 2)))
        boxes = [(bx[c, 0], bx[c, 1]) for c in range(n_ch)]
    l_obs = np.where(valid, np.pi * c_exit * np.nan_to_num(obs) / np.where(ft > 1e-6, ft, 1.0)[:, None], 0.0)
    if not np.any(valid.sum(0) >= 3):
        return _failure("fewer than 3 valid observations in every channel", method, model, eta_f, t0)
    if np.all(l_obs[valid] <= 0):
        return _failure("all observed radiances are <= 0", method, model, eta_f, t0)

    c_k = np.ascontiguousarray(e_t * patches.areas_mm2[:, None])
    spacing = patches.spacing_mm
    if not spacing > 0:
        spacing = float(np.sqrt(np.median(patches.areas_mm2[patches.areas_mm2 > 0])))
    rho = NEAR_FIELD_SPACINGS * spacing
    r_self = spacing / np.sqrt(np.pi)  # radius of the disk with the median patch area (pinv's self term)
    binned = method != "direct"
    if far_field == "auto":
        budget = EXACT_PAIR_BUDGET_BINNED if binned else EXACT_PAIR_BUDGET
        far_field = "clustered" if vis.size * k_all > budget else "exact"
    if far_field_theta is None:
        far_field_theta = FAR_FIELD_THETA_BINNED if binned else FAR_FIELD_THETA
    geo_args = (patches.centers_mm[vis], patches.centers_mm, patches.areas_mm2, c_k, rho, cutoff_mm, far_field,
                far_field_theta, spacing)
    geo = _Geometry(*geo_args)
    notes: list[str] = []

    # ------------------------------------------------------------------ per-method system
    ring_max = float(geo.ring_out.max(initial=0.0))
    if method == "direct":
        # (cached by content: the reference loop's refits see the same patches and light every time)
        mats, disk_nodes, far_nodes = _cached_direct_system(geo_args, n_ch)
        bins = np.arange(0.0, max(geo.d_max, rho) + bin_mm, bin_mm)
        cond = np.nan
        empty = 0

        def vector_fn(theta: Array, dn: Array = disk_nodes, fn: Array = far_nodes) -> Array:
            return _direct_vector(model, eta_f, fdr, theta, dn, fn)
    else:
        n_long = int(np.ceil((max(geo.d_upper, rho, ring_max) + 1.5 * bin_mm) / bin_mm))
        if n_long > 2 * MAX_BINS:
            return _failure(f"bin_mm = {bin_mm:g} mm gives ~{n_long} distance bins over this object (> {MAX_BINS}); "
                            f"use bin_mm >= {max(geo.d_upper, rho) / MAX_BINS:.3g} mm or method='direct'",
                            method, model, eta_f, t0)
        long_bins = np.arange(0.0, max(geo.d_upper, rho, ring_max) + 1.5 * bin_mm, bin_mm)
        far_w = geo.far_matrices(long_bins.size, _hat_basis(long_bins))
        bins = np.arange(0.0, max(geo.d_max, rho, ring_max) + 1.5 * bin_mm, bin_mm)
        if bins.size < 3:
            bins = np.array([0.0, bin_mm, 2 * bin_mm])
        if bins.size > MAX_BINS:
            return _failure(f"bin_mm = {bin_mm:g} mm gives {bins.size} distance bins (> {MAX_BINS}); use bin_mm >= "
                            f"{bins[-1] / MAX_BINS:.3g} mm or method='direct'", method, model, eta_f, t0)
        # the far pairs reach node floor(d_max / bin) + 1 < bins.size: the trimmed columns are all zero
        far_w = [np.pad(w, ((0, 0), (0, max(bins.size - w.shape[1], 0))))[:, :bins.size] for w in far_w]
        # near field: published = point samples (self term at d = 0); tikhonov = exact ring integrals
        if method == "pinv":
            near_w = []
            i, beta = quantization_weights(geo.near_d, bins)
            for c in range(n_ch):
                w = c_k[geo.near_k, c]
                acc = np.bincount(geo.near_j * bins.size + i, weights=beta * w, minlength=vis.size * bins.size)
                acc += np.bincount(geo.near_j * bins.size + i + 1, weights=(1 - beta) * w,
                                   minlength=vis.size * bins.size)
                near_w.append(acc.reshape(vis.size, bins.size))
        else:
            near_w = geo.near_matrices(bins)
        w_full = [far_w[c] + near_w[c] for c in range(n_ch)]
        col_nonzero = np.any(np.stack([np.abs(w) for w in w_full]).sum(0) > 0, axis=0)
        empty = int((~col_nonzero).sum())
        if int(col_nonzero.sum()) < 4:
            return _failure(f"only {int(col_nonzero.sum())} non-empty distance bins of {bin_mm:g} mm (observed "
                            f"distances <= {max(geo.d_max, ring_max):.3g} mm): too few to fit the 2-parameter "
                            "dipole; use a smaller bin_mm or method='direct'", method, model, eta_f, t0)
        cond = 0.0
    t_system = time.perf_counter() - t0

    # ------------------------------------------------------------------ per-channel fits
    theta_hat = np.full((n_ch, 2), np.nan)
    fits: list[_ChannelFit] = []
    rel_rms = np.full(n_ch, np.nan)
    res_rms = np.full(n_ch, np.nan)
    prof_vals = np.full((bins.size, n_ch), np.nan)
    lambdas = np.full(n_ch, np.nan)
    jac_conds = np.full(n_ch, np.nan)
    downweighted = np.full(n_ch, 0.0)
    nfev = 0
    for c in range(n_ch):
        ok = valid[:, c]
        if ok.sum() < 3:
            return _failure(f"channel {c}: fewer than 3 valid observations", method, model, eta_f, t0)
        if not np.any(e_t[:, c] > 0):
            return _failure(f"channel {c}: the illumination gives no irradiance in this channel", method, model,
                            eta_f, t0)
        l_c = l_obs[ok, c]
        if not np.any(l_c != 0):
            return _failure(f"channel {c}: all observed radiances are 0", method, model, eta_f, t0)
        sig_l = None if sig is None else np.pi * c_exit * sig[ok, c] / ft[ok]  # sigma of l = pi c sigma_L / F_t
        if sig_l is not None:
            w_obs = 1.0 / np.sqrt(sig_l ** 2 + (model_error * l_c) ** 2)
        else:
            w_obs = 1.0 / (np.abs(l_c) + noise_floor * np.max(np.abs(l_c)))
        if method == "direct":
            # weights from the first fit's prediction (data-based weights correlate with the noise: noisy-low pixels
            # would get large weights), Huber reweighting, the final fit (:mod:`.weights`)
            w_tot = mats[c][ok]
            sl_c = None if slope_obs is None else (np.pi * c_exit / ft[ok])[:, None] * slope_obs[ok, c]
            vfn = vector_fn if maps[c] is None else _mapped(vector_fn, *maps[c])
            wf = fit_direct_channel(vfn, w_tot, l_c, sig_l, sa_floor=sigma_a_floor_per_mm,
                                    model_error=model_error, noise_floor=noise_floor, robust=robust,
                                    profile=profile_likelihood, start_hint=hints[c], slope=sl_c,
                                    theta_ref=None if ref_log is None else ref_log[c], box=boxes[c])
            fit = wf.fit
            nfev += wf.nfev_extra
            jac_conds[c] = fit.jac_cond
            downweighted[c] = float(np.mean(wf.robust_weight < 1.0))
            if np.all(np.isfinite(fit.theta)):
                prof_vals[:, c] = _profile_batch(model, eta_f, fdr, fit.theta[None, :], bins)[:, 0]
                rel_rms[c] = float(np.sqrt(np.mean(((wf.pred - l_c) / np.where(l_c != 0, l_c, 1)) ** 2)))
                res_rms[c] = float(np.sqrt(fit.ssr / l_c.size))
        else:
            w_c = w_full[c][ok]
            if method == "pinv" and int(col_nonzero.sum()) > l_c.size:
                return _failure(f"channel {c}: the published pinv route needs at least as many observations as "
                                f"non-empty bins (Eq. 28, n <= m): n = {int(col_nonzero.sum())}, m = {l_c.size}; "
                                "use a larger bin_mm or method='direct'", method, model, eta_f, t0)
            r_w, y_w, _ = _reduce(w_c, l_c)  # W = Q R: singular values and pinv via the small R
            if col_nonzero.any():
                sv = np.linalg.svd(r_w[:, col_nonzero], compute_uv=False)
                cond = max(cond, float(sv[0] / sv[-1]) if sv.size and sv[-1] > 0 else np.inf)
            if method == "pinv":
                r_bins = np.linalg.pinv(r_w) @ y_w if r_w.shape[0] == r_w.shape[1] else np.linalg.pinv(w_c) @ l_c
                fit_cols = col_nonzero
            else:
                a_t, b_t, off_t = _reduce(w_c * w_obs[:, None], l_c * w_obs)
                r_bins, lam = _tikhonov(a_t, b_t, regularization, monotone, n_data=l_c.size, offset=off_t)
                lambdas[c] = lam
                fit_cols = np.ones(bins.size, dtype=bool)
            prof_vals[:, c] = r_bins
            pred_img = w_c @ r_bins
            rel_rms[c] = float(np.sqrt(np.mean(((pred_img - l_c) / np.where(l_c != 0, l_c, 1)) ** 2)))
            if method == "pinv":  # Eq. 29: unweighted least squares on the (non-empty) bins
                radii = bins[fit_cols]

                def model_fn_b(theta: Array, radii: Array = radii) -> Array:
                    return _binned_profile(model, eta_f, fdr, theta, radii, method, r_self, bin_mm)

                problem = _Problem(model_fn_b, None, r_bins[fit_cols], int(fit_cols.sum()), r_bins[fit_cols])
            else:
                # R' near d = 0 is only seen through disk integrals (smooth irradiance), so compare profiles in
                # the metric of the data: || w (W R(theta) - W r') || (the information W^T W on r')
                def model_fn_b(theta: Array) -> Array:
                    return _binned_profile(model, eta_f, fdr, theta, bins, method, r_self, bin_mm)

                problem = _Problem(model_fn_b, a_t, a_t @ r_bins, l_c.size, w_obs * pred_img)
            fit = _fit_channel(problem, sigma_a_floor_per_mm, profile=profile_likelihood, model_error=model_error,
                               start_hint=hints[c])
            res_rms[c] = float(np.sqrt(fit.ssr / max(problem.n_data, 1))) if np.isfinite(fit.ssr) else np.nan
            jac_conds[c] = fit.jac_cond
        nfev += fit.nfev
        if not np.all(np.isfinite(fit.theta)):
            return _failure(f"channel {c}: {fit.message}", method, model, eta_f, t0)
        if not fit.ok:
            notes.append(f"channel {c}: {fit.message}")
        theta_hat[c] = fit.theta
        fits.append(fit)

    # ------------------------------------------------------------------ assemble
    ssp = np.exp(theta_hat[:, 0])
    sa = np.exp(theta_hat[:, 1])
    rd, ld, D = _reflectance(model, ssp, sa, eta_f, fdr)
    sd = np.array([np.sqrt(np.clip(np.diag(f.cov), 0, None)) for f in fits])  # (C, 2)
    # (0 when a variance vanishes: the correlation is then undefined)
    corr = np.array([float(np.clip(f.cov[0, 1] / np.sqrt(f.cov[0, 0] * f.cov[1, 1]), -1.0, 1.0))
                     if np.isfinite(f.cov).all() and f.cov[0, 0] * f.cov[1, 1] > 0 else 0.0 for f in fits])
    sd = np.minimum(sd, 300.0)  # (exp overflow guard: an SD of 300 in a log parameter is "unbounded")
    ssp_ci = np.stack([ssp * np.exp(-_Z95 * sd[:, 0]), ssp * np.exp(_Z95 * sd[:, 0])], axis=1)
    # a sigma_s' at the edge of the search range is no optimum: the data did not bound it (its interval: the range)
    at_bound = (theta_hat[:, 0] <= _LOG_SSP_BOUNDS[0] + 1e-3) | (theta_hat[:, 0] >= _LOG_SSP_BOUNDS[1] - 1e-3)
    ssp_ci[at_bound] = np.exp(np.array(_LOG_SSP_BOUNDS))
    sa_ci_jac = np.stack([sa * np.exp(-_Z95 * sd[:, 1]), sa * np.exp(_Z95 * sd[:, 1])], axis=1)
    rd_ci, ld_ci = _derived_intervals(theta_hat, [f.cov for f in fits], eta_f, model, fdr)
    if profile_likelihood:
        sa_ci = np.array([f.sa_profile_ci for f in fits])
        one_sided = [f.one_sided for f in fits]
    else:
        sa_ci = sa_ci_jac.copy()
        one_sided = [bool(lo <= sigma_a_floor_per_mm * 1.0001) for lo in sa_ci[:, 0]]
    ident: list[bool] = []
    reasons: list[str] = []
    for c in range(n_ch):
        ok_c, why = sigma_a_verdict(float(sa_ci[c, 0]), float(sa_ci[c, 1]), identifiable_ratio, one_sided[c])
        if not ok_c and "floor" in why:
            why += (f"; the observed distances (<= {geo.d_max:.3g} mm) are short against l_d = {ld[c]:.3g} mm")
        ident.append(ok_c)
        reasons.append(f"channel {c}: {why}")
    for c in range(n_ch):
        lo, hi = ssp_ci[c]
        if not (lo > 0 and hi <= identifiable_ratio * lo):
            notes.append(f"channel {c}: sigma_s' is not identifiable (95% interval {lo:.3g}-{hi:.3g} /mm); "
                         f"R_d = {rd[c]:.3g} ({rd_ci[c, 0]:.3g}-{rd_ci[c, 1]:.3g}) is the constrained quantity")
        if spacing > 2.0 * float(ld[c]):
            notes.append(f"channel {c}: the patch spacing ({spacing:.3g} mm) exceeds twice the fitted diffusion "
                         f"length l_d = {float(ld[c]):.3g} mm: the profile is not resolved by the mesh "
                         "(refine it; only R_d is reliable)")
    if cutoff_mm is not None:
        need = _cutoff(model, tolerance, ssp, sa, eta_f, fdr)
        if need > geo.cutoff:
            notes.append(f"cutoff {geo.cutoff:.3g} mm is shorter than the fitted profile needs for tolerance "
                         f"{tolerance:g} ({need:.3g} mm)")
    if method == "pinv" and empty:
        notes.append(f"{empty} empty distance bins are zero columns of W (pinv returns 0 for them); "
                     "they were left out of the dipole fit")
    cond_out = cond if method != "direct" else float(np.nanmax(jac_conds))
    if not cond_out < _COND_SINGULAR:
        cond_out = _COND_SINGULAR
        notes.append("the system is numerically singular (condition number reported as 1/eps)")
    seconds = time.perf_counter() - t0
    diag = SingleImageDiagnostics(cond_out, int(bins.size), int(empty), res_rms, rel_rms,
                                  seconds, int(valid.sum()), int(k_all), int(nfev),
                                  lambdas if method == "tikhonov" else None, tuple(notes))
    extra = {"far_field": geo.far_field, "far_field_theta": geo.theta if geo.far_field == "clustered" else None,
             "far_terms": int(geo.n_far_terms), "near_pairs": int(geo.near_j.size),
             "seconds_system": float(t_system), "seconds_fit": float(seconds - t_system),
             "exit_normalization": float(c_exit), "model_bias": model_bias(ssp, sa, eta_f, model, fdr=fdr),
             "noise_model": {"weights": ("stated sigma and a relative model error" if sig is not None else
                                         "relative (model error only; noise level from the residuals)"),
                             "model_error": float(model_error),
                             "robust": "huber" if (robust and method == "direct") else None,
                             "downweighted_fraction": downweighted.tolist()}}
    flat = flat_model_reasons(patches, valid, ld, ssp / (ssp + sa), eta_f) if search_box_per_mm is None else [""] * n_ch
    forced = [("; ".join(x for x in (f"sigma_s' at the edge of its search range ({np.exp(_LOG_SSP_BOUNDS[0]):g}-"
                                     f"{np.exp(_LOG_SSP_BOUNDS[1]):g} /mm): not bounded by the data"
                                     if at_bound[c] else "", flat[c]) if x)) for c in range(n_ch)]
    out = SingleImageResult(
        True, "ok" if not notes else "; ".join(notes), method, model, eta_f,
        sigma_s_prime_per_mm=ssp, sigma_a_per_mm=sa, R_d=np.asarray(rd), l_d_mm=np.asarray(ld), D_mm=np.asarray(D),
        sigma_s_prime_ci_per_mm=ssp_ci, sigma_a_ci_per_mm=sa_ci, sigma_a_ci_jacobian_per_mm=sa_ci_jac,
        R_d_ci=rd_ci, l_d_ci_mm=ld_ci, correlation_log=corr,
        sigma_a_identifiable=bool(all(ident)), sigma_a_identifiable_per_channel=tuple(ident),
        identifiability_reason="; ".join(reasons), profile_bins_mm=bins, profile_values=prof_vals,
        diagnostics=diag, extra=extra)
    status, why = parameter_status(out, None, extra_reasons=forced)
    # a plain (flat-profile) fit whose sigma_s' is weak — outside the model's validity, or not bounded by the data —
    # has no error bound (measured on the scene zoo: a factor 1.2 to 80 off, and its validity checks use the fitted
    # l_d, which a wildly wrong fit shrinks): its honest interval is the search range; the fit's own is kept in
    # "statistical_ci" (the reference loop starts from it). Inside the loop (a search box) the fit is the corrected
    # model's and keeps its intervals.
    unbounded = [search_box_per_mm is None and (bool(flat[c]) or status["sigma_s_prime_per_mm"][c] != "ok")
                 for c in range(n_ch)]
    if any(unbounded):
        extra["statistical_ci"] = {"sigma_s_prime_per_mm": ssp_ci.tolist(), "sigma_a_per_mm": sa_ci.tolist()}
        extra["interval_note"] = ("channels whose sigma_s' is weak report the search range as their intervals (no "
                                  "error bound for a flat profile there; 'statistical_ci' is the fit's own)")
        ssp_ci, sa_ci = ssp_ci.copy(), sa_ci.copy()
        for c in range(n_ch):
            if unbounded[c]:
                ssp_ci[c] = np.exp(np.array(_LOG_SSP_BOUNDS))
                sa_ci[c] = (0.0, float(np.exp(_LOG_SA_MAX)))  # (one-sided: [0, hi], as everywhere)
        out = replace(out, sigma_s_prime_ci_per_mm=ssp_ci, sigma_a_ci_per_mm=sa_ci)
        status, why = parameter_status(out, None, extra_reasons=forced)
    out.extra.update(status=status, status_reasons=why, flat_model_reasons=flat)
    return out
