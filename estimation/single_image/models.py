"""The profile models as the fit sees them (dipoles and the Monte Carlo table) and their table-level bias."""
from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..dipole import (MODELS, cumulative_disk, cutoff_radius_mm, dipole_coefficients,
                      profile_from_coefficients, reflectance_from_coefficients)
from ..fresnel import fresnel_moment
from ..mc_table import MODEL_NAME as MC_MODEL
from ..mc_table import default_table
from .fit import _Z95

Array = NDArray[np.float64]
#: profile models accepted by the estimator: the dipoles of :mod:`.dipole` and the Monte Carlo table
MODELS_ALL: tuple[str, ...] = tuple(MODELS) + (MC_MODEL,)
#: radii (in transport mean free paths 1/sigma_t' of the fitted parameters) of the profile ratios in model_bias
BIAS_RADII_MFP: tuple[float, ...] = (0.5, 1.0, 2.0, 5.0)


def check_model(model: str, eta: float | None = None) -> str:
    """Return ``model`` if it is one of :data:`MODELS_ALL`, else raise ValueError listing them; for
    ``"mc-table"`` also check that ``eta`` lies in the table's range (1.0-1.8)."""
    if model not in MODELS_ALL:
        raise ValueError(f"unknown model {model!r}; valid models: {', '.join(MODELS_ALL)}")
    if model == MC_MODEL and eta is not None:
        default_table().check_eta(float(eta))
    return model


def _exit_normalization(model: str, eta: float) -> float:
    """c with L_o = F_t(eta, w_o)/(pi c) * sum_k R c_k: 1 for the dipoles (Jensen's F_t/pi, as published),
    1 - 2 FM1_ext(eta) for the table (:func:`estimation.mc_table.exit_radiance_factor`)."""
    if model == MC_MODEL:
        return float(1.0 - 2.0 * fresnel_moment(eta, 1, side="external"))
    return 1.0


def _profile_batch(coeff_model: str, eta: float, fdr: str, theta: Array, radii: Array) -> Array:
    """R(radii; theta) for a batch of log parameters: (T, 2) x (n,) -> (n, T)."""
    ssp = np.exp(theta[:, 0])[:, None]
    sa = np.exp(theta[:, 1])[:, None]
    if coeff_model == MC_MODEL:
        return default_table().profile(radii[None, :], ssp, sa, eta, out_of_range="clip").T
    co = dipole_coefficients(ssp, sa, eta, model=coeff_model, fdr=fdr)
    return profile_from_coefficients(co, radii[None, :]).T


def _disk_batch(coeff_model: str, eta: float, fdr: str, theta: Array, radii: Array) -> Array:
    """Disk integrals int_0^r R 2 pi r' dr' (closed form / the table's cumulative) for a batch: (n, T)."""
    ssp = np.exp(theta[:, 0])[:, None]
    sa = np.exp(theta[:, 1])[:, None]
    if coeff_model == MC_MODEL:
        return default_table().cumulative(radii[None, :], ssp, sa, eta, out_of_range="clip").T
    return np.asarray(cumulative_disk(radii[None, :], ssp, sa, eta, model=coeff_model, fdr=fdr)).T


def _reflectance(model: str, ssp: ArrayLike, sa: ArrayLike, eta: float, fdr: str) -> tuple[Array, Array, Array]:
    """(R_d, l_d, D) of ``model`` at (sigma_s', sigma_a)."""
    if model == MC_MODEL:
        return default_table().reflectance_from_coefficients(ssp, sa, eta, out_of_range="clip")
    return reflectance_from_coefficients(ssp, sa, eta, model=model, fdr=fdr)


def _cutoff(model: str, tolerance: float, ssp: Array, sa: Array, eta: float, fdr: str) -> float:
    if model == MC_MODEL:
        return default_table().cutoff_radius_mm(tolerance, ssp, sa, eta, out_of_range="clip")
    return cutoff_radius_mm(tolerance, ssp, sa, eta, model=model, fdr=fdr)


