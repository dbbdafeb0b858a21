"""Subsurface-scattering parameters from one image under known illumination (Mukaigawa, Suzuki, Yagi 2009).

"Analysis of Subsurface Scattering under Generic Illumination" (ICPR 2008 / seed 000): with known geometry and
illumination, the radiance of every visible patch j is (Eq. 10-13)

    l_j = pi L_o(P_j) / F_t(eta, w_o) = sum_k R(d_jk) c_k,   c_k = E_t(P_k) A_k,

and R is recovered either (as published) by quantizing the distances with linear-interpolation weights,
l ~ W r (Eq. 20-27), r = pinv(W) l (Eq. 28) and a dipole fit to r (Eq. 29), or — better — by fitting
(log sigma_s', log sigma_a) directly to the l_j with exact self-patch integrals. Methods (``method=``):

- ``"pinv"``: the published method. Uniform bins of ``bin_mm`` from 0 (the self term is point-sampled at d=0
  as in the paper); empty bins are zero columns of W — pinv returns 0 for them — so they are reported in the
  diagnostics and left out of the dipole fit (the one deviation from the paper). Unweighted fit of Eq. 29.
- ``"tikhonov"``: same bins, exact near-field integrals of the hat functions, second-difference penalty with
  lambda by generalized cross-validation, non-negative (NNLS), optionally monotone. The dipole is then fitted
  to R' in the metric of the data, || w (W R(theta) - W R') ||: under smooth irradiance the profile within
  ~1 mm is seen only through its disk integrals, so a pointwise fit to R' near d = 0 would be biased.
- ``"direct"`` (default): fit (log sigma_s', log sigma_a) to l_j = sum_k R(d_jk) c_k with exact self-patch
  integrals: the near field of patch j uses the equal-area rings of :func:`estimation.forward.ring_radii`
  (own patch = central disk) integrated exactly, far pairs are point terms; both are expressed on one fine
  grid (node 0, then 1 % log spacing from 1e-3 mm; linear interpolation, relative error ~1e-5) as
  l = W R(nodes; theta), so one model evaluation is one mat-vec. Grid start, then
  ``scipy.optimize.least_squares`` with bounds (3 starts); recovers its own forward model to ~1e-4.

Every method reports Jacobian confidence intervals and a profile-likelihood interval for sigma_a (which is
one-sided near 0: science.md sec. 6), ``sigma_a_identifiable`` with the reason, and diagnostics. Failures
return a falsy :class:`SingleImageResult` whose ``message`` says why (never NaN parameters).

Geometry in mm (rig frame), colour channels on the last axis.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Iterator, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import optimize, sparse
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from .dipole import (check_model, cutoff_radius_mm, dipole_coefficients,
                     profile_from_coefficients, reflectance_from_coefficients)
from .forward import NEAR_FIELD_SPACINGS, irradiance_directional, irradiance_point_lights, ring_radii
from .fresnel import fresnel_transmittance

__all__ = [
    "METHODS",
    "Patches",
    "PointLights",
    "DirectionalLights",
    "EnvironmentMap",
    "patches_from_mesh",
    "sample_image_at_patches",
    "patch_irradiance",
    "quantization_weights",
    "SingleImageDiagnostics",
    "SingleImageResult",
    "estimate_single_image",
]

Array = NDArray[np.float64]
METHODS: tuple[str, ...] = ("direct", "tikhonov", "pinv")

_LOG_SSP_BOUNDS = (np.log(1e-3), np.log(1e3))
_LOG_SA_MAX = np.log(50.0)
_CHI2_1_95 = 3.841458820694124
_Z95 = 1.959963984540054


# ---------------------------------------------------------------------------------------------- geometry
@dataclass(frozen=True)
class Patches:
    """Surface patches of the object: all of them are light sources (c_k); the ``visible`` ones are observed.

    ``cos_out`` = n . (camera - x)/|camera - x| (the exit cosine for F_t(eta, w_o)).
    """

    centers_mm: Array  # (K, 3)
    normals: Array  # (K, 3), unit
    areas_mm2: Array  # (K,)
    cos_out: Array  # (K,)
    visible: NDArray[np.bool_]  # (K,)

    def __post_init__(self) -> None:
        k = self.centers_mm.shape[0]
        if not (self.centers_mm.shape == (k, 3) and self.normals.shape == (k, 3) and self.areas_mm2.shape == (k,)
                and self.cos_out.shape == (k,) and self.visible.shape == (k,)):
            raise ValueError("Patches: centers (K,3), normals (K,3), areas (K,), cos_out (K,), visible (K,)")

    @property
    def visible_index(self) -> NDArray[np.intp]:
        return np.flatnonzero(self.visible)

    @property
    def spacing_mm(self) -> float:
        """sqrt(median patch area): the patch spacing used for the near-field radius."""
        return float(np.sqrt(np.median(self.areas_mm2)))

    @classmethod
    def from_arrays(cls, centers_mm: ArrayLike, normals: ArrayLike, areas_mm2: ArrayLike,
                    camera_position_mm: ArrayLike, *, cos_min: float = float(np.cos(np.radians(70.0)))
                    ) -> "Patches":
        """Patches of a convex object from arrays: visible = facing the camera with n.v >= ``cos_min``."""
        c = np.asarray(centers_mm, dtype=np.float64).reshape(-1, 3)
        n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        n = n / np.linalg.norm(n, axis=1, keepdims=True)
        cos_out = _cos_to(c, n, np.asarray(camera_position_mm, dtype=np.float64))
        return cls(c, n, np.asarray(areas_mm2, dtype=np.float64).reshape(-1), cos_out, cos_out >= cos_min)


def _cos_to(centers: Array, normals: Array, camera_position: Array) -> Array:
    v = camera_position[None, :] - centers
    return np.einsum("kc,kc->k", v, normals) / np.linalg.norm(v, axis=1)


def _occluded(origins: Array, target: Array, vertices: Array, faces: NDArray[np.intp], skip_face: NDArray[np.intp],
              chunk: int = 256) -> NDArray[np.bool_]:
    """Segment origin_k -> target blocked by any triangle (Moller-Trumbore, vectorized; own face skipped)."""
    v0 = vertices[faces[:, 0]]
    e1 = vertices[faces[:, 1]] - v0
    e2 = vertices[faces[:, 2]] - v0
    out = np.zeros(len(origins), dtype=bool)
    eps = 1e-9
    for s in range(0, len(origins), chunk):
        o = origins[s:s + chunk]
        d = target[None, :] - o  # (n, 3), t in (0, 1) is on the segment
        p = np.cross(d[:, None, :], e2[None, :, :])  # (n, F, 3)
        det = np.einsum("fc,nfc->nf", e1, p)
        ok = np.abs(det) > eps
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tv = o[:, None, :] - v0[None, :, :]
        u = np.einsum("nfc,nfc->nf", tv, p) * inv
        q = np.cross(tv, e1[None, :, :])
        w = np.einsum("nc,nfc->nf", d, q) * inv
        t = np.einsum("fc,nfc->nf", e2, q) * inv
        hit = ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 1e-6) & (t < 1 - 1e-6)
        hit[np.arange(len(o)), skip_face[s:s + chunk]] = False
        out[s:s + chunk] = hit.any(axis=1)
    return out


def patches_from_mesh(mesh: Any, camera: Any, *, cos_min: float = float(np.cos(np.radians(70.0))),
                      occlusion: Union[bool, str] = "auto", max_edge_mm: float | None = None) -> Patches:
    """Faces of a ``trimesh.Trimesh`` as patches (centroids, face normals, areas) with camera visibility.

    ``camera``: an object with ``center_mm`` (e.g. :class:`estimation.camera.PinholeCamera`, whose ``project``
    also restricts visibility to the image frame) or a camera position (3,) in mm. A patch is visible when it
    faces the camera with n.v >= ``cos_min`` (default cos 70 deg: grazing views are masked because dividing by
    F_t(w_o) explodes there), lies in the frame, and (``occlusion``) nothing blocks the segment to the camera:
    "auto" tests occlusion only for non-convex meshes (back-face culling is exact for convex ones).
    ``max_edge_mm`` subdivides the mesh first (``trimesh.remesh.subdivide_to_size``).
    """
    import trimesh

    if max_edge_mm is not None:
        v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=float(max_edge_mm))
        mesh = trimesh.Trimesh(v, f, process=False)
    centers = np.asarray(mesh.triangles_center, dtype=np.float64)
    normals = np.asarray(mesh.face_normals, dtype=np.float64)
    areas = np.asarray(mesh.area_faces, dtype=np.float64)
    cam_pos = np.asarray(getattr(camera, "center_mm", camera), dtype=np.float64).reshape(3)
    cos_out = _cos_to(centers, normals, cam_pos)
    visible = cos_out >= cos_min
    if hasattr(camera, "project") and hasattr(camera, "width_px"):
        uv, z = camera.project(centers)
        visible &= (z > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= camera.width_px - 0.5) \
            & (uv[:, 1] >= -0.5) & (uv[:, 1] <= camera.height_px - 0.5)
    test = (not bool(mesh.is_convex)) if occlusion == "auto" else bool(occlusion)
    if test and visible.any():
        idx = np.flatnonzero(visible)
        blocked = _occluded(centers[idx], cam_pos, np.asarray(mesh.vertices, dtype=np.float64),
                            np.asarray(mesh.faces), idx)
        visible[idx[blocked]] = False
    return Patches(centers, normals, areas, cos_out, visible)


def sample_image_at_patches(image: ArrayLike, camera: Any, patches: Patches, *,
                            mask: ArrayLike | None = None) -> Array:
    """Radiance of the visible patches (m, C) read from an image by bilinear interpolation at the projected
    patch centres (``camera.project``, e.g. :class:`estimation.camera.PinholeCamera`; pixel centres at integer
    coordinates). NaN where the centre falls outside the frame or any of the four pixels is outside ``mask``
    (H, W) bool (object, unsaturated, non-specular pixels) — NaN rows are ignored by the estimator.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim == 2:
        img = img[:, :, None]
    h, w, _ = img.shape
    ok_px = np.ones((h, w), dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    uv, z = camera.project(patches.centers_mm[patches.visible_index])
    u, v = uv[:, 0], uv[:, 1]
    inside = (z > 0) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    u0 = np.clip(np.floor(np.where(inside, u, 0)).astype(np.intp), 0, max(w - 2, 0))
    v0 = np.clip(np.floor(np.where(inside, v, 0)).astype(np.intp), 0, max(h - 2, 0))
    fu = np.clip(np.where(inside, u, 0) - u0, 0, 1)[:, None]
    fv = np.clip(np.where(inside, v, 0) - v0, 0, 1)[:, None]
    u1 = np.minimum(u0 + 1, w - 1)
    v1 = np.minimum(v0 + 1, h - 1)
    val = ((1 - fu) * (1 - fv) * img[v0, u0] + fu * (1 - fv) * img[v0, u1]
           + (1 - fu) * fv * img[v1, u0] + fu * fv * img[v1, u1])
    good = inside & ok_px[v0, u0] & ok_px[v0, u1] & ok_px[v1, u0] & ok_px[v1, u1]
    val[~good] = np.nan
    return val


# ---------------------------------------------------------------------------------------------- illumination
@dataclass(frozen=True)
class PointLights:
    """Isotropic point lights: positions (L, 3) mm, radiant intensity (L, C) (W/sr-like units)."""

    positions_mm: ArrayLike
    intensity: ArrayLike


@dataclass(frozen=True)
class DirectionalLights:
    """Distant lights: unit directions towards the light (L, 3) and radiance x solid angle weights (L, C)."""

    directions: ArrayLike
    radiance_weights: ArrayLike


@dataclass(frozen=True)
class EnvironmentMap:
    """Distant lat-long environment map, radiance (H, W, C), in the rig frame (+z up).

    Mapping: pixel (row i, column j) is the direction with polar angle theta = pi (i + 0.5)/H from +z (row 0 is
    straight up) and azimuth phi = 2 pi (j + 0.5)/W from +x towards +y:
    w = (sin theta cos phi, sin theta sin phi, cos theta), pointing from the object towards the environment.
    Solid angle of a pixel: sin theta (pi/H)(2 pi/W). Maps larger than ``max_size`` rows are box-downsampled
    (rows and columns by the same integer factor) before use. No shadowing (convex objects).
    """

    radiance: ArrayLike
    max_size: int = 64

    def directions_and_weights(self) -> tuple[Array, Array]:
        img = np.asarray(self.radiance, dtype=np.float64)
        if img.ndim == 2:
            img = img[:, :, None]
        h, w, c = img.shape
        f = max(1, int(np.ceil(h / self.max_size)))
        if f > 1:
            h2, w2 = h // f, w // f
            img = img[:h2 * f, :w2 * f].reshape(h2, f, w2, f, c).mean(axis=(1, 3))
            h, w = h2, w2
        theta = np.pi * (np.arange(h) + 0.5) / h
        phi = 2 * np.pi * (np.arange(w) + 0.5) / w
        th, ph = np.meshgrid(theta, phi, indexing="ij")
        dirs = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=-1).reshape(-1, 3)
        d_omega = (np.sin(th) * (np.pi / h) * (2 * np.pi / w)).reshape(-1, 1)
        return dirs, img.reshape(-1, c) * d_omega


