"""Diffusion parameters from polarized spherical gradient maps (issue 5, second seed: Zhu et al.).

Two estimators, kept side by side so their disagreement can be reported (``docs/gradients.md``):

1. **Seed** (Zhu, Peers, Debevec, Ghosh, "Estimating diffusion parameters from polarized spherical gradient
   illumination"): D = k R_d / |n_z|. A flat homogeneous region under distant light has the same exitance
   for every dipole (science.md sec. 4), so ``k`` is an *empirical length* that depends on the capture
   geometry: :func:`calibrate_k` measures it on a reference of known D in the actual geometry,
   :func:`diffusion_seed` applies it, :func:`seed_regression` checks the slope of log D on log(R_d/|n_z|).
   ``n_z`` here is the component of the ideal-equivalent diffuse vector along the surface normal (the
   camera-facing axis when no normals are given), divided by tau1/tau0: 1 for an unblurred surface.

2. **Grounded**: for pattern P_i the transmitted irradiance is E_t^i = tau0/2 + (tau1/2) n_i, so
   v(x_o) = (tau1/tau0) (R * n)(x_o) / (R * 1)(x_o): the diffuse normal is the true normal field blurred by the
   normalized dipole profile. The shortening S = v.n_true / (tau1/tau0) measures the profile's spread:
   - ``method="sphere"`` (exact for a sphere of radius rho with the Euclidean-distance dipole used by the
     renderers): with d the chord, dA = 2 pi d dd and cos(theta) = 1 - d^2/(2 rho^2), so
       albedo = C(2 rho) = int_0^{2 rho} R 2 pi d dd          (the apparent R_d, < R_d)
       S      = 1 - M2(2 rho) / (2 rho^2 C(2 rho)),   M2(D) = int_0^D R d^2 2 pi d dd  (closed form here).
     Both are functions of (alpha', l' = 1/sigma_t'); the pair (albedo, S) is inverted exactly (nested Brent
     for region summaries; per-pixel maps look it up in a tabulated exact inverse,
     or run damped Newton with a bisection fallback). No fitted constant.
     For a general surface with principal curvatures k1, k2, rho_eff = sqrt(2 / (k1^2 + k2^2)) is used.
   - ``method="small_blur"``: S ~ 1 - <r^2> (k1^2 + k2^2)/4 (first order; biased by 5-30% where the
     shortening is 5-15%), alpha' from R_d, l' = sqrt(<r^2>/G(alpha', A)).
   Then sigma_t' = 1/l', sigma_s' = alpha' sigma_t', sigma_a = (1 - alpha') sigma_t', D = l'/3 (Jensen).
   Where a region carries no information (flat, dark, masked, grazing) the value is NaN and ``unknown`` is set.

Only the Jensen 2001 dipole (``model="dipole-jensen"``, ``fdr`` as in :mod:`estimation.dipole`) is supported
by the grounded estimator. Units: mm, 1/mm.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import optimize, stats

from .dipole import (boundary_A, cumulative_disk, dipole_coefficients, hankel_transform,
                     reduced_albedo_from_total_reflectance, second_moment_factor_G, total_diffuse_reflectance_albedo)
from .gradients import _BLOCK_PX, DerivedMap, GradientMaps, _run_tiles, map_allocator, tile_workers

__all__ = [
    "METHODS",
    "MODELS_GROUNDED",
    "check_grounded_model",
    "grounded_model_bias",
    "sphere_albedo",
    "sphere_shortening",
    "truncated_second_moment_mm4",
    "invert_sphere",
    "invert_sphere_scalar",
    "DiffusionMaps",
    "estimate_diffusion",
    "curvature_sq_from_normals",
    "ParameterSummary",
    "DiffusionSummary",
    "summarize",
    "sphere_geometry",
    "SphereEstimate",
    "estimate_sphere",
    "SeedCalibration",
    "SeedEstimate",
    "calibrate_k",
    "diffusion_seed",
    "seed_regression",
    "EstimateComparison",
    "compare_estimates",
    "relief_mtf",
    "fit_relief",
]

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
        from .mc_table import default_table

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
        from .mc_table import default_table, second_moment_factor

        tab = default_table()
        lo, hi = tab.alpha_prime_range
        r_f = tab.total_reflectance(np.clip(a_f, lo, hi), eta)
        r_g = tab.total_reflectance(np.clip(a_g, lo, hi), eta)
        sg = s_g * second_moment_factor(np.clip(a_g, lo, hi), eta)
        r_lo, r_hi = float(tab.total_reflectance(lo, eta)), float(tab.total_reflectance(hi, eta))
        s_min = float(np.sqrt(3.0 * (1.0 - hi)))
    else:
        from .dipole import second_moment_mm2, total_diffuse_reflectance

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
        from .mc_table import default_table

        tab = default_table()
        lo, hi = (float(tab.total_reflectance(a, eta)) for a in tab.alpha_prime_range)
        cens = not lo <= rd <= hi
        return float(tab.invert_albedo(min(max(rd, lo), hi), eta)), cens
    al = float(reduced_albedo_from_total_reflectance(min(max(rd, 0.0), 1.0), eta, model=model, fdr=fdr))
    return al, rd >= 1.0


def _model_rd(alpha: float, eta: float, fdr: str, model: str) -> float:
    """Half-space R_d of ``model`` at alpha' (scalar)."""
    if model == "mc-table":
        from .mc_table import default_table

        return float(default_table().total_reflectance(alpha, eta, out_of_range="clip"))
    from .dipole import total_diffuse_reflectance

    return float(total_diffuse_reflectance(alpha, 1.0 - alpha, eta, model=model, fdr=fdr))


def _G_model(alpha: float, eta: float, fdr: str, model: str) -> float:
    """<r^2> sigma_t'^2 of ``model``'s half-space profile at alpha' (scalar)."""
    if model == "mc-table":
        from .mc_table import second_moment_factor

        return float(second_moment_factor(alpha, eta, out_of_range="clip")[0])
    if model == "dipole-jensen":
        return float(second_moment_factor_G(alpha, float(boundary_A(eta, fdr=fdr))))
    from .dipole import second_moment_mm2

    return float(second_moment_mm2(alpha, 1.0 - alpha, eta, model=model, fdr=fdr))


def grounded_model_bias(sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike, eta: float, model: str, *,
                        fdr: str = "fit") -> dict[str, Any]:
    """Bias of ``model`` against the Monte Carlo table at fitted (sigma_s', sigma_a) (3,) — the quantities the
    gradients estimator uses: :func:`estimation.single_image.model_bias` (R_d, profile and radiance ratios,
    table-equivalent parameters) plus ``r2_ratio`` = <r^2>_model / <r^2>_table of the normalized half-space
    profile. Channels with non-finite or non-positive parameters are None."""
    from .mc_table import second_moment_mm2 as mc_r2
    from .single_image import model_bias

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


# --------------------------------------------------------------------------------------------------------------
# sphere model (closed forms)
# --------------------------------------------------------------------------------------------------------------
def truncated_second_moment_mm4(radius_mm: ArrayLike, sigma_s_prime_per_mm: ArrayLike,
                                sigma_a_per_mm: ArrayLike, eta: float, *, fdr: str = "fit") -> Array:
    """M2(D) = int_0^D R(r) r^2 2 pi r dr [mm^2] for the Jensen dipole, closed form.

    With U = sqrt(D^2 + z^2), Delta = U - z, for each source depth z in {z_r, z_v}:
    (alpha'/2) z [2 Delta phi1(sigma_tr Delta) e^(-sigma_tr z) - (D^2/U) e^(-sigma_tr U)], phi1(y) = (1-e^-y)/y;
    tends to R_d <r^2> as D -> inf (science.md sec. 1).
    """
    c = dipole_coefficients(sigma_s_prime_per_mm, sigma_a_per_mm, eta, model="dipole-jensen", fdr=fdr)
    D = np.asarray(radius_mm, dtype=np.float64)
    sig = c.sigma_tr_per_mm
    out = 0.0
    for z in (c.z_r_mm, c.z_v_abs_mm):
        U = np.sqrt(D * D + z * z)
        delta = D * D / (U + z)
        out = out + z * (2.0 * delta * _phi1(sig * delta) * np.exp(-sig * z) - (D * D / U) * np.exp(-sig * U))
    return 0.5 * c.alpha_prime * out


def sphere_albedo(radius_mm: ArrayLike, sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike,
                  eta: float, *, fdr: str = "fit") -> Array:
    """Apparent albedo of a sphere under uniform light: int over the sphere of R(chord) dA = C(2 rho)."""
    return cumulative_disk(2.0 * np.asarray(radius_mm, dtype=np.float64), sigma_s_prime_per_mm, sigma_a_per_mm,
                           eta, model="dipole-jensen", fdr=fdr)


def sphere_shortening(radius_mm: ArrayLike, sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike,
                      eta: float, *, fdr: str = "fit") -> Array:
    """S = v.n / (tau1/tau0) on a sphere of radius rho: 1 - M2(2 rho) / (2 rho^2 C(2 rho)) (exact, chord distance).

    The first-order value is 1 - <r^2>/(2 rho^2); this one includes the profile's truncation by the sphere.

    >>> round(float(sphere_shortening(10.0, 2.19, 0.0021, 1.3)), 4)
    0.9246
    """
    rho = np.asarray(radius_mm, dtype=np.float64)
    m2 = truncated_second_moment_mm4(2.0 * rho, sigma_s_prime_per_mm, sigma_a_per_mm, eta, fdr=fdr)
    c = sphere_albedo(rho, sigma_s_prime_per_mm, sigma_a_per_mm, eta, fdr=fdr)
    with np.errstate(invalid="ignore", divide="ignore"):
        return 1.0 - m2 / (2.0 * rho * rho * c)