def _binned_profile(model: str, eta: float, fdr: str, theta: Array, radii: Array, method: str,
                    r_self: float, bin_mm: float) -> Array:
    """The profile the binned methods compare with their bin values R' (n, T).

    Dipoles: R at the bin nodes (as published). The table's R diverges like 1/r at the source, so a point sample
    at d = 0 means nothing; at the node d = 0 it gives instead: ``pinv`` (self term point-sampled at d = 0) the
    mean of R over the own patch's disk, C(r_self)/(pi r_self^2); ``tikhonov`` (hat functions integrated exactly)
    the value that gives the first hat interval its exact disk integral, 3 C(h)/(pi h^2) - 2 R(h), h = bin.
    """
    out = _profile_batch(model, eta, fdr, theta, radii)
    if model != MC_MODEL:
        return out
    zero = radii == 0.0
    if not np.any(zero):
        return out
    if method == "pinv":
        g = _disk_batch(model, eta, fdr, theta, np.array([r_self]))[0]
        out[zero] = g / (np.pi * r_self**2)
    else:
        h = float(bin_mm)
        g = _disk_batch(model, eta, fdr, theta, np.array([h]))[0]
        r_h = _profile_batch(model, eta, fdr, theta, np.array([h]))[0]
        out[zero] = 3.0 * g / (np.pi * h * h) - 2.0 * r_h
    return out