Lights = Union[PointLights, DirectionalLights, EnvironmentMap, ArrayLike]


def patch_irradiance(patches: Patches, lights: Lights, eta: float) -> Array:
    """Fresnel-transmitted irradiance E_t per patch (K, C) (the seed's c_k / A_k, Eq. 12).

    ``lights``: :class:`PointLights`, :class:`DirectionalLights`, :class:`EnvironmentMap`, or an array (K, C)
    or (K,) that already is E_t per patch.
    """
    if isinstance(lights, PointLights):
        return irradiance_point_lights(patches.centers_mm, patches.normals, lights.positions_mm, lights.intensity,
                                       eta)
    if isinstance(lights, DirectionalLights):
        return irradiance_directional(patches.normals, lights.directions, lights.radiance_weights, eta)
    if isinstance(lights, EnvironmentMap):
        d, w = lights.directions_and_weights()
        return irradiance_directional(patches.normals, d, w, eta)
    e = np.asarray(lights, dtype=np.float64)
    if e.ndim == 1:
        e = e[:, None]
    if e.shape[0] != patches.centers_mm.shape[0]:
        raise ValueError(f"irradiance array has {e.shape[0]} rows, expected one per patch ({len(patches.areas_mm2)})")
    return e


# ---------------------------------------------------------------------------------------------- quantization
def quantization_weights(distances_mm: ArrayLike, nodes_mm: ArrayLike) -> tuple[NDArray[np.intp], Array]:
    """Mukaigawa Eq. 19-21: index i with d'_i <= d < d'_{i+1} and beta = (d'_{i+1} - d)/(d'_{i+1} - d'_i).

    R(d) ~ beta R'_i + (1 - beta) R'_{i+1}. Distances outside [d'_0, d'_{n-1}] are clamped to the end intervals
    (beta clipped to [0, 1]).
    """
    d = np.asarray(distances_mm, dtype=np.float64)
    nodes = np.asarray(nodes_mm, dtype=np.float64)
    i = np.clip(np.searchsorted(nodes, d, side="right") - 1, 0, nodes.size - 2)
    beta = np.clip((nodes[i + 1] - d) / (nodes[i + 1] - nodes[i]), 0.0, 1.0)
    return i, beta


