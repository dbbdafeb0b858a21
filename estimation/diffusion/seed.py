"""The seed's estimator (Zhu et al.): D = k R_d / |n_z| with a calibrated length k, its regression check and the
comparison with the grounded estimate (``estimation.diffusion``).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import stats

from ..gradients import GradientMaps
from .maps import DiffusionMaps, _shortening
from .models import Array
from .summary import _median_ci


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
