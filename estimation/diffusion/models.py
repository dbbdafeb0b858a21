"""Models of the grounded diffusion estimate: which dipoles it supports, their tabulated R_d and second-moment
factor G, the model bias of a grounded estimate (``estimation.diffusion``; Jensen et al. 2001, d'Eon & Irving 2011).
"""
from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..dipole import (boundary_A, reduced_albedo_from_total_reflectance, second_moment_factor_G,
                      total_diffuse_reflectance_albedo)


Array = NDArray[np.float64]


METHODS: tuple[str, ...] = ("sphere", "small_blur")


_S_MAX = float(np.sqrt(3.0))


_PARAMS = ("albedo", "shortening", "R_d", "alpha_prime", "l_prime_mm", "sigma_t_prime_per_mm",
           "sigma_s_prime_per_mm", "sigma_a_per_mm", "D_mm", "l_d_mm", "r2_mm2")


MODELS_GROUNDED: tuple[str, ...] = ("dipole-jensen", "dipole-better", "mc-table")


def _check_jensen(model: str) -> None:
    if model != "dipole-jensen":
        raise ValueError(f"the grounded estimator supports model='dipole-jensen' only, got {model!r}")


def check_grounded_model(model: str, method: str, eta: float | None = None) -> str:
    """``model`` for the grounded estimator: any of :data:`MODELS_GROUNDED` with ``method="small_blur"`` (alpha'
    from R_d and <r^2> = l'^2 G(alpha') of that model's half-space profile); ``method="sphere"`` uses the
    Jensen closed forms of the truncated sphere integrals and supports "dipole-jensen" only. "mc-table" also
    needs eta in the table's range (1.0-1.8)."""
    if model not in MODELS_GROUNDED:
        raise ValueError(f"unknown model {model!r}; valid models: {', '.join(MODELS_GROUNDED)}")
    if method == "sphere" and model != "dipole-jensen":
        raise ValueError(f"method='sphere' (exact Jensen sphere integrals) supports model='dipole-jensen' only; "
                         f"use method='small_blur' for model={model!r}")
    if model == "mc-table" and eta is not None:
        from ..mc_table import default_table

        default_table().check_eta(float(eta))
    return model


@lru_cache(maxsize=16)
def _model_tables(eta: float, fdr: str, model: str, n: int = 4097) -> tuple[NDArray[np.float32], NDArray[np.float32],
                                                                            NDArray[np.float32], float, float, float]:
    """Half-space tables of ``model`` (sigma_t' = 1): s(R_d) on a uniform R_d grid in [0, 1] (n), and R_d(s),
    s G(s) on a uniform s grid in [0, sqrt 3] (n; s G is finite at s = 0 for the dipoles), plus the R_d range the
    model covers (the table's albedo range for "mc-table": outside it the pixel is censored at the edge) and the
    smallest s the model covers (mc-table: s of its largest albedo, so that an albedo above the table's largest R_d
    is censored at that edge instead of reaching s = 0, where G = s G / s is 0 / 0; the dipoles: 0)."""
    s_f = np.linspace(0.0, _S_MAX, 65537)
    a_f = 1.0 - s_f * s_f / 3.0
    s_g = np.linspace(0.0, _S_MAX, n)
    a_g = 1.0 - s_g * s_g / 3.0
    if model == "mc-table":
        from ..mc_table import default_table, second_moment_factor

        tab = default_table()
        lo, hi = tab.alpha_prime_range
        r_f = tab.total_reflectance(np.clip(a_f, lo, hi), eta)
        r_g = tab.total_reflectance(np.clip(a_g, lo, hi), eta)
        sg = s_g * second_moment_factor(np.clip(a_g, lo, hi), eta)
        r_lo, r_hi = float(tab.total_reflectance(lo, eta)), float(tab.total_reflectance(hi, eta))
        s_min = float(np.sqrt(3.0 * (1.0 - hi)))
    else:
        from ..dipole import second_moment_mm2, total_diffuse_reflectance

        af = np.clip(a_f, 0.0, 1.0)
        r_f = total_diffuse_reflectance(af, 1.0 - af, eta, model=model, fdr=fdr)
        ag = np.clip(a_g, 0.0, 1.0)
        r_g = total_diffuse_reflectance(ag, 1.0 - ag, eta, model=model, fdr=fdr)
        with np.errstate(invalid="ignore", divide="ignore"):
            sg = s_g * second_moment_mm2(ag, 1.0 - ag, eta, model=model, fdr=fdr)
        sg[0] = 2.0 * sg[1] - sg[2]  # s G at s = 0 (finite): linear extrapolation
        r_lo, r_hi = float(r_f[-1]), float(r_f[0])
        s_min = 0.0
    s_of_r = np.interp(np.linspace(0.0, 1.0, n), r_f[::-1], s_f[::-1])
    return (s_of_r.astype(np.float32), np.asarray(r_g, np.float32), np.asarray(sg, np.float32), r_lo, r_hi, s_min)


def _s_lookup(s: Array, table: NDArray[np.float32]) -> Array:
    """f(s) from a table on the uniform s grid [0, sqrt 3] (linear)."""
    n = table.size - 1
    fx = np.clip(np.nan_to_num(s), 0.0, _S_MAX) * np.float32(n / _S_MAX)
    i = np.minimum(fx.astype(np.intp), n - 1)
    f = (fx - i).astype(np.float32)
    return table[i] * (np.float32(1.0) - f) + table[i + 1] * f