def _hat_parts(nodes: Array) -> tuple[Array, Array]:
    """Complete integrals of the hat functions times 2 pi r: rising half L_i (into node i) and full F_i."""
    x0, x1 = nodes[:-1], nodes[1:]
    h = x1 - x0
    i_r = np.pi * (x1**2 - x0**2)  # int 2 pi r dr over the interval
    i_r2 = 2 * np.pi * (x1**3 - x0**3) / 3  # int 2 pi r^2 dr
    fall = (x1 * i_r - i_r2) / h  # int (x1 - r)/h 2 pi r dr -> node i
    rise = (i_r2 - x0 * i_r) / h  # int (r - x0)/h 2 pi r dr -> node i+1
    L = np.concatenate([[0.0], rise])
    F = L + np.concatenate([fall, [0.0]])
    return L, F


def _ring_hat_matrix(rows: NDArray[np.intp], r_in: Array, r_out: Array, weight: Array, nodes: Array, m: int
                     ) -> Array:
    """W (m, n) with W @ R(nodes) = sum_pairs weight * int_{r_in}^{r_out} R_interp(r) 2 pi r dr.

    R_interp is the piecewise-linear interpolant of R on ``nodes`` (nodes[0] = 0). The cumulative integral
    G(rho) of each hat is complete (F_i) below the interval t holding rho, plus partial terms at t and t+1;
    the spans of complete hats between t_in and t_out are added with a difference array.
    """
    n = nodes.size
    L, F = _hat_parts(nodes)
    out = np.zeros(m * n)
    diff = np.zeros(m * (n + 1))

    def partial(rho: Array) -> tuple[NDArray[np.intp], Array, Array, Array]:
        t = np.clip(np.searchsorted(nodes, rho, side="right") - 1, 0, n - 2)
        x0, x1 = nodes[t], nodes[t + 1]
        h = x1 - x0
        a2 = rho**2 - x0**2
        a3 = (rho**3 - x0**3) / 3
        fall = 2 * np.pi * (x1 * a2 / 2 - a3) / h
        rise = 2 * np.pi * (a3 - x0 * a2 / 2) / h
        return t, fall, rise, L[t]

    t_in, f_in, q_in, l_in = partial(r_in)
    t_out, f_out, q_out, l_out = partial(r_out)
    base = rows * n
    np.add.at(diff, rows * (n + 1) + t_in, weight)
    np.add.at(diff, rows * (n + 1) + t_out, -weight)
    mult = np.cumsum(diff.reshape(m, n + 1), axis=1)[:, :n]
    out += (mult * F[None, :]).ravel()
    out += np.bincount(base + t_out, weights=weight * (l_out + f_out), minlength=m * n)
    out += np.bincount(base + t_out + 1, weights=weight * q_out, minlength=m * n)
    out -= np.bincount(base + t_in, weights=weight * (l_in + f_in), minlength=m * n)
    out -= np.bincount(base + t_in + 1, weights=weight * q_in, minlength=m * n)
    return out.reshape(m, n)