def _model_pair(s: Array, l_mm: Array, rho: Array, eta: float, fdr: str) -> tuple[Array, Array]:
    """(apparent albedo C(2 rho), shortening S) of a sphere for s = sqrt(3(1 - alpha')) and l' = 1/sigma_t'."""
    ssp, sa = _coeffs_from_s_l(s, l_mm)
    c = sphere_albedo(rho, ssp, sa, eta, fdr=fdr)
    m2 = truncated_second_moment_mm4(2.0 * rho, ssp, sa, eta, fdr=fdr)
    with np.errstate(invalid="ignore", divide="ignore"):
        return c, 1.0 - m2 / (2.0 * rho * rho * c)


def _l_bounds(rho: Array, l_bounds_rel: tuple[float, float]) -> tuple[Array, Array]:
    return rho * l_bounds_rel[0], rho * l_bounds_rel[1]


def _newton_polish(s: Array, y: Array, A: Array, S: Array, rho: Array, eta: float, fdr: str, y_lo: Array,
                   y_hi: Array, steps: int) -> tuple[Array, Array, Array]:
    """Damped Newton on F(s, y = log l') = (C - A, S_model - S) with a forward-difference Jacobian.

    Steps are clipped to s in [0, sqrt 3], y in [y_lo, y_hi] and halved until |F| decreases. Returns s, y, |F|.
    """

    def F(sv: Array, yv: Array) -> tuple[Array, Array]:
        c, sh = _model_pair(sv, np.exp(yv), rho, eta, fdr)
        return c - A, sh - S

    f1, f2 = F(s, y)
    for _ in range(steps):
        hs = 1e-7 * np.maximum(s, 1e-3)
        hs = np.where(s + hs > _S_MAX, -hs, hs)  # stay inside s <= sqrt 3 (sigma_s' >= 0)
        hy = 1e-7
        a1, a2 = F(s + hs, y)
        b1, b2 = F(s, y + hy)
        j11, j21 = (a1 - f1) / hs, (a2 - f2) / hs
        j12, j22 = (b1 - f1) / hy, (b2 - f2) / hy
        det = j11 * j22 - j12 * j21
        good = np.abs(det) > 1e-300
        det = np.where(good, det, 1.0)
        ds = np.where(good, -(j22 * f1 - j12 * f2) / det, 0.0)
        dy = np.where(good, -(-j21 * f1 + j11 * f2) / det, 0.0)
        norm0 = np.hypot(f1, f2)
        t = np.ones_like(s)
        acc = np.zeros(s.shape, bool)
        ns, ny, n1, n2 = s, y, f1, f2
        for _ in range(6):  # backtracking: accept the first step length that reduces |F|
            cs = np.clip(s + t * ds, 0.0, _S_MAX)
            cy = np.clip(y + t * dy, y_lo, y_hi)
            g1, g2 = F(cs, cy)
            better = ~acc & (np.hypot(g1, g2) < norm0)
            ns, ny = np.where(better, cs, ns), np.where(better, cy, ny)
            n1, n2 = np.where(better, g1, n1), np.where(better, g2, n2)
            acc |= better
            t = np.where(acc, t, 0.5 * t)
            if acc.all():
                break
        s, y, f1, f2 = ns, ny, n1, n2
        if np.max(np.hypot(f1, f2)) < 1e-14:
            break
    return s, y, np.hypot(f1, f2)


def invert_sphere(albedo: ArrayLike, shortening: ArrayLike, radius_mm: ArrayLike, eta: float, *,
                  fdr: str = "fit", newton_steps: int = 12, max_rounds: int = 4,
                  l_bounds_rel: tuple[float, float] = (1e-4, 1e2)) -> tuple[Array, Array, NDArray[np.bool_]]:
    """Vectorized inversion of (apparent albedo, shortening) on spheres of radius rho -> (alpha', l' [mm], censored).

    Solves C(2 rho; s, l') = albedo and S(s, l'; rho) = shortening for s = sqrt(3(1 - alpha')) in [0, sqrt 3] and
    l' in rho * ``l_bounds_rel``: a damped 2-D Newton iteration in (s, log l') from the half-space / first-order
    start; values it does not converge (|F| > 1e-11) go to a robust fallback that alternates bisections (l' from
    S, monotone decreasing in l'; s from C, monotone decreasing in s) and is then polished by Newton. Values
    outside the model range are clipped to the bound and flagged ``censored`` (S >= 1: no measurable blur -> l'
    at its lower bound; albedo above C(s = 0): sigma_a = 0). NaN in, NaN out. The scalar reference is
    :func:`invert_sphere_scalar` (nested Brent).
    """
    A = np.asarray(albedo, dtype=np.float64)
    S = np.asarray(shortening, dtype=np.float64)
    rho = np.asarray(radius_mm, dtype=np.float64)
    A, S, rho = np.broadcast_arrays(A, S, rho)
    shape = A.shape
    A, S, rho = A.ravel(), S.ravel(), rho.ravel()
    ok = np.isfinite(A) & np.isfinite(S) & np.isfinite(rho) & (A > 0) & (rho > 0)
    a_ok, s_ok, r_ok = np.where(ok, A, 0.5), np.where(ok, S, 0.9), np.where(ok, rho, 1.0)
    lo_l, hi_l = _l_bounds(r_ok, l_bounds_rel)
    y_lo, y_hi = np.log(lo_l), np.log(hi_l)
    # start: alpha' from the half-space R_d (tabulated inverse), l' from the first-order law
    # 1 - S = <r^2>/(2 rho^2), <r^2> = l'^2 G
    s = _uniform_lookup(np.clip(a_ok, 0.0, 1.0), _halfspace_s_table(float(eta), fdr)).astype(np.float64)
    alpha0 = 1.0 - s * s / 3.0
    G = second_moment_factor_G(np.minimum(alpha0, 1.0 - 1e-12), float(boundary_A(eta, fdr=fdr)))
    r2 = 2.0 * r_ok * r_ok * np.clip(1.0 - s_ok, 0.0, None)
    lnl = np.clip(0.5 * np.log(np.maximum(r2 / G, 1e-300)), y_lo, y_hi)
    cens = np.zeros(a_ok.shape, bool)
    todo = np.flatnonzero(ok)
    if todo.size and newton_steps > 0:
        ss, yy, res = _newton_polish(s[todo], lnl[todo], a_ok[todo], s_ok[todo], r_ok[todo], eta, fdr,
                                     y_lo[todo], y_hi[todo], newton_steps)
        s[todo], lnl[todo] = ss, yy
        todo = todo[~((res < 1e-11) & (ss > 0) & (yy > y_lo[todo]) & (yy < y_hi[todo]))]
    if todo.size:  # fallback: alternating bisections (with censoring), then Newton
        sf, yf, cf = _alternate(s[todo], a_ok[todo], s_ok[todo], r_ok[todo], eta, fdr, y_lo[todo], y_hi[todo],
                                max_rounds)
        free = ~cf
        if np.any(free) and newton_steps > 0:
            sf[free], yf[free], _ = _newton_polish(sf[free], yf[free], a_ok[todo][free], s_ok[todo][free],
                                                   r_ok[todo][free], eta, fdr, y_lo[todo][free], y_hi[todo][free],
                                                   newton_steps)
        s[todo], lnl[todo], cens[todo] = sf, yf, cf
    alpha = np.where(ok, 1.0 - s * s / 3.0, np.nan).reshape(shape)
    l_mm = np.where(ok, np.exp(lnl), np.nan).reshape(shape)
    return alpha, l_mm, (cens & ok).reshape(shape)


def _alternate(s: Array, A: Array, S: Array, rho: Array, eta: float, fdr: str, y_lo: Array, y_hi: Array,
               rounds: int) -> tuple[Array, Array, NDArray[np.bool_]]:
    """Alternating bisections: l' from S at fixed s, then s from C at fixed l'; returns s, log l', censored."""
    lnl = np.full_like(s, np.nan)
    c_l = c_s = np.zeros(s.shape, bool)
    for _ in range(max(1, rounds)):
        lo, hi = y_lo.copy(), y_hi.copy()
        c_l = (S >= _model_pair(s, np.exp(y_lo), rho, eta, fdr)[1]) | (S <= _model_pair(s, np.exp(y_hi), rho, eta,
                                                                                          fdr)[1])
        for _ in range(42):
            mid = 0.5 * (lo + hi)
            above = _model_pair(s, np.exp(mid), rho, eta, fdr)[1] > S
            lo = np.where(above, mid, lo)
            hi = np.where(above, hi, mid)
        new_lnl = 0.5 * (lo + hi)
        l_mm = np.exp(new_lnl)
        slo, shi = np.zeros_like(s), np.full_like(s, _S_MAX)
        c_s = A >= _model_pair(slo, l_mm, rho, eta, fdr)[0]
        for _ in range(42):
            mid = 0.5 * (slo + shi)
            above = _model_pair(mid, l_mm, rho, eta, fdr)[0] > A
            slo = np.where(above, mid, slo)
            shi = np.where(above, shi, mid)
        new_s = 0.5 * (slo + shi)
        moved = max(float(np.max(np.abs(new_s - s))), float(np.max(np.abs(np.nan_to_num(new_lnl - lnl, nan=1.0)))))
        s, lnl = new_s, new_lnl
        if moved < 1e-9:
            break
    return s, lnl, c_l | c_s