def _alpha_from_rd(rd: float, eta: float, fdr: str, model: str) -> tuple[float, bool]:
    """(alpha', censored) of the half-space R_d of ``model`` (scalar, exact)."""
    if model == "mc-table":
        from ..mc_table import default_table

        tab = default_table()
        lo, hi = (float(tab.total_reflectance(a, eta)) for a in tab.alpha_prime_range)
        cens = not lo <= rd <= hi
        return float(tab.invert_albedo(min(max(rd, lo), hi), eta)), cens
    al = float(reduced_albedo_from_total_reflectance(min(max(rd, 0.0), 1.0), eta, model=model, fdr=fdr))
    return al, rd >= 1.0


def _model_rd(alpha: float, eta: float, fdr: str, model: str) -> float:
    """Half-space R_d of ``model`` at alpha' (scalar)."""
    if model == "mc-table":
        from ..mc_table import default_table

        return float(default_table().total_reflectance(alpha, eta, out_of_range="clip"))
    from ..dipole import total_diffuse_reflectance

    return float(total_diffuse_reflectance(alpha, 1.0 - alpha, eta, model=model, fdr=fdr))


def _G_model(alpha: float, eta: float, fdr: str, model: str) -> float:
    """<r^2> sigma_t'^2 of ``model``'s half-space profile at alpha' (scalar)."""
    if model == "mc-table":
        from ..mc_table import second_moment_factor

        return float(second_moment_factor(alpha, eta, out_of_range="clip")[0])
    if model == "dipole-jensen":
        return float(second_moment_factor_G(alpha, float(boundary_A(eta, fdr=fdr))))
    from ..dipole import second_moment_mm2

    return float(second_moment_mm2(alpha, 1.0 - alpha, eta, model=model, fdr=fdr))


def grounded_model_bias(sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike, eta: float, model: str, *,
                        fdr: str = "fit") -> dict[str, Any]:
    """Bias of ``model`` against the Monte Carlo table at fitted (sigma_s', sigma_a) (3,) — the quantities the
    gradients estimator uses: :func:`estimation.single_image.model_bias` (R_d, profile and radiance ratios,
    table-equivalent parameters) plus ``r2_ratio`` = <r^2>_model / <r^2>_table of the normalized half-space
    profile. Channels with non-finite or non-positive parameters are None."""
    from ..mc_table import second_moment_mm2 as mc_r2
    from ..single_image import model_bias

    ssp = np.asarray(sigma_s_prime_per_mm, dtype=np.float64).reshape(-1)
    sa = np.asarray(sigma_a_per_mm, dtype=np.float64).reshape(-1)
    ok = np.isfinite(ssp) & np.isfinite(sa) & (ssp > 0) & (sa > 0)
    out: dict[str, Any] = {"reference": "mc-table", "model": model, "channels_evaluated": ok.tolist()}
    if not ok.any():
        out.update(available=False, reason="no channel with finite sigma_s' > 0 and sigma_a > 0")
        return out
    mb = model_bias(ssp[ok], sa[ok], eta, model, fdr=fdr)
    if mb.get("available", True):
        st = ssp[ok] + sa[ok]
        r2_ref = mc_r2(ssp[ok], sa[ok], eta, out_of_range="clip")
        r2_m = np.array([_G_model(float(a), eta, fdr, model) for a in ssp[ok] / st]) / (st * st)
        mb["r2_ratio"] = (r2_m / r2_ref).tolist()

    def expand(v: Any) -> Any:
        if isinstance(v, list) and len(v) == int(ok.sum()):
            it = iter(v)
            return [next(it) if o else None for o in ok]
        return v

    out.update({k: expand(v) for k, v in mb.items() if k not in ("model", "reference")})
    return out


def _phi1(y: Array) -> Array:
    """(1 - e^-y)/y, 1 at y = 0."""
    y = np.asarray(y, dtype=np.float64)
    small = np.abs(y) < 1e-8
    ys = np.where(small, 1.0, y)
    return np.where(small, 1.0 - 0.5 * y, -np.expm1(-ys) / ys)


def _coeffs_from_s_l(s: ArrayLike, l_mm: ArrayLike) -> tuple[Array, Array]:
    """(sigma_s', sigma_a) from s = sqrt(3(1 - alpha')) and l' = 1/sigma_t'."""
    s = np.asarray(s, dtype=np.float64)
    l_mm = np.asarray(l_mm, dtype=np.float64)
    sa = (s * s / 3.0) / l_mm
    ssp = (1.0 - s * s / 3.0) / l_mm
    return ssp, sa


@lru_cache(maxsize=8)
def _halfspace_s_table(eta: float, fdr: str, n: int = 4097) -> NDArray[np.float32]:
    """s = sqrt(3(1 - alpha')) of the half-space R_d on a uniform grid of R_d in [0, 1] (monotone inverse of
    R_d(s) sampled at 65537 values of s; linear interpolation, error < 1e-7)."""
    s_f = np.linspace(0.0, _S_MAX, 65537)
    A = float(boundary_A(eta, fdr=fdr))
    r_f = total_diffuse_reflectance_albedo(1.0 - s_f * s_f / 3.0, A)
    return np.interp(np.linspace(0.0, 1.0, n), r_f[::-1], s_f[::-1]).astype(np.float32)


def _uniform_lookup(x: Array, table: NDArray[np.float32]) -> Array:
    n = table.size - 1
    fx = np.clip(np.nan_to_num(x), 0.0, 1.0) * np.float32(n)
    i = np.minimum(fx.astype(np.intp), n - 1)
    f = fx - i
    return table[i] * (1.0 - f) + table[i + 1] * f