# ---------------------------------------------------------------------------------------------- results
@dataclass(frozen=True)
class SingleImageDiagnostics:
    """How the solve went. ``condition_number``: of W (binned methods) or of the scaled Jacobian (direct)."""

    condition_number: float
    n_bins: int
    empty_bins: int
    residual_rms: Array  # per channel, in the weighted residual units
    relative_residual_rms: Array  # per channel, rms of (model - l)/l over observed patches
    seconds: float
    n_observations: int
    n_patches: int
    nfev: int
    regularization: Array | None = None  # tikhonov lambda per channel
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class SingleImageResult:
    """Estimated parameters per colour channel, shape (C,), with 95 % intervals (C, 2); falsy on failure.

    ``sigma_a_ci_per_mm`` is the profile-likelihood interval (lower bound 0 when one-sided);
    ``sigma_a_ci_jacobian_per_mm`` the Wald interval in log sigma_a. ``profile_*`` hold the binned R'
    (pinv/tikhonov) or the fitted model at the bins (direct) as a diagnostic.
    """

    success: bool
    message: str
    method: str
    model: str
    eta: float
    sigma_s_prime_per_mm: Array | None = None
    sigma_a_per_mm: Array | None = None
    R_d: Array | None = None
    l_d_mm: Array | None = None
    D_mm: Array | None = None
    sigma_s_prime_ci_per_mm: Array | None = None
    sigma_a_ci_per_mm: Array | None = None
    sigma_a_ci_jacobian_per_mm: Array | None = None
    R_d_ci: Array | None = None
    l_d_ci_mm: Array | None = None
    correlation_log: Array | None = None  # corr(log sigma_s', log sigma_a) per channel
    sigma_a_identifiable: bool = False
    sigma_a_identifiable_per_channel: tuple[bool, ...] = ()
    identifiability_reason: str = ""
    profile_bins_mm: Array | None = None
    profile_values: Array | None = None  # (n_bins, C)
    diagnostics: SingleImageDiagnostics | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def __bool__(self) -> bool:
        return self.success


def _failure(message: str, method: str, model: str, eta: float, t0: float, **extra: Any) -> SingleImageResult:
    diag = SingleImageDiagnostics(np.nan, 0, 0, np.array([]), np.array([]), time.perf_counter() - t0, 0, 0, 0)
    return SingleImageResult(False, message, method, model, float(eta), diagnostics=diag, extra=dict(extra))


