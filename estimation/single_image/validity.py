"""When is a flat-profile estimate a measurement? Per-parameter status ("ok" / "weak") of every single-image result.

The profile models (the dipoles, the Monte Carlo half-space table) explain a patch's radiance by a *flat,
semi-infinite* profile with a separable angular factor. Measured on Monte Carlo frames (benchmarks/scene_zoo.py,
docs/model-error.md), that is wrong by far more than the statistical intervals say in three situations, which
:func:`flat_model_reasons` detects from the geometry and the fitted parameters:

- **edges and curvature within a few diffusion lengths**: light that would diffuse on through the half-space leaves
  through the next face instead (a 20 mm marble cube: the table's sigma_s' -37 %). The check: the median over the
  observed patches of the distance to the nearest crease (a neighbouring patch whose normal differs by more than
  :data:`CREASE_DEG`) or to a curvature radius, against :data:`FLAT_LENGTHS` fitted diffusion lengths l_d;
- **an index-matched boundary** (eta < :data:`ETA_MATCHED`): low-order scattering leaves the surface far from the
  separable, Lambertian-like angular factor (measured on a 100 mm box of skin1-G: 18-53 % more radiance than the
  table at oblique light and view; 4-16 % for marble);
- **low albedo** (alpha' < :data:`LOW_ALBEDO`): single and low-order scattering, strongly angle dependent, carry a
  large part of the light (skin1-G on the same box at eta 1.3: 9-18 %).

:func:`parameter_status` turns a result, the reasons above and (for the reference-corrected fit) convergence into
the status every estimate reports: sigma_s' is "ok" only when nothing forces "weak", its 95 % interval spans at
most :data:`MAX_OK_INTERVAL_RATIO` and lies within :data:`OK_TOLERANCE_SIGMA_S_PRIME` of the estimate; sigma_a only
when, in addition, it is identifiable (its interval two-sided and narrower than a factor 10) and its interval lies
within :data:`OK_TOLERANCE_SIGMA_A` of the estimate. So an "ok" parameter meets its tolerance (issue 15: sigma_s'
within 10 %, sigma_a within 50 %) whenever its interval covers the truth: a wider interval cannot claim it. "weak" is not "wrong": it says the number is not a measurement to quote without its
interval, and the interval is what covers the truth.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from .geometry import Patches
from .results import SingleImageResult

__all__ = ["MAX_OK_INTERVAL_RATIO", "OK_TOLERANCE_SIGMA_S_PRIME", "OK_TOLERANCE_SIGMA_A", "CREASE_DEG", "FLAT_LENGTHS", "ETA_MATCHED", "LOW_ALBEDO", "flat_model_reasons",
           "parameter_status"]

Array = NDArray[np.float64]

#: a converged / valid sigma_s' is "ok" only when its 95 % interval spans at most this factor (hi / lo): an "ok"
#: estimate is then within ~22 % of the truth whenever its interval covers it
MAX_OK_INTERVAL_RATIO: float = 1.5

#: an "ok" sigma_s' has its 95 % interval inside [estimate / (1 + tol), estimate x (1 + tol)]: if the interval covers
#: the truth, the estimate is then within -9.1 % / +10 % of it (issue 15's tolerance). Measured need: the zoo's z15
#: (apple-G, one point light) said "ok" at +10.5 % with a +-17 % interval (docs/model-error.md sec. 4)
OK_TOLERANCE_SIGMA_S_PRIME: float = 0.10
#: the same for sigma_a (issue 15's tolerance 50 %): an "ok" sigma_a is within -33 % / +50 % when covered
OK_TOLERANCE_SIGMA_A: float = 0.50
CREASE_DEG: float = 20.0
#: the flat profile is trusted when the median observed patch lies this many diffusion lengths from a crease and
#: its curvature radius is at least as large
FLAT_LENGTHS: float = 3.0
ETA_MATCHED: float = 1.1
LOW_ALBEDO: float = 0.95


def _flat_distance_mm(patches: Patches, rows: NDArray[np.intp]) -> Array:
    """Per observed patch (``rows``): min(distance to the nearest crease patch, local curvature radius) in mm."""
    c, n = patches.centers_mm, patches.normals
    spacing = patches.spacing_mm if patches.spacing_mm > 0 else 1.0
    tree = cKDTree(c)
    pairs = tree.query_pairs(1.6 * spacing, output_type="ndarray")
    if pairs.size == 0:
        return np.full(rows.size, np.inf)
    cosang = np.clip(np.einsum("ij,ij->i", n[pairs[:, 0]], n[pairs[:, 1]]), -1.0, 1.0)
    crease = np.zeros(len(c), bool)
    sharp = cosang < np.cos(np.radians(CREASE_DEG))
    crease[pairs[sharp, 0]] = True
    crease[pairs[sharp, 1]] = True
    d_crease = np.full(rows.size, np.inf)
    if crease.any():
        d_crease, _ = cKDTree(c[crease]).query(c[rows])
    # curvature radius from the smooth pairs: distance / angle between the normals (flat: infinite)
    smooth = ~sharp
    ang = np.arccos(cosang[smooth])
    dist = np.linalg.norm(c[pairs[smooth, 0]] - c[pairs[smooth, 1]], axis=1)
    radius = np.where(ang > 1e-6, dist / np.maximum(ang, 1e-12), np.inf)
    r_patch = np.full(len(c), np.inf)
    np.minimum.at(r_patch, pairs[smooth, 0], radius)
    np.minimum.at(r_patch, pairs[smooth, 1], radius)
    return np.minimum(d_crease, r_patch[rows])


def flat_model_reasons(patches: Patches, observed: NDArray[np.bool_], l_d_mm: Array, albedo: Array, eta: float
                       ) -> list[str]:
    """Per channel, why a flat-profile estimate is not to be trusted here ("" when nothing is found): module
    docstring. ``observed`` (m, C) over the visible patches; ``l_d_mm``, ``albedo`` (C,) the fitted values."""
    vis = patches.visible_index
    out: list[str] = []
    for c in range(len(l_d_mm)):
        rows = vis[observed[:, c]]
        why: list[str] = []
        if rows.size:
            d = float(np.median(_flat_distance_mm(patches, rows)))
            if not d >= FLAT_LENGTHS * float(l_d_mm[c]):
                why.append(f"edges or curvature within {d:.3g} mm of the median observed patch, against "
                           f"{FLAT_LENGTHS:g} l_d = {FLAT_LENGTHS * float(l_d_mm[c]):.3g} mm: the flat half-space "
                           "profile misses light that leaves through the next face (mc-table+reference corrects it)")
        if eta < ETA_MATCHED:
            why.append(f"index-matched boundary (eta {eta:g}): low-order scattering is not Lambertian-like there "
                       "(10-50 % model error measured)")
        if float(albedo[c]) < LOW_ALBEDO:
            why.append(f"low albedo ({float(albedo[c]):.3g}): single and low-order scattering are angle dependent "
                       "(up to ~20 % model error measured)")
        out.append("; ".join(why))
    return out


def _inside(value: float, lo: float, hi: float, tol: float) -> bool:
    """Is the interval [lo, hi] inside [value / (1 + tol), value x (1 + tol)] (value > 0, finite)?"""
    return bool(np.isfinite(value) and value > 0 and np.isfinite(hi) and lo >= value / (1.0 + tol)
                and hi <= value * (1.0 + tol))


def parameter_status(result: SingleImageResult, converged: NDArray[np.bool_] | None, *,
                     max_ratio: float = MAX_OK_INTERVAL_RATIO, extra_reasons: list[str] | None = None,
                     tol_sigma_s_prime: float = OK_TOLERANCE_SIGMA_S_PRIME, tol_sigma_a: float = OK_TOLERANCE_SIGMA_A
                     ) -> tuple[dict[str, list[str]], list[str]]:
    """Per channel "ok" | "weak" for sigma_s' and sigma_a (module docstring) and the reasons. ``converged`` (C,), or
    None when no iteration ran; ``extra_reasons`` (per channel; "" for none) force "weak" with that reason."""
    ssp_ci = np.asarray(result.sigma_s_prime_ci_per_mm, dtype=np.float64).reshape(-1, 2)
    n_ch = ssp_ci.shape[0]
    conv = np.ones(n_ch, bool) if converged is None else np.asarray(converged, bool)
    forced = extra_reasons or [""] * n_ch
    ident = list(result.sigma_a_identifiable_per_channel) or [False] * n_ch
    ssp = np.full(n_ch, np.nan) if result.sigma_s_prime_per_mm is None else \
        np.asarray(result.sigma_s_prime_per_mm, dtype=np.float64).reshape(-1)
    sa = np.full(n_ch, np.nan) if result.sigma_a_per_mm is None else \
        np.asarray(result.sigma_a_per_mm, dtype=np.float64).reshape(-1)
    sa_ci = np.full((n_ch, 2), np.nan) if result.sigma_a_ci_per_mm is None else \
        np.asarray(result.sigma_a_ci_per_mm, dtype=np.float64).reshape(-1, 2)
    st_s, st_a, reasons = [], [], []
    for c in range(n_ch):
        lo, hi = ssp_ci[c]
        why: list[str] = []
        if not conv[c]:
            why.append("the reference iteration did not converge")
        if forced[c]:
            why.append(forced[c])
        wide = not (lo > 0 and np.isfinite(hi) and hi / lo <= max_ratio)
        loose = not wide and not _inside(float(ssp[c]), lo, hi, tol_sigma_s_prime)
        s_ok = not why and not wide and not loose
        a_loose = bool(ident[c]) and not _inside(float(sa[c]), *sa_ci[c], tol_sigma_a)
        # sigma_a is no measurement while sigma_s' is not one: the two are estimated together (correlated)
        a_ok = s_ok and bool(ident[c]) and not a_loose
        if wide:
            why.append(f"sigma_s' interval {lo:.3g}-{hi:.3g} /mm spans more than a factor {max_ratio:g}")
        if loose:
            why.append(f"sigma_s' interval {lo:.3g}-{hi:.3g} /mm reaches beyond +-{100 * tol_sigma_s_prime:g} % of "
                       "the estimate (the tolerance an 'ok' claims)")
        if not ident[c]:
            why.append("sigma_a not identifiable (its interval)")
        elif a_loose:
            why.append(f"sigma_a interval {sa_ci[c][0]:.3g}-{sa_ci[c][1]:.3g} /mm reaches beyond "
                       f"+-{100 * tol_sigma_a:g} % of the estimate")
        st_s.append("ok" if s_ok else "weak")
        st_a.append("ok" if a_ok else "weak")
        reasons.append(f"channel {c}: " + ("; ".join(why) if why else "ok"))
    return {"sigma_s_prime_per_mm": st_s, "sigma_a_per_mm": st_a}, reasons
