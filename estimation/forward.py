"""Forward model: Fresnel-transmitted irradiance on surface patches -> diffuse exitance -> outgoing radiance.

The dipole BSSRDF (Jensen et al. 2001; Mukaigawa, Suzuki, Yagi 2009 Eq. 10):

    L_o(x_o, w_o) = (1/pi) F_t(eta, w_o) B(x_o),   B(x_o) = sum_k R(|x_o - x_k|) E_t(x_k) A_k,
    E_t(x) = integral F_t(eta, w) L_i(x, w) max(0, n.w) dw   (the seed's c_k = E_t(x_k) A_k).

Geometry in mm, rig frame of docs/architecture.md; colour channels along the last axis.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from .dipole import (DipoleCoefficients, check_model, cumulative_disk, cutoff_radius_mm, dipole_coefficients,
                     profile_from_coefficients)
from .fresnel import fresnel_transmittance

__all__ = [
    "diffuse_exitance",
    "radiance_from_exitance",
    "irradiance_point_lights",
    "irradiance_directional",
    "NEAR_FIELD_SPACINGS",
    "ring_radii",
]

Array = NDArray[np.float64]

#: near-field radius in units of the patch spacing sqrt(median patch area)
NEAR_FIELD_SPACINGS = 2.0

_PAIR_BUDGET = 1_500_000  # pair-distance elements per block (memory ~ 12 bytes x C x budget)


def _channel_arrays(sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike) -> tuple[Array, Array]:
    ssp = np.atleast_1d(np.asarray(sigma_s_prime_per_mm, dtype=np.float64))
    sa = np.atleast_1d(np.asarray(sigma_a_per_mm, dtype=np.float64))
    if ssp.ndim != 1 or sa.ndim != 1:
        raise ValueError("sigma arrays must be scalars or 1-D per-channel arrays")
    ssp, sa = np.broadcast_arrays(ssp, sa)
    return ssp.copy(), sa.copy()


def _channel_coefficients(ssp: Array, sa: Array, eta: float, model: str, fdr: str) -> list[DipoleCoefficients]:
    return [dipole_coefficients(ssp[c], sa[c], eta, model=model, fdr=fdr) for c in range(ssp.size)]


def diffuse_exitance(points_mm: ArrayLike, patch_centers_mm: ArrayLike, patch_areas_mm2: ArrayLike,
                     patch_irradiance: ArrayLike, sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike,
                     eta: float, *, model: str = "dipole-jensen", tolerance: float = 1e-7, chunk: int = 2048,
                     near_radius_mm: float | None = None, fdr: str = "fit") -> Array:
    """B(x_o) = sum_k R(|x_o - x_k|) E_k A_k for each output point, (P, 3) -> (P, C).

    ``patch_irradiance`` (K, C) (or (K,) for one channel) is the Fresnel-transmitted irradiance E_t per patch
    per channel, C = len(sigma arrays) (usually 3; scalar sigmas give C = 1 unless the irradiance has more
    channels). The near field — patches within ``near_radius_mm`` (default 2 patch spacings,
    spacing = sqrt(median patch area)) of x_o — is integrated exactly: sorted by distance, each near patch
    gets its equal-area annulus (:func:`ring_radii`; the own patch the central disk) and contributes E_k times
    the cumulative-disk closed form over that annulus. R is never point-sampled at d = 0, the weighting is
    local (R-weighted, unlike a mean irradiance over the near field), and a uniform irradiance gives exactly
    the disk integral. Farther patches contribute R(d_k) E_k A_k; those beyond the cutoff radius
    where the profile's tail holds less than ``tolerance`` of R_d (from the model's own decay, max over
    channels) are skipped via a KD-tree (``scipy.spatial.cKDTree``). ``chunk`` bounds the output points per
    block. Units: E in W/mm^2 (or any radiometric unit) gives B in the same unit.

    Accuracy: a flat plane under uniform irradiance gives B = R_d E within ~0.3% at spacings up to ~4 z_r
    (tests/estimation/test_forward.py); errors fall under refinement (sphere under a point light: 5120
    patches on a 10 mm sphere agree with 20480 to ~1% at the terminator, better elsewhere).
    """
    check_model(model)
    pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    ctr = np.asarray(patch_centers_mm, dtype=np.float64).reshape(-1, 3)
    area = np.asarray(patch_areas_mm2, dtype=np.float64).reshape(-1)
    irr = np.asarray(patch_irradiance, dtype=np.float64)
    if irr.ndim == 1:
        irr = irr[:, None]
    ssp, sa = _channel_arrays(sigma_s_prime_per_mm, sigma_a_per_mm)
    n_ch = max(ssp.size, irr.shape[1])
    if ssp.size not in (1, n_ch) or irr.shape[1] not in (1, n_ch):
        raise ValueError(f"channel mismatch: sigma arrays have {ssp.size}, irradiance has {irr.shape[1]}")
    ssp = np.broadcast_to(ssp, (n_ch,)).copy()
    sa = np.broadcast_to(sa, (n_ch,)).copy()
    irr = np.broadcast_to(irr, (irr.shape[0], n_ch))
    k = ctr.shape[0]
    if area.shape[0] != k or irr.shape[0] != k:
        raise ValueError("patch_centers_mm (K,3), patch_areas_mm2 (K,) and patch_irradiance (K,C) disagree in K")
    if np.any(area < 0) or not np.all(np.isfinite(irr)):
        raise ValueError("patch areas must be >= 0 and irradiance finite")
    out = np.zeros((pts.shape[0], n_ch))
    if pts.shape[0] == 0 or k == 0:
        return out
    eta_f = float(eta)
    coeffs = _channel_coefficients(ssp, sa, eta_f, model, fdr)
    spacing = float(np.sqrt(np.median(area[area > 0]))) if np.any(area > 0) else 0.0
    rho = float(near_radius_mm) if near_radius_mm is not None else NEAR_FIELD_SPACINGS * spacing
    r_cut = max(cutoff_radius_mm(tolerance, ssp, sa, eta_f, model=model, fdr=fdr), rho)
    ea = irr * area[:, None]  # (K, C) = c_k
    lo = np.minimum(pts.min(0), ctr.min(0))
    hi = np.maximum(pts.max(0), ctr.max(0))
    diag = float(np.linalg.norm(hi - lo))
    dense = r_cut >= diag
    tree = None if dense else cKDTree(ctr)
    block = max(1, min(int(chunk), _PAIR_BUDGET // max(k, 1))) if dense else max(1, int(chunk))
    for start in range(0, pts.shape[0], block):
        sl = slice(start, min(start + block, pts.shape[0]))
        p = pts[sl]
        if dense:
            out[sl] = _block_dense(p, ctr, area, ea, coeffs, ssp, sa, eta_f, model, fdr, rho)
        else:
            assert tree is not None
            out[sl] = _block_sparse(p, tree, area, ea, coeffs, ssp, sa, eta_f, model, fdr, rho, r_cut)
    return out


def ring_radii(rows: NDArray[np.intp], d: Array, area: Array) -> tuple[NDArray[np.intp], Array, Array]:
    """Equal-area annuli of the near patches of each output point, in order of distance.

    For the pairs (row j, patch k) of one near field, sorted by (j, d_jk), patch k is given the annulus
    between r_in = sqrt(S_prev/pi) and r_out = sqrt(S/pi), S being the cumulative area of the patches of row
    j up to and including k. The nearest (own) patch gets the central disk — the exact self-patch integral —
    and a uniform irradiance telescopes to the disk integral of the whole near field.
    Returns (order, r_in, r_out): ``order`` sorts the pairs; the radii are in that order.
    """
    order = np.lexsort((d, rows))
    r_sorted = rows[order]
    a_sorted = area[order]
    cs = np.cumsum(a_sorted)
    start = np.ones(r_sorted.size, dtype=bool)
    start[1:] = r_sorted[1:] != r_sorted[:-1]
    base = np.maximum.accumulate(np.where(start, cs - a_sorted, 0.0))
    cum = cs - base
    r_out = np.sqrt(cum / np.pi)
    r_in = np.sqrt(np.clip(cum - a_sorted, 0.0, None) / np.pi)
    return order, r_in, r_out


def _near_field(rows: NDArray[np.intp], cols: NDArray[np.intp], d: Array, area: Array, ea: Array, n_rows: int,
                ssp: Array, sa: Array, eta: float, model: str, fdr: str) -> Array:
    """sum over near patches of E_k times the exact integral of R over the patch's equal-area annulus."""
    out = np.zeros((n_rows, ea.shape[1]))
    if rows.size == 0:
        return out
    order, r_in, r_out = ring_radii(rows, d, area[cols])
    k = cols[order]
    j = rows[order]
    w = (cumulative_disk(r_out[:, None], ssp[None, :], sa[None, :], eta, model=model, fdr=fdr)
         - cumulative_disk(r_in[:, None], ssp[None, :], sa[None, :], eta, model=model, fdr=fdr))
    e_k = ea[k] / area[k][:, None]  # irradiance of the patch (ea = E A)
    for c in range(ea.shape[1]):
        out[:, c] = np.bincount(j, weights=w[:, c] * e_k[:, c], minlength=n_rows)
    return out


