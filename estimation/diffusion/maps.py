"""Per-pixel grounded diffusion maps (:func:`estimate_diffusion`) with the fast tabulated inverse of the sphere
model, streamed by tiles (``estimation.diffusion``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..dipole import boundary_A, second_moment_factor_G, total_diffuse_reflectance_albedo
from ..gradients import DerivedMap, GradientMaps, map_allocator, tile_workers
from ..gradients.compute import _BLOCK_PX
from ..gradients.storage import _run_tiles
from .models import METHODS, Array, _halfspace_s_table, _model_tables, _s_lookup, _uniform_lookup, check_grounded_model
from .sphere import _model_pair, invert_sphere


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