def invert_sphere_scalar(albedo: float, shortening: float, radius_mm: float, eta: float, *, fdr: str = "fit",
                         l_bounds_rel: tuple[float, float] = (1e-4, 1e2)) -> tuple[float, float, bool]:
    """Scalar (alpha', l' [mm], censored) by nested Brent root finds (the reference for :func:`invert_sphere`).

    Inner: s(l') solves C(2 rho; s, l') = albedo (clipped to s = 0 when even sigma_a = 0 is too dark). Outer:
    g(l') = S(s(l'), l') - shortening, which is strictly decreasing (a wider profile shortens more, and keeping the
    albedo then needs less absorption, which widens it further), solved in log l' on rho * ``l_bounds_rel``.
    """
    A, S, rho = float(albedo), float(shortening), float(radius_mm)
    if not (np.isfinite(A) and np.isfinite(S) and np.isfinite(rho) and A > 0 and rho > 0):
        return float("nan"), float("nan"), False
    lo, hi = np.log(rho * l_bounds_rel[0]), np.log(rho * l_bounds_rel[1])

    def s_of(l_mm: float) -> tuple[float, bool]:
        def fA(sv: float) -> float:
            return float(_model_pair(np.array(sv), np.array(l_mm), np.array(rho), eta, fdr)[0]) - A

        if fA(0.0) <= 0:
            return 0.0, True
        return float(optimize.brentq(fA, 0.0, _S_MAX, xtol=1e-15, rtol=1e-15)), False

    def g(lnl: float) -> float:
        l_mm = float(np.exp(lnl))
        return float(_model_pair(np.array(s_of(l_mm)[0]), np.array(l_mm), np.array(rho), eta, fdr)[1]) - S

    if g(lo) <= 0:
        lnl, c_l = lo, True
    elif g(hi) >= 0:
        lnl, c_l = hi, True
    else:
        lnl, c_l = float(optimize.brentq(g, lo, hi, xtol=1e-13, rtol=1e-14)), False
    l_mm = float(np.exp(lnl))
    s, c_s = s_of(l_mm)
    return 1.0 - s * s / 3.0, l_mm, bool(c_l or c_s)


def curvature_sq_from_normals(normals: ArrayLike, points_mm: ArrayLike) -> Array:
    """k1^2 + k2^2 [1/mm^2] per pixel from a normal map and the surface points it belongs to (H, W, 3 each).

    With J_n = [dn/du, dn/dv] and J_x = [dx/du, dx/dv] (central differences over the pixel grid), the shape
    operator S maps dx to dn, and k1^2 + k2^2 = ||S||_F^2 = trace(J_n (J_x^T J_x)^-1 J_n^T). Use specular
    normals (or known geometry) and the matching depth map; NaN where a neighbour is missing or the
    parameterization is degenerate. Feed it to :func:`estimate_diffusion` (``curvature_sq_per_mm2``).
    """
    n = np.asarray(normals, dtype=np.float64)
    x = np.asarray(points_mm, dtype=np.float64)
    if n.shape != x.shape or n.ndim != 3 or n.shape[2] != 3:
        raise ValueError("normals and points_mm must both be (H, W, 3)")
    nu, nv = np.gradient(n, axis=1), np.gradient(n, axis=0)
    xu, xv = np.gradient(x, axis=1), np.gradient(x, axis=0)
    g11 = np.sum(xu * xu, -1)
    g12 = np.sum(xu * xv, -1)
    g22 = np.sum(xv * xv, -1)
    det = g11 * g22 - g12 * g12
    with np.errstate(invalid="ignore", divide="ignore"):
        i11, i12, i22 = g22 / det, -g12 / det, g11 / det
        out = (i11 * np.sum(nu * nu, -1) + 2 * i12 * np.sum(nu * nv, -1) + i22 * np.sum(nv * nv, -1))
    return np.where(det > 1e-12 * np.maximum(g11 * g22, 1e-300), out, np.nan)


# --------------------------------------------------------------------------------------------------------------
# per-pixel grounded estimate
# --------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DiffusionMaps:
    """Per-pixel, per-channel grounded estimate (H, W, 3); NaN where ``unknown``.

    ``albedo``: measured apparent albedo; ``shortening``: S = v.n_true/(tau1/tau0); ``radius_mm`` (H, W): sphere
    (or sphere-equivalent) radius used; ``R_d``: half-space total diffuse reflectance of the estimated alpha';
    ``r2_mm2``: half-space <r^2> of the estimated profile; ``censored``: clipped at a model bound. Where sigma_a
    is censored at 0, ``l_d_mm`` and ``r2_mm2`` are +inf (a true statement, not a failure); nothing else is inf.
    """

    albedo: NDArray[np.float32]
    shortening: NDArray[np.float32]
    radius_mm: NDArray[np.float32]
    R_d: NDArray[np.float32]
    alpha_prime: NDArray[np.float32]
    l_prime_mm: NDArray[np.float32]
    sigma_t_prime_per_mm: NDArray[np.float32]
    sigma_s_prime_per_mm: NDArray[np.float32]
    sigma_a_per_mm: NDArray[np.float32]
    D_mm: NDArray[np.float32]
    l_d_mm: NDArray[np.float32]
    r2_mm2: NDArray[np.float32]
    unknown: NDArray[np.bool_]
    censored: NDArray[np.bool_]
    method: str
    eta: float
    provenance: dict[str, Any] = field(default_factory=dict)


def _derived(alpha: Array, l_mm: Array, eta: float, fdr: str) -> dict[str, Array]:
    with np.errstate(invalid="ignore", divide="ignore"):
        st = 1.0 / l_mm
        s = np.sqrt(3.0 * np.clip(1.0 - alpha, 0.0, None))
        A = float(boundary_A(eta, fdr=fdr))
        return {
            "alpha_prime": alpha, "l_prime_mm": l_mm, "sigma_t_prime_per_mm": st,
            "sigma_s_prime_per_mm": alpha * st, "sigma_a_per_mm": (1.0 - alpha) * st, "D_mm": l_mm / 3.0,
            "l_d_mm": np.where(s > 0, l_mm / np.where(s > 0, s, 1.0), np.inf) * np.where(np.isfinite(l_mm), 1, np.nan),
            "r2_mm2": l_mm * l_mm * second_moment_factor_G(alpha, A),
            "R_d": total_diffuse_reflectance_albedo(alpha, A),
        }


def _check_geometry(curvature_sq_per_mm2: ArrayLike | None, sphere_radius_mm: float | None,
                    shape: tuple[int, int]) -> None:
    if sphere_radius_mm is not None:
        if curvature_sq_per_mm2 is not None:
            raise ValueError("give sphere_radius_mm or curvature_sq_per_mm2, not both")
        if not sphere_radius_mm > 0:
            raise ValueError("sphere_radius_mm must be > 0")
        return
    if curvature_sq_per_mm2 is None:
        raise ValueError("the grounded estimator needs the geometry: sphere_radius_mm or curvature_sq_per_mm2")
    k2s = np.shape(curvature_sq_per_mm2)
    try:
        np.broadcast_shapes(k2s, shape)
    except ValueError:
        raise ValueError(f"curvature_sq_per_mm2 of shape {k2s} does not broadcast to {shape}") from None