# ---------------------------------------------------------------------------------------------- pair geometry
class _Geometry:
    """Near-field sums and far-pair enumeration between observed points j and source patches k."""

    def __init__(self, obs_points: Array, centers: Array, areas: Array, c_k: Array, rho: float,
                 cutoff_mm: float | None, chunk: int = 256) -> None:
        self.obs = obs_points
        self.centers = centers
        self.areas = areas
        self.c_k = c_k  # (K, C) = E_t A
        self.rho = rho
        lo = np.minimum(obs_points.min(0), centers.min(0))
        hi = np.maximum(obs_points.max(0), centers.max(0))
        diag = float(np.linalg.norm(hi - lo))
        self.cutoff = diag * 1.0001 + 1e-9 if cutoff_mm is None or cutoff_mm >= diag else float(cutoff_mm)
        self.dense = cutoff_mm is None or cutoff_mm >= diag
        self.tree = None if self.dense else cKDTree(centers)
        self.chunk = max(1, min(chunk, 4_000_000 // max(len(centers), 1)))
        m = len(obs_points)
        self.d_max = 0.0
        js, ks, ds = [], [], []
        for _sl, j, k, d in self.pairs(near=True):
            js.append(j)
            ks.append(k)
            ds.append(d)
        j_all = np.concatenate(js) if js else np.zeros(0, dtype=np.intp)
        k_all = np.concatenate(ks) if ks else np.zeros(0, dtype=np.intp)
        d_all = np.concatenate(ds) if ds else np.zeros(0)
        order, self.ring_in, self.ring_out = ring_radii(j_all, d_all, areas[k_all])
        self.near_j = j_all[order]
        self.near_k = k_all[order]
        self.near_d = d_all[order]
        self.m = m

    def near_matrices(self, nodes: Array) -> list[Array]:
        """W_near,c (m, n): equal-area rings of the near patches (forward.ring_radii), exact hat integrals."""
        e_k = self.c_k[self.near_k] / self.areas[self.near_k][:, None]
        return [_ring_hat_matrix(self.near_j, self.ring_in, self.ring_out, e_k[:, c], nodes, self.m)
                for c in range(self.c_k.shape[1])]

    def pairs(self, *, near: bool) -> Iterator[tuple[slice, NDArray[np.intp], NDArray[np.intp], Array]]:
        """Yield (row slice, j (global), k, d) for pairs with d <= rho (near) or rho < d <= cutoff (far)."""
        m = len(self.obs)
        for s in range(0, m, self.chunk):
            sl = slice(s, min(s + self.chunk, m))
            if near:
                tree = self.tree if self.tree is not None else cKDTree(self.centers)
                self.tree = tree
                pr = cKDTree(self.obs[sl]).sparse_distance_matrix(tree, self.rho, output_type="ndarray")
                j, k, d = pr["i"].astype(np.intp) + s, pr["j"].astype(np.intp), pr["v"]
                keep = d <= self.rho
                yield sl, j[keep], k[keep], d[keep]
                continue
            if self.dense:
                dd = cdist(self.obs[sl], self.centers)
                far = dd > self.rho
                jj, kk = np.nonzero(far)
                d = dd[jj, kk]
                j = jj + s
            else:
                assert self.tree is not None
                pr = cKDTree(self.obs[sl]).sparse_distance_matrix(self.tree, self.cutoff, output_type="ndarray")
                j, kk, d = pr["i"].astype(np.intp) + s, pr["j"].astype(np.intp), pr["v"]
                far = d > self.rho
                j, kk, d = j[far], kk[far], d[far]
            if d.size:
                self.d_max = max(self.d_max, float(d.max()))
            yield sl, j, kk, d

    def far_matrices(self, nodes: Array) -> list[Any]:
        """W_c (m, n) = sum_k c_k,c hat_i(d_jk) over far pairs, one per channel (dense or CSR)."""
        m, n, n_ch = len(self.obs), nodes.size, self.c_k.shape[1]
        acc = [np.zeros((m, n)) for _ in range(n_ch)]
        for sl, j, k, d in self.pairs(near=False):
            rows = sl.stop - sl.start
            i, beta = quantization_weights(d, nodes)
            idx0 = (j - sl.start) * n + i
            for c in range(n_ch):
                w = self.c_k[k, c]
                block = np.bincount(idx0, weights=beta * w, minlength=rows * n)
                block += np.bincount(idx0 + 1, weights=(1 - beta) * w, minlength=rows * n)
                acc[c][sl] += block.reshape(rows, n)
        mats: list[Any] = []
        for c in range(n_ch):
            w_c = acc[c]
            density = np.count_nonzero(w_c) / max(w_c.size, 1)
            mats.append(sparse.csr_matrix(w_c) if density < 0.25 else w_c)
        return mats


def _fine_nodes(rho: float, d_max: float, ratio: float = 1.01) -> Array:
    lo = max(rho, 1e-6)
    hi = max(d_max, lo * ratio) * 1.0001
    n = int(np.ceil(np.log(hi / lo) / np.log(ratio))) + 1
    return lo * ratio ** np.arange(n + 1)


# ---------------------------------------------------------------------------------------------- fitting core
class _Problem:
    """Batch model for one channel: model(theta (T, 2) log params) -> (N, T); data (N,), weights (N,)."""

    def __init__(self, model_fn: Any, data: Array, weights: Array) -> None:
        self.model_fn = model_fn
        self.data = data
        self.weights = weights
        self.nfev = 0

    def resid(self, theta: Array) -> Array:
        t = np.atleast_2d(theta)
        self.nfev += t.shape[0]
        return (self.model_fn(t) - self.data[:, None]) * self.weights[:, None]

    def ssr(self, theta: Array) -> Array:
        r = self.resid(theta)
        return np.einsum("nt,nt->t", r, r)


def _profile_batch(coeff_model: str, eta: float, fdr: str, theta: Array, radii: Array) -> Array:
    """R(radii; theta) for a batch of log parameters: (T, 2) x (n,) -> (n, T)."""
    ssp = np.exp(theta[:, 0])[:, None]
    sa = np.exp(theta[:, 1])[:, None]
    co = dipole_coefficients(ssp, sa, eta, model=coeff_model, fdr=fdr)
    return profile_from_coefficients(co, radii[None, :]).T


def _golden_batch(f: Any, lo: Array, hi: Array, iters: int = 32) -> tuple[Array, Array]:
    """Vectorized golden-section minimization of f(x (T,)) -> (T,) on [lo, hi] per element."""
    g = (np.sqrt(5) - 1) / 2
    a, b = lo.copy(), hi.copy()
    c = b - g * (b - a)
    d = a + g * (b - a)
    fc, fd = f(c), f(d)
    for _ in range(iters):
        left = fc < fd  # the minimum lies in [a, d]
        a_new = np.where(left, a, c)
        b_new = np.where(left, d, b)
        c_new = np.where(left, b_new - g * (b_new - a_new), d)
        d_new = np.where(left, c, a_new + g * (b_new - a_new))
        f_eval = f(np.where(left, c_new, d_new))
        fc, fd = np.where(left, f_eval, fd), np.where(left, fc, f_eval)
        a, b, c, d = a_new, b_new, c_new, d_new
    x = 0.5 * (a + b)
    return x, f(x)


@dataclass
class _ChannelFit:
    theta: Array
    cov: Array
    ssr: float
    s2: float
    nfev: int
    jac_cond: float
    sa_profile_ci: tuple[float, float]
    one_sided: bool
    ok: bool
    message: str


def _fit_channel(problem: _Problem, sa_floor: float, n_params_dof: int = 2, known_noise: bool = False,
                 profile: bool = True, model_error: float = 0.0) -> _ChannelFit:
    """Grid start + bounded least squares in (log sigma_s', log sigma_a); Wald covariance and sigma_a profile.

    The residual scale is s^2 = SSR/dof (or 1 for known noise), floored so that the 95 % thresholds are never
    tighter than a relative model error ``model_error`` on every datum: Delta SSR >= sum (model_error * data *
    weight)^2, i.e. parameters whose best-fit predictions differ by less than that rms are not distinguished.
    """
    lb = np.array([_LOG_SSP_BOUNDS[0], np.log(sa_floor)])
    ub = np.array([_LOG_SSP_BOUNDS[1], _LOG_SA_MAX])
    # coarse grid (one batched evaluation), then trust-region least squares with bounds
    g_s = np.linspace(np.log(0.01), np.log(100.0), 21)
    g_a = np.linspace(max(np.log(1e-6), lb[1]), np.log(10.0), 21)
    grid = np.array(np.meshgrid(g_s, g_a, indexing="ij")).reshape(2, -1).T
    ssr_grid = problem.ssr(grid)
    if not np.any(np.isfinite(ssr_grid)):
        return _ChannelFit(np.full(2, np.nan), np.full((2, 2), np.nan), np.nan, np.nan, problem.nfev, np.nan,
                           (np.nan, np.nan), False, False, "model evaluation is not finite on the start grid")
    x0 = grid[int(np.nanargmin(ssr_grid))]
    best = None
    for start in (x0, np.clip(x0 + np.array([0.0, 2.0]), lb, ub), np.clip(x0 - np.array([0.0, 2.0]), lb, ub)):
        res = optimize.least_squares(lambda t: problem.resid(t[None, :])[:, 0], start, bounds=(lb, ub),
                                     method="trf", x_scale=1.0, xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=400)
        if best is None or res.cost < best.cost:
            best = res
    assert best is not None
    theta = best.x
    ssr_min = 2.0 * best.cost
    dof = max(problem.data.size - n_params_dof, 1)
    s2 = 1.0 if known_noise else max(ssr_min / dof, 1e-300)
    if model_error > 0:
        s2 = max(s2, float(np.sum((model_error * problem.data * problem.weights) ** 2)) / _CHI2_1_95)
    J = best.jac
    try:
        sv = np.linalg.svd(J, compute_uv=False)
        jac_cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else np.inf
        cov = s2 * np.linalg.pinv(J.T @ J)
    except np.linalg.LinAlgError:
        jac_cond, cov = np.inf, np.full((2, 2), np.inf)
    ci = (np.nan, np.nan)
    one_sided = False
    if profile:
        ci, one_sided = _profile_sigma_a(problem, theta, ssr_min, s2, lb, ub)
    msg = "ok" if best.success else f"least_squares: {best.message}"
    return _ChannelFit(theta, cov, ssr_min, s2, problem.nfev, jac_cond, ci, one_sided, bool(best.status > 0), msg)


def _profile_sigma_a(problem: _Problem, theta: Array, ssr_min: float, s2: float, lb: Array, ub: Array
                     ) -> tuple[tuple[float, float], bool]:
    """95 % profile-likelihood interval for sigma_a: {sigma_a : min_ssp SSR <= SSR_min + 3.84 s^2}."""
    grid = np.unique(np.concatenate([np.linspace(lb[1], ub[1], 41), [theta[1]]]))
    lo_s = np.full(grid.size, max(lb[0], theta[0] - 5.0))
    hi_s = np.full(grid.size, min(_LOG_SSP_BOUNDS[1], theta[0] + 5.0))

    def f(x: Array) -> Array:
        return problem.ssr(np.stack([x, grid], axis=1))

    _, prof = _golden_batch(f, lo_s, hi_s)
    prof = np.minimum(prof, np.where(grid == theta[1], ssr_min, np.inf))
    thresh = ssr_min + _CHI2_1_95 * s2
    inside = prof <= thresh
    i0 = int(np.argmin(np.abs(grid - theta[1])))
    inside[i0] = True
    # connected run around the optimum
    lo_i = i0
    while lo_i > 0 and inside[lo_i - 1]:
        lo_i -= 1
    hi_i = i0
    while hi_i < grid.size - 1 and inside[hi_i + 1]:
        hi_i += 1

    def cross(i_in: int, i_out: int) -> float:
        a, b = prof[i_in], prof[i_out]
        if not np.isfinite(b) or b == a:
            return float(grid[i_in])
        t = (thresh - a) / (b - a)
        return float(grid[i_in] + np.clip(t, 0, 1) * (grid[i_out] - grid[i_in]))

    one_sided = lo_i == 0
    lower = 0.0 if one_sided else float(np.exp(cross(lo_i, lo_i - 1)))
    upper = float(np.exp(grid[-1])) if hi_i == grid.size - 1 else float(np.exp(cross(hi_i, hi_i + 1)))
    return (lower, upper), one_sided


# ---------------------------------------------------------------------------------------------- public entry
def estimate_single_image(observed_radiance: ArrayLike, patches: Patches, lights: Lights, eta: float, *,
                          method: str = "direct", model: str = "dipole-jensen", bin_mm: float = 0.35,
                          cutoff_mm: float | None = None, tolerance: float = 1e-4, noise_sigma: ArrayLike | None = None,
                          noise_floor: float = 1e-3, sigma_a_floor_per_mm: float = 1e-7, monotone: bool = False,
                          regularization: float | None = None, profile_likelihood: bool = True,
                          identifiable_ratio: float = 10.0, model_error: float = 0.02,
                          fdr: str = "fit") -> SingleImageResult:
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
    model : "dipole-jensen" or "dipole-better".
    bin_mm : quantization step of the binned methods (paper: 0.35 mm) and of the diagnostic profile.
    cutoff_mm : ignore pairs farther apart (KD-tree); None uses all pairs (small objects). A note is added
        when the fitted profile still holds more than ``tolerance`` of R_d beyond it.
    noise_sigma : per-observation standard deviation of L_o (same shape as ``observed_radiance``); the residuals
        are then chi-square scaled. Default: relative weights 1/(l_j + noise_floor * max l) and the noise
        variance estimated from the residuals.
    sigma_a_floor_per_mm : lower bound of sigma_a in the fits and the profile scan.
    monotone, regularization : Tikhonov options (non-increasing R'; fixed lambda instead of GCV).
    identifiable_ratio : sigma_a counts as identifiable when its profile interval is two-sided and
        upper/lower <= this ratio.
    model_error : relative rms of unmodelled error (calibration, geometry, diffusion model; default 2 %). The
        intervals are never tighter than the set of parameters whose best-fit image differs from the optimum
        by less than this rms — without it, noiseless or many-pixel data give intervals that reflect only the
        pixel count, not the (spatially correlated) systematic error. 0 gives purely statistical intervals.

    Returns a :class:`SingleImageResult` (falsy with ``message`` on failure). Example: the lead's demo path is
    ``patches_from_mesh(mesh, camera)`` -> ``estimate_single_image(2 * cross_radiance, patches,
    PointLights(led_position[None], led_intensity[None]), eta)``.
    """
    t0 = time.perf_counter()
    eta_f = float(eta)
    check_model(model)
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; valid methods: {', '.join(METHODS)}")
    if bin_mm <= 0:
        raise ValueError("bin_mm must be > 0")
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
    ft = fresnel_transmittance(eta_f, patches.cos_out[vis])
    valid = np.isfinite(obs) & (ft[:, None] > 1e-6)
    if sig is not None:
        valid &= np.isfinite(sig) & (sig > 0)
    l_obs = np.where(valid, np.pi * np.nan_to_num(obs) / np.where(ft > 1e-6, ft, 1.0)[:, None], 0.0)
    if not np.any(valid.sum(0) >= 3):
        return _failure("fewer than 3 valid observations in every channel", method, model, eta_f, t0)
    if np.all(l_obs[valid] <= 0):
        return _failure("all observed radiances are <= 0", method, model, eta_f, t0)

    c_k = e_t * patches.areas_mm2[:, None]
    rho = NEAR_FIELD_SPACINGS * patches.spacing_mm
    geo = _Geometry(patches.centers_mm[vis], patches.centers_mm, patches.areas_mm2, c_k, rho, cutoff_mm)
    notes: list[str] = []

    # ------------------------------------------------------------------ per-method system
    d_far = _far_extent(geo)
    if method == "direct":
        # near rings and far pairs on one fine grid: 0, then 1 % log spacing from 1e-3 mm (or below rho/100)
        nodes = np.concatenate([[0.0], _fine_nodes(min(1e-3, rho / 100.0), max(d_far, float(geo.ring_out.max(
            initial=rho))))])
        mats = [w_n + _dense(w_f) for w_n, w_f in zip(geo.near_matrices(nodes), geo.far_matrices(nodes))]
        bins = np.arange(0.0, max(d_far, rho) + bin_mm, bin_mm)
        cond = np.nan
        empty = 0
    else:
        bins = np.arange(0.0, max(d_far, rho, float(geo.ring_out.max(initial=0.0))) + 1.5 * bin_mm, bin_mm)
        if bins.size < 3:
            bins = np.array([0.0, bin_mm, 2 * bin_mm])
        mats = geo.far_matrices(bins)
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
        w_full = [np.asarray(_dense(mats[c])) + near_w[c] for c in range(n_ch)]
        col_nonzero = np.any(np.stack([np.abs(w) for w in w_full]).sum(0) > 0, axis=0)
        empty = int((~col_nonzero).sum())
        cond = float(np.max([_cond(w[:, col_nonzero]) for w in w_full])) if col_nonzero.any() else np.inf

    # ------------------------------------------------------------------ per-channel fits
    theta_hat = np.full((n_ch, 2), np.nan)
    fits: list[_ChannelFit] = []
    rel_rms = np.full(n_ch, np.nan)
    res_rms = np.full(n_ch, np.nan)
    prof_vals = np.full((bins.size, n_ch), np.nan)
    lambdas = np.full(n_ch, np.nan)
    jac_conds = np.full(n_ch, np.nan)
    nfev = 0
    for c in range(n_ch):
        ok = valid[:, c]
        if ok.sum() < 3:
            return _failure(f"channel {c}: fewer than 3 valid observations", method, model, eta_f, t0)
        if not np.any(e_t[:, c] > 0):
            return _failure(f"channel {c}: the illumination gives no irradiance in this channel", method, model,
                            eta_f, t0)
        l_c = l_obs[ok, c]
        if sig is not None:
            w_obs = (ft[ok] / (np.pi * sig[ok, c]))  # sigma of l = pi sigma_L / F_t
        else:
            w_obs = 1.0 / (np.abs(l_c) + noise_floor * np.max(np.abs(l_c)))
        if method == "direct":
            w_tot = mats[c][ok]

            def model_fn(theta: Array, w_tot: Array = w_tot) -> Array:
                return w_tot @ _profile_batch(model, eta_f, fdr, theta, nodes)

            problem = _Problem(model_fn, l_c, w_obs)
            fit = _fit_channel(problem, sigma_a_floor_per_mm, known_noise=sig is not None, profile=profile_likelihood,
                               model_error=model_error)
            jac_conds[c] = fit.jac_cond
            if np.all(np.isfinite(fit.theta)):
                prof_vals[:, c] = _profile_batch(model, eta_f, fdr, fit.theta[None, :], bins)[:, 0]
                pred = model_fn(fit.theta[None, :])[:, 0]
                rel_rms[c] = float(np.sqrt(np.mean(((pred - l_c) / np.where(l_c != 0, l_c, 1)) ** 2)))
                res_rms[c] = float(np.sqrt(fit.ssr / l_c.size))
        else:
            w_c = w_full[c][ok]
            if method == "pinv":
                r_bins = np.linalg.pinv(w_c) @ l_c
                fit_cols = col_nonzero
                fit_w = np.ones(int(fit_cols.sum()))
            else:
                r_bins, lam = _tikhonov(w_c * w_obs[:, None], l_c * w_obs, regularization, monotone)
                lambdas[c] = lam
                fit_cols = np.ones(bins.size, dtype=bool)
                fit_w = np.ones(bins.size)
            prof_vals[:, c] = r_bins
            pred_img = w_c @ r_bins
            rel_rms[c] = float(np.sqrt(np.mean(((pred_img - l_c) / np.where(l_c != 0, l_c, 1)) ** 2)))
            if method == "pinv":  # Eq. 29: unweighted least squares on the (non-empty) bins
                radii = bins[fit_cols]

                def model_fn_b(theta: Array, radii: Array = radii) -> Array:
                    return _profile_batch(model, eta_f, fdr, theta, radii)

                problem = _Problem(model_fn_b, r_bins[fit_cols], fit_w)
            else:
                # R' near d = 0 is only seen through disk integrals (smooth irradiance), so compare profiles in
                # the metric of the data: || w (W R(theta) - W r') || (the information W^T W on r')
                def model_fn_b(theta: Array, w_c: Array = w_c) -> Array:
                    return w_c @ _profile_batch(model, eta_f, fdr, theta, bins)

                problem = _Problem(model_fn_b, pred_img, w_obs)
            fit = _fit_channel(problem, sigma_a_floor_per_mm, profile=profile_likelihood, model_error=model_error)
            res_rms[c] = float(np.sqrt(fit.ssr / max(problem.data.size, 1))) if np.isfinite(fit.ssr) else np.nan
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
    rd, ld, D = reflectance_from_coefficients(ssp, sa, eta_f, model=model, fdr=fdr)
    sd = np.array([np.sqrt(np.clip(np.diag(f.cov), 0, None)) for f in fits])  # (C, 2)
    corr = np.array([f.cov[0, 1] / np.sqrt(f.cov[0, 0] * f.cov[1, 1]) if f.cov[0, 0] * f.cov[1, 1] > 0 else np.nan
                     for f in fits])
    sd = np.minimum(sd, 300.0)  # (exp overflow guard: an SD of 300 in a log parameter is "unbounded")
    ssp_ci = np.stack([ssp * np.exp(-_Z95 * sd[:, 0]), ssp * np.exp(_Z95 * sd[:, 0])], axis=1)
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
        lo, hi = sa_ci[c]
        if one_sided[c] or lo <= 0:
            ident.append(False)
            reasons.append(f"channel {c}: the 95% interval of sigma_a reaches the floor ({lo:.3g}-{hi:.3g} /mm, "
                           f"one-sided); the observed distances (<= {geo.d_max:.3g} mm) are short against "
                           f"l_d = {ld[c]:.3g} mm")
        elif hi / lo > identifiable_ratio:
            ident.append(False)
            reasons.append(f"channel {c}: the 95% interval of sigma_a spans a factor {hi / lo:.3g} "
                           f"(> {identifiable_ratio:g}): {lo:.3g}-{hi:.3g} /mm")
        else:
            ident.append(True)
            reasons.append(f"channel {c}: sigma_a within {lo:.3g}-{hi:.3g} /mm (factor {hi / lo:.3g})")
    if cutoff_mm is not None:
        need = cutoff_radius_mm(tolerance, ssp, sa, eta_f, model=model, fdr=fdr)
        if need > geo.cutoff:
            notes.append(f"cutoff {geo.cutoff:.3g} mm is shorter than the fitted profile needs for tolerance "
                         f"{tolerance:g} ({need:.3g} mm)")
    if method == "pinv" and empty:
        notes.append(f"{empty} empty distance bins are zero columns of W (pinv returns 0 for them); "
                     "they were left out of the dipole fit")
    cond_out = cond if method != "direct" else float(np.nanmax(jac_conds))
    diag = SingleImageDiagnostics(cond_out, int(bins.size), int(empty), res_rms, rel_rms,
                                  time.perf_counter() - t0, int(valid.sum()), int(k_all), int(nfev),
                                  lambdas if method == "tikhonov" else None, tuple(notes))
    return SingleImageResult(
        True, "ok" if not notes else "; ".join(notes), method, model, eta_f,
        sigma_s_prime_per_mm=ssp, sigma_a_per_mm=sa, R_d=np.asarray(rd), l_d_mm=np.asarray(ld), D_mm=np.asarray(D),
        sigma_s_prime_ci_per_mm=ssp_ci, sigma_a_ci_per_mm=sa_ci, sigma_a_ci_jacobian_per_mm=sa_ci_jac,
        R_d_ci=rd_ci, l_d_ci_mm=ld_ci, correlation_log=corr,
        sigma_a_identifiable=bool(all(ident)), sigma_a_identifiable_per_channel=tuple(ident),
        identifiability_reason="; ".join(reasons), profile_bins_mm=bins, profile_values=prof_vals,
        diagnostics=diag)


def _far_extent(geo: _Geometry) -> float:
    """Largest observed-to-source distance (<= the cutoff), by a chunked exact pass."""
    d_max = 0.0
    step = max(1, 2_000_000 // max(len(geo.centers), 1))
    for s in range(0, len(geo.obs), step):
        d_max = max(d_max, float(cdist(geo.obs[s:s + step], geo.centers).max()))
    return float(min(d_max, geo.cutoff))


def _dense(w: Any) -> Array:
    return w.toarray() if sparse.issparse(w) else np.asarray(w)


def _cond(w: Array) -> float:
    if w.size == 0:
        return np.inf
    sv = np.linalg.svd(w, compute_uv=False)
    return float(sv[0] / sv[-1]) if sv[-1] > 0 else np.inf


def _tikhonov(w: Array, l: Array, lam: float | None, monotone: bool) -> tuple[Array, float]:
    """min ||W r - l||^2 + lam ||L2 r||^2, r >= 0 (monotone: r non-increasing); lam by GCV when None."""
    n = w.shape[1]
    L = np.diff(np.eye(n), 2, axis=0)
    # scale columns so lambda is dimensionless
    colscale = np.linalg.norm(w, axis=0)
    colscale = np.where(colscale > 0, colscale, 1.0)
    ws = w / colscale
    Ls = L / colscale  # penalty on r = r_s / colscale
    gtg = ws.T @ ws
    ltl = Ls.T @ Ls
    scale_l = np.trace(gtg) / max(np.trace(ltl), 1e-300)
    if lam is None:
        best = (np.inf, 1e-6)
        m = w.shape[0]
        for lg in np.linspace(-10, 2, 25):
            lam_t = 10.0**lg * scale_l
            a = gtg + lam_t * ltl
            try:
                rs = np.linalg.solve(a, ws.T @ l)
                infl = np.trace(np.linalg.solve(a, gtg))
            except np.linalg.LinAlgError:
                continue
            res = ws @ rs - l
            gcv = m * float(res @ res) / max(m - infl, 1e-9) ** 2
            if gcv < best[0]:
                best = (gcv, lam_t)
        lam_used = best[1]
    else:
        lam_used = float(lam) * scale_l
    a_aug = np.vstack([ws, np.sqrt(lam_used) * Ls])
    b_aug = np.concatenate([l, np.zeros(Ls.shape[0])])
    if monotone:
        # r = T u with u >= 0, r_i = sum_{t >= i} u_t: non-negative and non-increasing. The objective is the
        # same as in the scaled variables: ||W r - l||^2 + lam ||L r||^2 (ws r_s = W r, Ls r_s = L r).
        T = np.triu(np.ones((n, n)))
        a_aug = np.vstack([w @ T, np.sqrt(lam_used) * (L @ T)])
        u, _ = optimize.nnls(a_aug, b_aug, maxiter=50 * n)
        return T @ u, lam_used
    rs, _ = optimize.nnls(a_aug, b_aug, maxiter=50 * n)
    return rs / colscale, lam_used


def _derived_intervals(theta: Array, covs: list[Array], eta: float, model: str, fdr: str) -> tuple[Array, Array]:
    """Delta-method 95 % intervals of R_d and l_d (log scale) from the covariance of the log parameters."""
    rd_ci = np.full((theta.shape[0], 2), np.nan)
    ld_ci = np.full((theta.shape[0], 2), np.nan)
    h = 1e-5
    for c, (t, cov) in enumerate(zip(theta, covs)):
        def f(tt: Array) -> Array:
            rd, ld, _ = reflectance_from_coefficients(np.exp(tt[0]), np.exp(tt[1]), eta, model=model, fdr=fdr)
            return np.log(np.array([rd, ld], dtype=np.float64))

        f0 = f(t)
        g = np.stack([(f(t + h * e) - f(t - h * e)) / (2 * h) for e in np.eye(2)], axis=1)  # (2 out, 2 in)
        var = np.einsum("oi,ij,oj->o", g, cov, g)
        sd = np.minimum(np.sqrt(np.clip(var, 0, None)), 300.0)
        rd_ci[c] = np.exp(f0[0] + np.array([-1, 1]) * _Z95 * sd[0])
        ld_ci[c] = np.exp(f0[1] + np.array([-1, 1]) * _Z95 * sd[1])
    return rd_ci, ld_ci