def _block_dense(p: Array, ctr: Array, area: Array, ea: Array, coeffs: list[DipoleCoefficients],
                 ssp: Array, sa: Array, eta: float, model: str, fdr: str, rho: float) -> Array:
    d = cdist(p, ctr)
    near = d <= rho
    rows, cols = np.nonzero(near)
    out = _near_field(rows, cols, d[rows, cols], area, ea, p.shape[0], ssp, sa, eta, model, fdr)
    for c, co in enumerate(coeffs):
        r = profile_from_coefficients(co, d)
        r[near] = 0.0
        out[:, c] += r @ ea[:, c]
    return out


def _block_sparse(p: Array, tree: cKDTree, area: Array, ea: Array, coeffs: list[DipoleCoefficients],
                  ssp: Array, sa: Array, eta: float, model: str, fdr: str, rho: float, r_cut: float) -> Array:
    n = p.shape[0]
    pairs = cKDTree(p).sparse_distance_matrix(tree, r_cut, output_type="ndarray")
    i = pairs["i"].astype(np.intp)
    j = pairs["j"].astype(np.intp)
    d = pairs["v"]
    near = d <= rho
    out = _near_field(i[near], j[near], d[near], area, ea, n, ssp, sa, eta, model, fdr)
    far = ~near
    i_f, j_f, d_f = i[far], j[far], d[far]
    for c, co in enumerate(coeffs):
        r = profile_from_coefficients(co, d_f)
        out[:, c] += np.bincount(i_f, weights=r * ea[j_f, c], minlength=n)
    return out


