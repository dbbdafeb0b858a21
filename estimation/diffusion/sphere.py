"""The sphere model in closed form: the albedo and shortening of a sphere of radius rho under the truncated
half-space dipole, their exact inversion, and curvature from normals (``estimation.diffusion``, method "sphere").
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import optimize

from ..dipole import boundary_A, cumulative_disk, dipole_coefficients, second_moment_factor_G
from .models import _S_MAX, Array, _coeffs_from_s_l, _halfspace_s_table, _phi1, _uniform_lookup


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