def model_bias(sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike, eta: float, model: str, *,
               fdr: str = "fit", radii_mfp: tuple[float, ...] = BIAS_RADII_MFP) -> dict[str, Any]:
    """Bias of ``model`` against the Monte Carlo reference (the packaged table) at the given parameters.

    Returns a dict (lists per channel): ``R_d_model``, ``R_d_reference`` and ``R_d_rel_diff`` = model/reference - 1;
    ``profile_ratio`` (C, len(radii_mfp)) = R_model/R_reference at ``radii_mfp`` transport mean free paths
    1/sigma_t'; ``exit_normalization`` c of the model's exit factor F_t/(pi c) (1 for the dipoles) against the
    table's (c_ref = 1 - 2 FM1_ext(eta)); ``radiance_ratio`` = (R_d,model / c_model) / (R_d,ref / c_ref): the
    model's predicted radiance over the reference's under uniform illumination, so a fit of the model to real
    (transport-like) data finds R_d,ref smaller than the truth by about this factor; ``equivalent_sigma_s_prime``,
    ``equivalent_sigma_a``: the table's parameters with the same radiance-implied R_d and the same l_d as the
    model at these parameters (the albedo inverted by the table). ``clipped``: the parameters (or the
    equivalent albedo) lie outside the table's albedo range and were evaluated at its edge. For ``"mc-table"``
    every ratio is 1. ``available`` is False (with ``reason``) when eta lies outside the table's range.
    """
    check_model(model)
    ssp = np.atleast_1d(np.asarray(sigma_s_prime_per_mm, dtype=np.float64))
    sa = np.atleast_1d(np.asarray(sigma_a_per_mm, dtype=np.float64))
    ssp, sa = np.broadcast_arrays(ssp, sa)
    tab = default_table()
    eta_f = float(eta)
    out: dict[str, Any] = {"reference": MC_MODEL, "model": model, "radii_mfp": [float(r) for r in radii_mfp]}
    lo_e, hi_e = tab.eta_range
    if not lo_e <= eta_f <= hi_e:
        out.update(available=False, reason=f"eta = {eta_f:g} is outside the Monte Carlo table's range "
                                           f"[{lo_e:g}, {hi_e:g}]")
        return out
    lo_a, hi_a = tab.alpha_prime_range
    alpha = ssp / (ssp + sa)
    clipped = bool(np.any((alpha < lo_a) | (alpha > hi_a)))
    rd_ref, ld_ref, _ = tab.reflectance_from_coefficients(ssp, sa, eta_f, out_of_range="clip")
    st = ssp + sa
    radii = np.asarray(radii_mfp, dtype=np.float64)[None, :] / st[:, None]  # (C, n) mm
    prof_ref = tab.profile(radii, ssp[:, None], sa[:, None], eta_f, out_of_range="clip")
    c_ref = _exit_normalization(MC_MODEL, eta_f)
    if model == MC_MODEL:
        rd_m, ld_m, prof_m, c_m = rd_ref, ld_ref, prof_ref, c_ref
    else:
        rd_m, ld_m, _ = reflectance_from_coefficients(ssp, sa, eta_f, model=model, fdr=fdr)
        co = dipole_coefficients(ssp[:, None], sa[:, None], eta_f, model=model, fdr=fdr)
        prof_m = profile_from_coefficients(co, radii)
        c_m = _exit_normalization(model, eta_f)
    rd_m = np.broadcast_to(np.asarray(rd_m, dtype=np.float64), ssp.shape)
    ld_m = np.broadcast_to(np.asarray(ld_m, dtype=np.float64), ssp.shape)
    rd_ref = np.broadcast_to(np.asarray(rd_ref, dtype=np.float64), ssp.shape)
    radiance_ratio = (rd_m / c_m) / (rd_ref / c_ref)
    if model == MC_MODEL:
        eq_s, eq_a = ssp, sa
    else:
        rd_eq = np.clip(rd_m * c_ref / c_m, 1e-300, None)
        a_eq = tab.invert_albedo(rd_eq, eta_f, out_of_range="clip")
        clipped = clipped or bool(np.any(a_eq <= lo_a * (1 + 1e-12)) or np.any(a_eq >= hi_a * (1 - 1e-12)))
        eq_s, eq_a = tab.coefficients_from_reflectance(rd_eq, ld_m, eta_f, out_of_range="clip")
    out.update(available=True, reason="ok", clipped=clipped,
               R_d_model=rd_m.tolist(), R_d_reference=rd_ref.tolist(), R_d_rel_diff=(rd_m / rd_ref - 1.0).tolist(),
               profile_ratio=(prof_m / prof_ref).tolist(), exit_normalization=float(c_m),
               exit_normalization_reference=float(c_ref), radiance_ratio=radiance_ratio.tolist(),
               equivalent_sigma_s_prime_per_mm=np.asarray(eq_s, dtype=np.float64).tolist(),
               equivalent_sigma_a_per_mm=np.asarray(eq_a, dtype=np.float64).tolist())
    return out



def _derived_intervals(theta: Array, covs: list[Array], eta: float, model: str, fdr: str) -> tuple[Array, Array]:
    """Delta-method 95 % intervals of R_d and l_d (log scale) from the covariance of the log parameters."""
    rd_ci = np.full((theta.shape[0], 2), np.nan)
    ld_ci = np.full((theta.shape[0], 2), np.nan)
    h = 1e-5
    for c, (t, cov) in enumerate(zip(theta, covs)):
        def f(tt: Array) -> Array:
            rd, ld, _ = _reflectance(model, np.exp(tt[0]), np.exp(tt[1]), eta, fdr)
            return np.log(np.array([rd, ld], dtype=np.float64))

        f0 = f(t)
        g = np.stack([(f(t + h * e) - f(t - h * e)) / (2 * h) for e in np.eye(2)], axis=1)  # (2 out, 2 in)
        var = np.einsum("oi,ij,oj->o", g, cov, g)
        sd = np.minimum(np.sqrt(np.clip(var, 0, None)), 300.0)
        rd_ci[c] = np.exp(f0[0] + np.array([-1, 1]) * _Z95 * sd[0])
        ld_ci[c] = np.exp(f0[1] + np.array([-1, 1]) * _Z95 * sd[1])
    return rd_ci, ld_ci