def radiance_from_exitance(exitance: ArrayLike, cos_out: ArrayLike, eta: float) -> Array:
    """Outgoing radiance L_o = F_t(eta, cos_out) / pi * B (Jensen 2001 Eq. 5 with the exit Fresnel factor).

    ``exitance`` (P, C) or (P,), ``cos_out`` (P,) cosine between normal and view direction (<= 0 gives 0).
    """
    b = np.asarray(exitance, dtype=np.float64)
    ft = fresnel_transmittance(eta, cos_out)
    if b.ndim == ft.ndim + 1:
        ft = ft[..., None]
    return ft / np.pi * b


def irradiance_point_lights(centers: ArrayLike, normals: ArrayLike, light_positions_mm: ArrayLike,
                            light_intensity: ArrayLike, eta: float, *, visibility: ArrayLike | None = None) -> Array:
    """Fresnel-transmitted irradiance of isotropic point lights, (K, C).

    E_t(x_k) = sum_l F_t(eta, cos_kl) max(0, cos_kl) I_l / |p_l - x_k|^2, cos_kl = n_k . (p_l - x_k)/|p_l - x_k|.
    ``light_intensity`` (L, C) is radiant intensity (W/sr-like); E comes out per mm^2. ``normals`` need not be
    unit length (they are normalized). Shadowing: none beyond n.l > 0, exact for convex objects; pass
    ``visibility`` (K, L) in [0, 1] for anything else (cast shadows: :func:`estimation.shadows.point_light_visibility`).
    """
    x = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    lp = np.asarray(light_positions_mm, dtype=np.float64).reshape(-1, 3)
    inten = np.asarray(light_intensity, dtype=np.float64)
    if inten.ndim == 1:
        inten = inten[:, None] if inten.shape[0] == lp.shape[0] else inten[None, :]
    if inten.shape[0] != lp.shape[0]:
        raise ValueError("light_intensity must be (L, C) with L = len(light_positions_mm)")
    v = lp[None, :, :] - x[:, None, :]  # (K, L, 3)
    dist2 = np.einsum("klc,klc->kl", v, v)
    if np.any(dist2 <= 0):
        raise ValueError("a point light coincides with a patch centre")
    cos = np.einsum("klc,kc->kl", v, n) / np.sqrt(dist2)
    cos_pos = np.maximum(cos, 0.0)
    w = fresnel_transmittance(eta, cos_pos) * cos_pos / dist2
    if visibility is not None:
        w = w * np.asarray(visibility, dtype=np.float64)
    return w @ inten


def transmitted_cosine(cos: ArrayLike, eta: float) -> Array:
    """F_t(eta, c) max(0, c) elementwise, with F_t evaluated only where c > 0 (about half of a patch x
    environment-direction table: half the cost, the same values)."""
    c = np.asarray(cos, dtype=np.float64)
    out = np.zeros(c.shape)
    m = c > 0.0
    cm = c[m]
    out[m] = fresnel_transmittance(eta, cm) * cm
    return out


def irradiance_directional(normals: ArrayLike, directions: ArrayLike, radiance_weights: ArrayLike,
                           eta: float, *, visibility: ArrayLike | None = None) -> Array:
    """Fresnel-transmitted irradiance from distant lights / environment samples, (K, C).

    E_t = sum_l F_t(eta, n.w_l) max(0, n.w_l) * weight_l, ``directions`` (L, 3) pointing from the surface
    *towards* the light (normalized here), ``radiance_weights`` (L, C) = radiance x solid angle (or irradiance
    at normal incidence for a distant point source). Shadowing: none beyond n.w > 0 (exact for convex objects);
    pass ``visibility`` (K, L) in [0, 1] for anything else (:func:`estimation.shadows.direction_visibility`; for
    an environment map's many directions :func:`estimation.shadows.environment_irradiance`).
    """
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    w = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    w = w / np.linalg.norm(w, axis=1, keepdims=True)
    wt = np.asarray(radiance_weights, dtype=np.float64)
    if wt.ndim == 1:
        wt = wt[:, None] if wt.shape[0] == w.shape[0] else wt[None, :]
    if wt.shape[0] != w.shape[0]:
        raise ValueError("radiance_weights must be (L, C) with L = len(directions)")
    a = transmitted_cosine(n @ w.T, eta)
    if visibility is not None:
        a = a * np.asarray(visibility, dtype=np.float64)
    return a @ wt