def _radius_from_curvature(k2: Array) -> Array:
    """Sphere-equivalent radius sqrt(2 / (k1^2 + k2^2)); inf where the curvature is 0 (flat) or negative."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(k2 > 0, np.sqrt(2.0 / np.where(k2 > 0, k2, 1.0)), np.inf)


def _shortening(maps: GradientMaps, true_normals: Array) -> Array:
    return np.einsum("hwck,hwk->hwc", maps.diffuse_vectors.astype(np.float64), true_normals) / maps.tau_ratio


# --------------------------------------------------------------------------------------------------------------
# fast per-pixel inversion: tabulated inverse of the sphere model
# --------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _InverseTable:
    """(albedo, shortening) -> (s, ln(l'/rho), censored) of :func:`invert_sphere`, tabulated (see
    :func:`_sphere_inverse_table`). ``lanes`` (nx*ny,) complex128 = float32 lanes (s, t, censored, 0)."""

    y_lo: float
    y_hi: float
    a_max: NDArray[np.float32]  # (ny,) albedo of sigma_a = 0 at each y (the boundary of the feasible region)
    nx: int
    ny: int
    lanes: NDArray[np.complex128]


_INV_NX, _INV_NY, _INV_Y_LO = 257, 257, -21.0


@lru_cache(maxsize=8)
def _sphere_inverse_table(eta: float, fdr: str) -> _InverseTable:
    """Tabulate the exact inverse (:func:`invert_sphere`, default bounds) of the sphere model once per (eta, fdr).

    Both observables depend on (alpha', l') only through s = sqrt(3(1 - alpha')) and t = ln(l'/rho), so one table
    serves every radius. Coordinates chosen so that the inverse is smooth on the grid: y = ln((1 - S)/S)
    (~ 2t + const for small blur, ~ -ln S for strong blur) on [-21, y(l' = 100 rho, s = 0)], and
    x = albedo / A_max(y) in [0, 1], where A_max(y) is the apparent albedo of a non-absorbing sphere with the same
    shortening, so the censoring boundary sigma_a = 0 is the grid line x = 1 (x > 1: censored, s = 0). 257 x 257
    nodes, bilinear: against the exact inversion, over Jensen-table-like materials on 2-50 mm spheres with
    l'/rho < 0.5, l' and sigma_s' agree to < 3e-3 (median 2e-5); sigma_a likewise wherever it is identifiable
    (errors grow where sigma_a/sigma_t' < 1e-3 and the sphere truncates the profile, where a 1e-4 change of the
    observables moves it as much). Building takes ~1-2 s (66k exact inversions).
    """
    y_hi = float(_model_logit(0.0, 100.0, eta, fdr))
    ny, nx = _INV_NY, _INV_NX
    y = np.linspace(_INV_Y_LO, y_hi, ny)
    S_y = 1.0 / (1.0 + np.exp(y))
    lo = np.full(ny, np.log(1e-4))
    hi = np.full(ny, np.log(1e2))
    zeros = np.zeros(ny)
    for _ in range(60):  # s = 0: S decreases with l'; bisection in ln(l'/rho) for the boundary curve
        mid = 0.5 * (lo + hi)
        above = _model_pair(zeros, np.exp(mid), np.ones(ny), eta, fdr)[1] > S_y
        lo, hi = np.where(above, mid, lo), np.where(above, hi, mid)
    a_max = _model_pair(zeros, np.exp(0.5 * (lo + hi)), np.ones(ny), eta, fdr)[0]
    xx = np.linspace(0.0, 1.0, nx)
    A = np.maximum(xx[:, None] * a_max[None, :], 1e-9)
    al, lp, cens = invert_sphere(A, np.broadcast_to(S_y, A.shape), 1.0, eta, fdr=fdr)
    out = np.zeros((nx * ny, 4), np.float32)
    out[:, 0] = np.sqrt(3.0 * np.clip(1.0 - al, 0.0, None)).ravel()
    out[:, 1] = np.log(lp).ravel()
    out[:, 2] = cens.ravel()
    return _InverseTable(_INV_Y_LO, y_hi, a_max.astype(np.float32), nx, ny, out.view(np.complex128)[:, 0])


def _model_logit(s: float, l_rel: float, eta: float, fdr: str) -> float:
    """ln((1 - S)/S) of the sphere model at s and l'/rho."""
    S = float(_model_pair(np.array(s), np.array(l_rel), np.array(1.0), eta, fdr)[1])
    return float(np.log((1.0 - S) / S))


def _table_invert(tab: _InverseTable, A: Array, S: Array) -> tuple[Array, Array, NDArray[np.bool_]]:
    """Bilinear lookup: (albedo, shortening) (M, 3) float32 -> s, t = ln(l'/rho), censored."""
    f32 = np.float32
    s_lo = 1.0 / (1.0 + np.exp(tab.y_hi))
    Sc = np.clip(S, f32(s_lo), f32(1.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        y = np.log1p(-Sc) - np.log(Sc)
    out_y = ~(y > tab.y_lo) | (S <= s_lo)  # no measurable blur (S -> 1) or more than l' = 100 rho makes
    fy = (np.clip(y, tab.y_lo, tab.y_hi) - f32(tab.y_lo)) * f32((tab.ny - 1) / (tab.y_hi - tab.y_lo))
    with np.errstate(invalid="ignore"):
        j = np.clip(fy.astype(np.intp), 0, tab.ny - 2)
    g = fy - j
    am = tab.a_max[j] * (1.0 - g) + tab.a_max[j + 1] * g
    xr = A / am
    out_x = ~(xr < 1.0)
    fx = np.clip(xr, 0.0, 1.0) * f32(tab.nx - 1)
    with np.errstate(invalid="ignore"):
        i = np.clip(fx.astype(np.intp), 0, tab.nx - 2)
    f = fx - i
    k = i * tab.ny + j

    def corner(kk: NDArray[np.intp]) -> Array:
        return np.take(tab.lanes, kk).view(np.float32).reshape(kk.shape + (4,))

    c00, c10, c01, c11 = corner(k), corner(k + tab.ny), corner(k + 1), corner(k + tab.ny + 1)
    f_, g_ = f[..., None], g[..., None]
    v = (c00 * (1.0 - f_) + c10 * f_) * (1.0 - g_) + (c01 * (1.0 - f_) + c11 * f_) * g_
    s = np.where(out_x, 0.0, v[..., 0])
    cens = out_x | out_y | (v[..., 2] > 0.5)
    return s, v[..., 1], cens


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


def _masks_unknown(masks: Any, o0: int, o1: int, n: int) -> NDArray[np.bool_]:
    """``masks.unknown`` for flat pixels o0:o1 without forming the full-size union."""
    def fl(a: NDArray[Any]) -> NDArray[Any]:
        return a.reshape((n,) + a.shape[2:])[o0:o1]

    u = fl(masks.saturated) | fl(masks.dark) | fl(masks.inconsistent)
    return u | (fl(masks.grazing) | fl(masks.background))[:, None]


def estimate_diffusion(maps: GradientMaps, true_normals: ArrayLike, *, sphere_radius_mm: float | None = None,
                       curvature_sq_per_mm2: ArrayLike | None = None, method: str = "sphere",
                       region: ArrayLike | None = None, max_radius_mm: float = 500.0, grazing_deg: float = 70.0,
                       fdr: str = "fit", model: str = "dipole-jensen", inversion: str = "table",
                       tile_rows: int = 256, out_dir: str | Path | None = None,
                       workers: int | None = None) -> DiffusionMaps:
    """Grounded per-pixel estimate from diffuse vectors and true normals (no fitted constant).

    ``true_normals`` (H, W, 3): specular normals or known geometry (unit; NaN = unknown). Geometry: a known
    ``sphere_radius_mm`` or per-pixel ``curvature_sq_per_mm2`` = k1^2 + k2^2 (sphere-equivalent radius
    sqrt(2/(k1^2+k2^2)); pixels flatter than ``max_radius_mm`` are unknown — a flat region carries no
    information about the length scale). ``method``: "sphere" (exact for spheres) or "small_blur" (first
    order). ``region`` (H, W) bool restricts the estimate. Masks of ``maps`` propagate; pixels with
    n_true.v < cos(``grazing_deg``) are unknown.

    ``inversion`` (method "sphere"): "table" (default) looks up (albedo, shortening) in the tabulated exact
    inverse (:func:`_sphere_inverse_table`: l', sigma_s', D within 3e-3 of the exact solve, far below per-pixel
    noise); "exact" runs :func:`invert_sphere` on every pixel (~7 us per value). Region summaries
    (:func:`summarize`) always invert exactly. The maps are computed in ``tile_rows`` row tiles, in float32;
    ``out_dir``: write them tile by tile into ``.npy`` memory maps there (``estimation.gradients.map_allocator``,
    prefix ``diffusion_``) instead of RAM. Only ``alpha_prime``, ``l_prime_mm``, ``shortening`` (the parameters
    and the observable), ``unknown``, ``censored`` and, with a curvature map, ``radius_mm`` are stored; albedo
    (the gradient albedo where known), R_d, sigma_t', sigma_s', sigma_a, D, l_d and <r^2> are
    :class:`estimation.gradients.DerivedMap` s computed element-wise from them on access (same float32 formulas;
    ``provenance["stored"]`` / ``["derived"]``). ``workers``: threads over row tiles (default min(2, CPUs)).
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; valid: {', '.join(METHODS)}")
    check_grounded_model(model, method, maps.eta)
    if inversion not in ("table", "exact"):
        raise ValueError(f"unknown inversion {inversion!r}; valid: table, exact")
    if tile_rows < 1:
        raise ValueError("tile_rows must be >= 1")
    H, W = maps.shape
    if np.shape(true_normals) != (H, W, 3):
        raise ValueError(f"true_normals must be (H, W, 3) = {(H, W, 3)}, got {np.shape(true_normals)}")
    _check_geometry(curvature_sq_per_mm2, sphere_radius_mm, (H, W))
    if region is not None and np.shape(region) != (H, W):
        raise ValueError("region must be (H, W)")
    eta = maps.eta
    f32 = np.float32
    npx = H * W
    alloc = map_allocator(out_dir, prefix="diffusion_")
    names = _STORED
    outs = {k: alloc(k, (H, W, 3), f32) for k in names}
    if curvature_sq_per_mm2 is not None:
        radius_out = alloc("radius_mm", (H, W), f32)
        flat_r = radius_out.reshape(npx)
    else:  # a known sphere: one radius everywhere, a zero-stride view (not stored)
        assert sphere_radius_mm is not None
        radius_out = np.broadcast_to(f32(sphere_radius_mm), (H, W))
        flat_r = None
    unknown_out = alloc("unknown", (H, W, 3), bool)
    cens_out = alloc("censored", (H, W, 3), bool)
    flat = {k: v.reshape(npx, 3) for k, v in outs.items()}
    flat_u, flat_c = unknown_out.reshape(npx, 3), cens_out.reshape(npx, 3)
    n_workers = tile_workers(workers)
    k2_full = None
    if curvature_sq_per_mm2 is not None:
        k2_full = np.broadcast_to(np.asarray(curvature_sq_per_mm2) if np.ndim(curvature_sq_per_mm2) < 2
                                  else curvature_sq_per_mm2, (H, W))
    A_b = float(boundary_A(eta, fdr=fdr))
    kz = 1.0 + 4.0 * A_b / 3.0
    tau = maps.tau_ratio
    cos_graz = float(np.cos(np.deg2rad(grazing_deg)))
    tab = _sphere_inverse_table(float(eta), fdr) if method == "sphere" and inversion == "table" else None
    hs = _halfspace_s_table(float(eta), fdr) if method == "small_blur" else None
    mtab = _model_tables(float(eta), fdr, model) if model != "dipole-jensen" else None
    nan = f32(np.nan)

    def tile(r0: int, r1: int) -> None:
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            t_nt = _rows(true_normals, r0, r1)
            t_v = _rows(maps.diffuse_vectors, r0, r1)
            t_a = _rows(maps.albedo, r0, r1)
            t_vd = _rows(maps.view_dirs, r0, r1)
            t_k2 = _rows(k2_full, r0, r1) if k2_full is not None else None
            t_reg = _rows(region, r0, r1) if region is not None else None
            n_tile = (r1 - r0) * W
            for b0 in range(0, n_tile, _BLOCK_PX):
                b1 = min(n_tile, b0 + _BLOCK_PX)
                o0, o1 = r0 * W + b0, r0 * W + b1
                nt = np.asarray(t_nt[b0:b1], dtype=f32)
                nlen = np.sqrt(np.einsum("mk,mk->m", nt, nt))
                nt = nt / nlen[:, None]
                nt_ok = np.isfinite(nt[:, 0] + nt[:, 1] + nt[:, 2])
                nt0 = np.where(nt_ok[:, None], nt, 0.0)
                v = np.asarray(t_v[b0:b1], dtype=f32)
                S = np.einsum("mck,mk->mc", v, nt0) / f32(tau)
                A = np.asarray(t_a[b0:b1], dtype=f32)
                vd = np.asarray(t_vd[b0:b1], dtype=f32)
                cos_v = np.einsum("mk,mk->m", nt0, vd)
                if t_k2 is not None:
                    rho = _radius_from_curvature(np.asarray(t_k2[b0:b1], dtype=np.float64)).astype(f32)
                else:
                    assert sphere_radius_mm is not None
                    rho = np.full(b1 - b0, sphere_radius_mm, f32)
                pix_bad = ~nt_ok | ~(cos_v >= cos_graz) | ~(rho <= max_radius_mm)
                if t_reg is not None:
                    pix_bad |= ~np.asarray(t_reg[b0:b1], dtype=bool)
                unknown = _masks_unknown(maps.masks, o0, o1, npx) | pix_bad[:, None]
                unknown |= ~np.isfinite(S) | ~np.isfinite(A) | ~(A > 0)
                rho3 = rho[:, None]
                if method == "sphere" and tab is not None:
                    s, t, cens = _table_invert(tab, A, S)
                    l_mm = rho3 * np.exp(t)
                elif method == "sphere":
                    s = np.full(A.shape, np.nan, f32)
                    l_mm = np.full(A.shape, np.nan, f32)
                    cens = np.zeros(A.shape, bool)
                    known = ~unknown
                    if known.any():
                        al, ll, cc = invert_sphere(A[known].astype(np.float64), S[known].astype(np.float64),
                                                   np.broadcast_to(rho3, A.shape)[known].astype(np.float64),
                                                   eta, fdr=fdr)
                        s[known] = np.sqrt(3.0 * np.clip(1.0 - al, 0.0, None))
                        l_mm[known], cens[known] = ll, cc
                elif mtab is not None:  # small_blur with a tabulated half-space model
                    s = np.maximum(_uniform_lookup(A, mtab[0]), f32(mtab[5]))  # alpha' from the model's R_d
                    r2 = 2.0 * (1.0 - S) * rho3 * rho3
                    G = _s_lookup(s, mtab[2]) / s
                    cens = (r2 <= 0) | ~(A > f32(mtab[3])) | ~(A < f32(mtab[4]))
                    l_mm = np.maximum(np.sqrt(np.maximum(r2, 0.0) / G), 1e-4 * rho3)
                else:
                    assert hs is not None
                    s = _uniform_lookup(A, hs)  # alpha' from the half-space R_d
                    r2 = 2.0 * (1.0 - S) * rho3 * rho3  # <r^2> = 4 (1 - S)/(k1^2 + k2^2), k1^2 + k2^2 = 2/rho^2
                    er, ev = np.exp(-s), np.exp(-s * kz)
                    G = 2.0 * (er + kz * ev) / (s * (er + ev))
                    cens = (r2 <= 0) | (A >= 1.0)
                    l_mm = np.maximum(np.sqrt(np.maximum(r2, 0.0) / G), 1e-4 * rho3)
                alpha = 1.0 - s * s / 3.0
                vals = {"shortening": S, "alpha_prime": alpha, "l_prime_mm": l_mm}
                unknown |= ~np.isfinite(l_mm) | ~np.isfinite(s)
                for k, val in vals.items():
                    o = flat[k][o0:o1]
                    o[...] = val
                    np.copyto(o, nan, where=unknown)
                if flat_r is not None:
                    flat_r[o0:o1] = np.where(np.isfinite(rho), rho, nan)
                flat_u[o0:o1] = unknown
                flat_c[o0:o1] = cens & ~unknown

    _run_tiles(tile, H, tile_rows, n_workers)
    der = _derived_maps(outs["alpha_prime"], outs["l_prime_mm"], unknown_out, maps.albedo, A_b, mtab, model)
    prov = {"module": "estimation.diffusion", "version": 2, "estimator": "grounded", "method": method,
            "model": model, "fdr": fdr, "eta": eta, "sphere_radius_mm": sphere_radius_mm,
            "curvature_given": curvature_sq_per_mm2 is not None, "max_radius_mm": max_radius_mm,
            "grazing_deg": grazing_deg, "inversion": inversion if method == "sphere" else "closed form",
            "storage": "RAM" if out_dir is None else f"memory maps in {out_dir}",
            "stored": list(_STORED) + ["unknown", "censored"] + (["radius_mm"] if flat_r is not None else []),
            "derived": {k: v.definition for k, v in der.items()}
                       | ({} if flat_r is not None else {"radius_mm": f"constant {sphere_radius_mm} mm (sphere)"}),
            "workers": n_workers,
            "gradients": dict(maps.provenance)}
    return DiffusionMaps(
        albedo=der["albedo"], shortening=outs["shortening"], radius_mm=radius_out, R_d=der["R_d"],
        alpha_prime=outs["alpha_prime"], l_prime_mm=outs["l_prime_mm"],
        sigma_t_prime_per_mm=der["sigma_t_prime_per_mm"], sigma_s_prime_per_mm=der["sigma_s_prime_per_mm"],
        sigma_a_per_mm=der["sigma_a_per_mm"], D_mm=der["D_mm"], l_d_mm=der["l_d_mm"], r2_mm2=der["r2_mm2"],
        unknown=unknown_out, censored=cens_out, method=method, eta=eta, provenance=prov)


_STORED = ("shortening", "alpha_prime", "l_prime_mm")


def _derived_maps(alpha: Any, l_mm: Any, unknown: Any, albedo: Any, A_b: float, mtab: Any = None,
                  model: str = "dipole-jensen") -> dict[str, DerivedMap]:
    """The maps :func:`estimate_diffusion` derives from alpha', l' (float32, NaN where ``unknown``)."""
    f32 = np.float32
    kz = f32(1.0 + 4.0 * A_b / 3.0)
    nan, inf = f32(np.nan), f32(np.inf)
    shape = np.shape(alpha)

    def s_of(a: Array) -> Array:
        return np.sqrt(f32(3.0) * np.maximum(f32(1.0) - a, f32(0.0)))

    def l_d(a: Array, l: Array, u: Array) -> Array:
        s = s_of(a)
        return np.where(u, nan, np.where(s > 0, l / s, inf))

    def r2(a: Array, l: Array, u: Array) -> Array:
        s = s_of(a)
        if mtab is not None:
            return np.where(u, nan, np.where(s > 0, l * l * (_s_lookup(s, mtab[2]) / s), inf))
        er, ev = np.exp(-s), np.exp(-s * kz)
        return np.where(u, nan, np.where(s > 0, l * l * (f32(2.0) * (er + kz * ev) / (s * (er + ev))), inf))

    def r_d(a: Array, u: Array) -> Array:
        s = s_of(a)
        if mtab is not None:
            return np.where(u, nan, _s_lookup(s, mtab[1]))
        return np.where(u, nan, f32(0.5) * a * (f32(1.0) + np.exp(f32(-4.0 / 3.0 * A_b) * s)) * np.exp(-s))

    def mk(func: Any, srcs: tuple[Any, ...], definition: str) -> DerivedMap:
        return DerivedMap(func, srcs, shape, np.float32, definition)

    return {
        "albedo": mk(lambda A, u: np.where(u, nan, A), (albedo, unknown), "gradient albedo where known"),
        "sigma_t_prime_per_mm": mk(lambda l: f32(1.0) / l, (l_mm,), "1 / l'"),
        "sigma_s_prime_per_mm": mk(lambda a, l: a * (f32(1.0) / l), (alpha, l_mm), "alpha' / l'"),
        "sigma_a_per_mm": mk(lambda a, l: (f32(1.0) - a) * (f32(1.0) / l), (alpha, l_mm), "(1 - alpha') / l'"),
        "D_mm": mk(lambda l: l / f32(3.0), (l_mm,), "l' / 3"),
        "l_d_mm": mk(l_d, (alpha, l_mm, unknown), "l' / sqrt(3 (1 - alpha')) (inf when sigma_a = 0)"),
        "r2_mm2": mk(r2, (alpha, l_mm, unknown), f"l'^2 G(alpha') of {model} (inf when sigma_a = 0)"),
        "R_d": mk(r_d, (alpha, unknown), f"half-space R_d(alpha', eta) of {model}"),
    }


def _rows(a: Any, r0: int, r1: int) -> NDArray[Any]:
    """Rows r0:r1 of an (H, W, ...) array as (h*W, ...) (a view for contiguous arrays and memory maps)."""
    t = np.asarray(a[r0:r1])
    return t.reshape((-1,) + t.shape[2:])


# --------------------------------------------------------------------------------------------------------------
# region summaries
# --------------------------------------------------------------------------------------------------------------
def _median_ci(x: Array, confidence: float) -> tuple[float, float, float]:
    """Median and distribution-free order-statistic interval (binomial) for the median of i.i.d. samples.

    O(n): the three order statistics come from one ``np.partition`` in the maps' own precision (no full sort and
    no float64 copy of a 24-megapixel region).
    """
    x = np.asarray(x)
    fin = np.isfinite(x)
    if not fin.all():
        x = x[fin]
    n = x.size
    if n == 0:
        return float("nan"), float("nan"), float("nan")
    if n < 6:
        x = np.sort(x.astype(np.float64))
        return float(np.median(x)), float(x[0]), float(x[-1])
    lo_k = max(int(stats.binom.ppf((1 - confidence) / 2, n, 0.5)) - 1, 0)
    hi_k = min(int(stats.binom.isf((1 - confidence) / 2, n, 0.5)), n - 1)
    mid = sorted({(n - 1) // 2, n // 2})
    part = np.partition(x, sorted({lo_k, hi_k, *mid}))
    med = 0.5 * (float(part[(n - 1) // 2]) + float(part[n // 2]))
    return med, float(part[lo_k]), float(part[hi_k])


@dataclass(frozen=True)
class ParameterSummary:
    """Per-channel value (3,) and interval (3, 2) of one parameter over a region."""

    value: Array
    interval: Array


@dataclass(frozen=True)
class DiffusionSummary:
    """Region summary. ``params[name]`` for name in albedo, shortening, R_d, alpha_prime, l_prime_mm,
    sigma_t_prime_per_mm, sigma_s_prime_per_mm, sigma_a_per_mm, D_mm, l_d_mm, r2_mm2.

    ``status`` per channel: "ok", "censored" (a model bound was hit: the interval is one-sided) or
    "unknown" (no usable pixels; values NaN). ``n_pixels`` per channel. ``spread``: (3, 2) 25/75 %
    quantiles of the per-pixel D_mm (a dispersion diagnostic, not an interval).
    """

    params: dict[str, ParameterSummary]
    status: tuple[str, str, str]
    n_pixels: NDArray[np.int64]
    confidence: float
    method: str
    spread_D_mm: Array
    provenance: dict[str, Any] = field(default_factory=dict)

    def value(self, name: str) -> Array:
        return self.params[name].value

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"status": list(self.status), "n_pixels": self.n_pixels.tolist(),
                               "confidence": self.confidence, "method": self.method}
        for k, p in self.params.items():
            out[k] = {"value": p.value.tolist(), "interval": p.interval.tolist()}
        out["model"] = self.provenance.get("model", "dipole-jensen")
        if "model_bias" in self.provenance:
            out["model_bias"] = self.provenance["model_bias"]
        return out


def summarize(dmaps: DiffusionMaps, region: ArrayLike | None = None, *, confidence: float = 0.95,
              systematic_shortening: float = 5e-4, systematic_albedo_rel: float = 2e-3,
              fdr: str = "fit", model: str | None = None, model_bias: bool = True) -> DiffusionSummary:
    """Robust per-channel summary over ``region`` (default: every known pixel).

    ``model``: the profile model of the maps (default: the one recorded in ``dmaps.provenance``, else
    "dipole-jensen"); ``model_bias``: also report the model's bias against the Monte Carlo table at the summary's
    parameters (:func:`grounded_model_bias`) in ``provenance["model_bias"]`` (and :meth:`DiffusionSummary.as_dict`).

    When the radius is uniform over the region (a known sphere) the *observables* are pooled: median albedo and
    median shortening with order-statistic intervals for the median (i.i.d. pixel noise), widened by the
    systematic allowances (``systematic_shortening`` absolute, ``systematic_albedo_rel`` relative: residuals of
    the discrete-LED correction, docs/gradients.md), then inverted once with :func:`invert_sphere_scalar` (or
    the first-order formula for ``method="small_blur"``); the interval of every parameter is the range over the
    four corners of the (albedo, shortening) box, which is exact for these monotone maps. Otherwise (varying
    curvature) the parameters' own per-pixel medians and order-statistic intervals are reported.
    """
    H, W = dmaps.albedo.shape[:2]
    if model is None:
        model = str(dmaps.provenance.get("model", "dipole-jensen"))
    check_grounded_model(model, dmaps.method, dmaps.eta)
    reg = np.ones((H, W), bool) if region is None else np.asarray(region, dtype=bool)
    eta = dmaps.eta
    vals = {k: np.full(3, np.nan) for k in _PARAMS}
    ints = {k: np.full((3, 2), np.nan) for k in _PARAMS}
    status: list[str] = []
    npix = np.zeros(3, np.int64)
    spread = np.full((3, 2), np.nan)
    for c in range(3):
        m = reg & ~dmaps.unknown[..., c]
        npix[c] = int(m.sum())
        if npix[c] == 0:
            status.append("unknown")
            continue
        d_c = dmaps.D_mm[..., c][m]
        spread[c] = np.percentile(d_c[np.isfinite(d_c)], [25, 75]) if np.isfinite(d_c).any() else np.nan
        radii = dmaps.radius_mm[m]
        uniform = np.ptp(radii) <= 1e-6 * float(np.max(radii))
        A_med, A_lo, A_hi = _median_ci(dmaps.albedo[..., c][m], confidence)
        S_med, S_lo, S_hi = _median_ci(dmaps.shortening[..., c][m], confidence)
        vals["albedo"][c], ints["albedo"][c] = A_med, (A_lo * (1 - systematic_albedo_rel),
                                                      A_hi * (1 + systematic_albedo_rel))
        vals["shortening"][c], ints["shortening"][c] = S_med, (S_lo - systematic_shortening,
                                                              S_hi + systematic_shortening)
        if uniform:
            rho = float(radii[0])

            def solve(a: float, s: float) -> tuple[dict[str, float], bool]:
                if dmaps.method == "sphere":
                    al, ll, cens = invert_sphere_scalar(a, s, rho, eta, fdr=fdr)
                else:
                    al, c_a = _alpha_from_rd(a, eta, fdr, model)
                    r2 = 4.0 * (1.0 - s) * rho * rho / 2.0
                    G = _G_model(al, eta, fdr, model)
                    cens = r2 <= 0 or c_a
                    ll = float(np.sqrt(max(r2, 0.0) / G)) if G > 0 else float("nan")
                    ll = max(ll, 1e-4 * rho)
                d = _derived(np.array(al), np.array(ll), eta, fdr)
                if model != "dipole-jensen":
                    d["R_d"] = np.asarray(_model_rd(al, eta, fdr, model))
                    d["r2_mm2"] = np.asarray(ll * ll * G)
                return {k: float(v) for k, v in d.items()}, cens

            point, cens = solve(A_med, S_med)
            corners = [solve(a, s)[0] for a in ints["albedo"][c] for s in ints["shortening"][c]]
            for k, v in point.items():
                vals[k][c] = v
                cv = np.array([cn[k] for cn in corners] + [v])
                ints[k][c] = (np.nanmin(cv), np.nanmax(cv))
            status.append("censored" if cens else "ok")
        else:
            cens = bool(np.mean(dmaps.censored[..., c][m]) > 0.5)
            for k in ("R_d", "alpha_prime", "l_prime_mm", "sigma_t_prime_per_mm", "sigma_s_prime_per_mm",
                      "sigma_a_per_mm", "D_mm", "l_d_mm", "r2_mm2"):
                med, lo, hi = _median_ci(getattr(dmaps, k)[..., c][m], confidence)
                vals[k][c], ints[k][c] = med, (lo, hi)
            status.append("censored" if cens else "ok")
    params = {k: ParameterSummary(vals[k], ints[k]) for k in _PARAMS}
    prov = {"confidence": confidence, "systematic_shortening": systematic_shortening,
            "systematic_albedo_rel": systematic_albedo_rel, "maps": dmaps.provenance, "model": model}
    if model_bias:
        try:
            prov["model_bias"] = grounded_model_bias(vals["sigma_s_prime_per_mm"], vals["sigma_a_per_mm"], eta,
                                                     model, fdr=fdr)
        except (ValueError, FileNotFoundError) as exc:  # e.g. eta outside the table: say so, do not fail
            prov["model_bias"] = {"available": False, "reason": str(exc)}
    st3 = (status[0], status[1], status[2])
    return DiffusionSummary(params, st3, npix, confidence, dmaps.method, spread, prov)


# --------------------------------------------------------------------------------------------------------------
# sphere convenience (the end-to-end demo path)
# --------------------------------------------------------------------------------------------------------------
def sphere_geometry(camera: Any, center_mm: ArrayLike, radius_mm: float) -> tuple[Array, Array, NDArray[np.bool_]]:
    """(normals (H, W, 3) NaN off the sphere, view directions (H, W, 3) towards the camera, hit mask (H, W))
    for a :class:`estimation.camera.PinholeCamera` and a sphere in the rig frame."""
    from .camera import intersect_sphere

    origins, dirs = camera.pixel_rays()
    pts, hit = intersect_sphere(origins, dirs, center_mm, radius_mm)
    n = (pts - np.asarray(center_mm, dtype=np.float64)) / float(radius_mm)
    view = -dirs
    return n, view, hit


@dataclass(frozen=True)
class SphereEstimate:
    """Per-pixel grounded maps and their region summary for a known sphere."""

    maps: DiffusionMaps
    summary: DiffusionSummary


def estimate_sphere(maps: GradientMaps, *, radius_mm: float, true_normals: ArrayLike | None = None,
                    camera: Any = None, center_mm: ArrayLike | None = None, region: ArrayLike | None = None,
                    method: str = "sphere", erode_px: int = 2, confidence: float = 0.95,
                    fdr: str = "fit", inversion: str = "table", tile_rows: int = 256,
                    out_dir: str | Path | None = None, workers: int | None = None,
                    model: str = "dipole-jensen") -> SphereEstimate:
    """Grounded estimate on a known sphere: per-pixel maps plus the region summary (median + interval).

    The true normals come from ``true_normals`` (H, W, 3) or from ``camera`` + ``center_mm`` via
    :func:`sphere_geometry`. ``region`` defaults to the pixels on the sphere, eroded by ``erode_px`` so that
    silhouette pixels (partly background) are not used; masked / grazing / dark pixels of ``maps`` are excluded.
    ``inversion``, ``tile_rows``, ``out_dir``: see :func:`estimate_diffusion` (the summary always inverts exactly).
    """
    from scipy import ndimage

    if true_normals is None:
        if camera is None or center_mm is None:
            raise ValueError("give true_normals, or camera and center_mm")
        true_normals = sphere_geometry(camera, center_mm, radius_mm)[0]
    H, W = maps.shape
    if np.shape(true_normals) != (H, W, 3):
        raise ValueError(f"true_normals must be (H, W, 3) = {(H, W, 3)}, got {np.shape(true_normals)}")
    if region is None:
        reg = np.empty((H, W), bool)
        for r0 in range(0, H, tile_rows):
            t = np.asarray(true_normals[r0:r0 + tile_rows])
            reg[r0:r0 + tile_rows] = np.isfinite(t[..., 0] + t[..., 1] + t[..., 2])
    else:
        reg = np.asarray(region, dtype=bool)
    if erode_px > 0:
        reg = ndimage.binary_erosion(reg, iterations=int(erode_px))
    dm = estimate_diffusion(maps, true_normals, sphere_radius_mm=radius_mm, method=method, region=reg, fdr=fdr,
                            inversion=inversion, tile_rows=tile_rows, out_dir=out_dir, workers=workers,
                            model=model)
    return SphereEstimate(dm, summarize(dm, reg, confidence=confidence, fdr=fdr, model=model))


# --------------------------------------------------------------------------------------------------------------
# the seed's estimator
# --------------------------------------------------------------------------------------------------------------
def _nz(maps: GradientMaps, axis_normals: ArrayLike | None) -> Array:
    H, W = maps.shape
    if axis_normals is None:
        ax = maps.view_dirs.astype(np.float64)
    else:
        ax = np.asarray(axis_normals, dtype=np.float64)
        if ax.shape == (3,):
            ax = np.broadcast_to(ax, (H, W, 3))
        if ax.shape != (H, W, 3):
            raise ValueError("true_normals must be (H, W, 3) or (3,)")
    with np.errstate(invalid="ignore", divide="ignore"):
        ax = ax / np.linalg.norm(ax, axis=-1, keepdims=True)
    return _shortening(maps, ax)


@dataclass(frozen=True)
class SeedCalibration:
    """Empirical length k [mm] per channel for D = k R_d/|n_z|, with its spread and where it came from."""

    k_mm: Array
    interval_mm: Array  # (3, 2) order-statistic interval of the median
    n_pixels: NDArray[np.int64]
    provenance: dict[str, Any]


@dataclass(frozen=True)
class SeedEstimate:
    D_mm: NDArray[np.float32]
    n_z: NDArray[np.float32]
    unknown: NDArray[np.bool_]
    provenance: dict[str, Any]


def calibrate_k(maps: GradientMaps, D_ref_mm: ArrayLike, *, region: ArrayLike | None = None,
                true_normals: ArrayLike | None = None, nz_floor: float = 0.05, confidence: float = 0.95,
                provenance: Mapping[str, Any] | None = None) -> SeedCalibration:
    """k = median over ``region`` of D_ref |n_z| / R_d, per channel, for a reference of known D (mm).

    Calibrate in the *actual* capture geometry (same rig, similar shape and size): k is an empirical length, not
    a material constant (science.md sec. 4). ``provenance`` (reference name, geometry, date...) is stored.
    """
    D_ref = np.broadcast_to(np.asarray(D_ref_mm, dtype=np.float64).reshape(-1), (3,))
    nz = _nz(maps, true_normals)
    reg = np.ones(maps.shape, bool) if region is None else np.asarray(region, dtype=bool)
    k = np.full(3, np.nan)
    iv = np.full((3, 2), np.nan)
    n = np.zeros(3, np.int64)
    for c in range(3):
        with np.errstate(invalid="ignore", divide="ignore"):
            kk = D_ref[c] * np.abs(nz[..., c]) / maps.albedo[..., c]
        m = reg & ~maps.unknown[..., c] & (np.abs(nz[..., c]) >= nz_floor) & np.isfinite(kk)
        n[c] = int(m.sum())
        k[c], iv[c, 0], iv[c, 1] = _median_ci(kk[m], confidence)
    prov = {"estimator": "seed (Zhu et al.)", "D_ref_mm": D_ref.tolist(), "nz_floor": nz_floor,
            "nz_axis": "true_normals" if true_normals is not None else "view direction",
            "gradients": dict(maps.provenance), **dict(provenance or {})}
    return SeedCalibration(k, iv, n, prov)


def diffusion_seed(maps: GradientMaps, k_mm: ArrayLike, provenance: Mapping[str, Any], *,
                   true_normals: ArrayLike | None = None, nz_floor: float = 0.05) -> SeedEstimate:
    """The seed's D = k R_d / |n_z| per pixel and channel (k from :func:`calibrate_k`; its provenance is kept).

    |n_z| < ``nz_floor`` (n_z -> 0: grazing or inverted normals) and masked pixels are unknown (NaN).
    """
    k = np.broadcast_to(np.asarray(k_mm, dtype=np.float64).reshape(-1), (3,))
    if np.any(~np.isfinite(k)) or np.any(k <= 0):
        raise ValueError("k_mm must be finite and > 0 (calibrate it with calibrate_k)")
    nz = _nz(maps, true_normals)
    with np.errstate(invalid="ignore", divide="ignore"):
        D = k * maps.albedo / np.abs(nz)
    unknown = maps.unknown | ~(np.abs(nz) >= nz_floor) | ~np.isfinite(D)
    prov = {"estimator": "seed (Zhu et al.)", "k_mm": k.tolist(), "nz_floor": nz_floor,
            "calibration": dict(provenance)}
    return SeedEstimate(np.where(unknown, np.nan, D).astype(np.float32),
                        np.where(unknown, np.nan, nz).astype(np.float32), unknown, prov)


def seed_regression(rd_over_nz: ArrayLike, D_mm: ArrayLike) -> dict[str, float]:
    """Regress log D on log(R_d/|n_z|) across reference materials: the seed predicts slope 1.

    Returns slope, intercept (log k), their standard errors, and k_mm = exp(intercept) (meaningful only when the
    slope is compatible with 1).
    """
    x = np.log(np.asarray(rd_over_nz, dtype=np.float64).ravel())
    y = np.log(np.asarray(D_mm, dtype=np.float64).ravel())
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size < 3:
        raise ValueError("need at least 3 finite (R_d/|n_z|, D) pairs")
    res = stats.linregress(x, y)
    return {"slope": float(res.slope), "slope_se": float(res.stderr), "intercept": float(res.intercept),
            "intercept_se": float(res.intercept_stderr), "k_mm": float(np.exp(res.intercept)),
            "r": float(res.rvalue), "n": int(x.size)}


@dataclass(frozen=True)
class EstimateComparison:
    """Seed vs grounded D: ratio map, where they disagree by more than ``rel_tol``, per-channel medians."""

    ratio: NDArray[np.float32]
    disagree: NDArray[np.bool_]
    median_ratio: Array
    fraction_disagree: Array
    rel_tol: float


def compare_estimates(seed: SeedEstimate, grounded: DiffusionMaps, *, rel_tol: float = 0.2,
                      region: ArrayLike | None = None) -> EstimateComparison:
    """Where (and how much) D_seed / D_grounded departs from 1 by more than ``rel_tol`` (both known only)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = seed.D_mm.astype(np.float64) / grounded.D_mm.astype(np.float64)
    known = ~seed.unknown & ~grounded.unknown & np.isfinite(ratio)
    if region is not None:
        known &= np.asarray(region, dtype=bool)[..., None]
    dis = known & (np.abs(np.log(np.where(known, ratio, 1.0))) > np.log1p(rel_tol))
    med = np.array([np.median(ratio[..., c][known[..., c]]) if known[..., c].any() else np.nan for c in range(3)])
    frac = np.array([dis[..., c].sum() / max(known[..., c].sum(), 1) if known[..., c].any() else np.nan
                     for c in range(3)])
    return EstimateComparison(np.where(known, ratio, np.nan).astype(np.float32), dis, med, frac, rel_tol)


# --------------------------------------------------------------------------------------------------------------
# fine relief: local spectral ratio (diffuse vs specular normal maps)
# --------------------------------------------------------------------------------------------------------------
def _tangent_components(true_normals: Array) -> NDArray[np.intp]:
    """Indices of the two rig-frame components that carry the relief (largest variance of the true normals)."""
    return np.argsort(true_normals.reshape(-1, 3).var(axis=0))[-2:]


def _window(h: int, w: int, window: str) -> Array:
    if window == "hann":
        return np.outer(np.hanning(h), np.hanning(w))
    if window == "none":
        return np.ones((h, w))
    raise ValueError(f"unknown window {window!r}; valid: hann, none")


def _unit_diffuse(Dn: Array, c: int) -> Array:
    return Dn[..., c, :] / np.linalg.norm(Dn[..., c, :], axis=-1, keepdims=True)


def relief_mtf(diffuse_normals: ArrayLike, true_normals: ArrayLike, pixel_mm: float, *, n_bins: int | None = None,
               window: str = "hann") -> tuple[Array, Array, Array]:
    """Diagnostic estimate of the blur's modulation transfer M(k) = R^(k)/R^(0) from one window of normal maps.

    ``diffuse_normals`` (h, w, 3 channels, 3) and ``true_normals`` (h, w, 3) (specular normals) over a small,
    fully valid window of roughly flat-on-average relief, pixel size ``pixel_mm`` on the surface. The two
    tangential components (largest variance) of both maps are windowed and Fourier transformed;
    M(k) = Re<D T*> / <|T|^2> per annulus (a cross-spectral estimate, unbiased under noise in D). Annuli are one
    fundamental frequency 2 pi/(N pixel_mm) wide up to Nyquist unless ``n_bins`` is given. Returns
    (k [rad/mm] (n_bins,), M (n_bins, 3), weight (n_bins,) = summed |T|^2). Window leakage averages M over ~2
    bins, so use windows much wider than l' (>= 8 l'); :func:`fit_relief` has no such bias.
    """
    Dn = np.asarray(diffuse_normals, dtype=np.float64)
    Tn = np.asarray(true_normals, dtype=np.float64)
    h, w = Tn.shape[:2]
    if Dn.shape != (h, w, 3, 3):
        raise ValueError("diffuse_normals must be (h, w, 3, 3) matching true_normals (h, w, 3)")
    if not (np.isfinite(Dn).all() and np.isfinite(Tn).all()):
        raise ValueError("the window must be fully valid (no NaN)")
    win = _window(h, w, window)
    ky = 2 * np.pi * np.fft.fftfreq(h, d=pixel_mm)
    kx = 2 * np.pi * np.fft.fftfreq(w, d=pixel_mm)
    kk = np.sqrt(ky[:, None] ** 2 + kx[None, :] ** 2)
    nb = int(n_bins) if n_bins is not None else min(h, w) // 2
    edges = np.linspace(0.0, np.pi / pixel_mm, nb + 1)
    edges[0] = 0.5 * (edges[1] - edges[0])  # drop the DC term
    centres = 0.5 * (edges[1:] + edges[:-1])
    num = np.zeros((nb, 3))
    den = np.zeros(nb)
    b = np.digitize(kk.ravel(), edges) - 1
    valid = (b >= 0) & (b < nb)
    for comp in _tangent_components(Tn):
        t = Tn[..., comp] - Tn[..., comp].mean()
        Tf = np.fft.fft2(t * win)
        p = (np.abs(Tf) ** 2).ravel()
        den += np.bincount(b[valid], weights=p[valid], minlength=nb)[:nb]
        for c in range(3):
            d = _unit_diffuse(Dn, c)[..., comp]
            Df = np.fft.fft2((d - d.mean()) * win)
            cr = np.real(Df * np.conj(Tf)).ravel()
            num[:, c] += np.bincount(b[valid], weights=cr[valid], minlength=nb)[:nb]
    with np.errstate(invalid="ignore", divide="ignore"):
        M = np.where(den[:, None] > 0, num / den[:, None], np.nan)
    return centres, M, den


def fit_relief(diffuse_normals: ArrayLike, true_normals: ArrayLike, pixel_mm: float, albedo: ArrayLike,
               eta: float, *, margin_px: int | None = None, window: str = "hann", fdr: str = "fit",
               l_bounds_mm: tuple[float, float] = (1e-3, 1e2)) -> Array:
    """l' [mm] per channel from fine relief: the diffuse normal map is the true one filtered by M(k).

    For each channel, alpha' comes from ``albedo`` (3,) (inversion of R_d, eta fixed); then the one length l'
    minimizes || w * (d_t - M_l' (x) n_t) ||^2 over the two tangential components, where (x) filters the
    (reflect-padded) true normal map by the Jensen MTF R^(k)/R^(0) in the Fourier domain and w is the window
    restricted to pixels at least ``margin_px`` (default a quarter of the window) from the edge: a diffuse
    normal depends on the relief within a few l_d = 1/sigma_tr around it, which the map must contain. Because the
    model is windowed exactly like the data, window leakage does not bias it (unlike the binned ratio of
    :func:`relief_mtf`); by Parseval this is the spectral-ratio fit weighted by the relief power. Requirements:
    pixel << l', and margin >~ 2 l_d. Bounded scalar minimization in log l'; NaN where the albedo is not usable.
    """
    Dn = np.asarray(diffuse_normals, dtype=np.float64)
    Tn = np.asarray(true_normals, dtype=np.float64)
    h, w = Tn.shape[:2]
    if Dn.shape != (h, w, 3, 3) or not (np.isfinite(Dn).all() and np.isfinite(Tn).all()):
        raise ValueError("need finite diffuse_normals (h, w, 3, 3) and true_normals (h, w, 3)")
    alb = np.broadcast_to(np.asarray(albedo, dtype=np.float64).reshape(-1), (3,))
    m = min(h, w) // 4 if margin_px is None else int(margin_px)
    if not 0 <= 2 * m < min(h, w) - 2:
        raise ValueError("margin_px leaves no pixels")
    win = np.zeros((h, w))
    win[m:h - m, m:w - m] = _window(h - 2 * m, w - 2 * m, window)
    ph, pw = h // 2, w // 2
    comps = _tangent_components(Tn)
    padded = [np.pad(Tn[..., c] - Tn[..., c].mean(), ((ph, ph), (pw, pw)), mode="reflect") for c in comps]
    H2, W2 = padded[0].shape
    ky = 2 * np.pi * np.fft.fftfreq(H2, d=pixel_mm)
    kx = 2 * np.pi * np.fft.fftfreq(W2, d=pixel_mm)
    kk = np.sqrt(ky[:, None] ** 2 + kx[None, :] ** 2)
    spectra = [np.fft.fft2(p) for p in padded]
    out = np.full(3, np.nan)
    for c in range(3):
        if not np.isfinite(alb[c]) or alb[c] <= 0:
            continue
        al = float(reduced_albedo_from_total_reflectance(min(alb[c], 1.0), eta, fdr=fdr))
        d = _unit_diffuse(Dn, c)
        data = [(d[..., comp] - d[..., comp].mean()) for comp in comps]

        def cost(lnl: float) -> float:
            st = float(np.exp(-lnl))
            M = hankel_transform(kk, al * st, (1.0 - al) * st, eta, fdr=fdr)
            M = M / hankel_transform(0.0, al * st, (1.0 - al) * st, eta, fdr=fdr)
            tot = 0.0
            for spec, dat in zip(spectra, data):
                pred = np.real(np.fft.ifft2(M * spec))[ph:ph + h, pw:pw + w]
                pred = pred - pred.mean()
                tot += float(np.sum((win * (dat - pred)) ** 2))
            return tot

        res = optimize.minimize_scalar(cost, bounds=(np.log(l_bounds_mm[0]), np.log(l_bounds_mm[1])),
                                       method="bounded", options={"xatol": 1e-5})
        out[c] = float(np.exp(res.x))
    return out
