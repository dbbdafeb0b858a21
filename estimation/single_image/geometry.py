"""Patches of a mesh seen by a camera, the lights, and the irradiance they put on each patch."""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..forward import irradiance_directional, irradiance_point_lights
from ..rays import RayEngine
from ..shadows import (ENV_SHADOW_ROWS, direction_visibility, environment_irradiance, is_convex_mesh,
                       point_light_visibility)

Array = NDArray[np.float64]


# ---------------------------------------------------------------------------------------------- geometry
@dataclass(frozen=True)
class Patches:
    """Surface patches of the object: all of them are light sources (c_k); the ``visible`` ones are observed.

    ``cos_out`` = n . (camera - x)/|camera - x| (the exit cosine for F_t(eta, w_o)).
    ``occluder``: the mesh (as a :class:`estimation.rays.RayEngine`) that casts shadows on the patches, with
    ``face_index`` (K,) the face each patch centre lies on (or None); None = no cast shadows (a convex object,
    or shadows switched off): :func:`patch_irradiance` then uses max(0, n.l) only.
    """

    centers_mm: Array  # (K, 3)
    normals: Array  # (K, 3), unit
    areas_mm2: Array  # (K,)
    cos_out: Array  # (K,)
    visible: NDArray[np.bool_]  # (K,)
    occluder: RayEngine | None = field(default=None, compare=False, repr=False)
    face_index: NDArray[np.intp] | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        k = self.centers_mm.shape[0]
        if not (self.centers_mm.shape == (k, 3) and self.normals.shape == (k, 3) and self.areas_mm2.shape == (k,)
                and self.cos_out.shape == (k,) and self.visible.shape == (k,)):
            raise ValueError("Patches: centers (K,3), normals (K,3), areas (K,), cos_out (K,), visible (K,)")
        if self.face_index is not None and np.shape(self.face_index) != (k,):
            raise ValueError(f"Patches: face_index must be (K,) = ({k},); got {np.shape(self.face_index)}")

    @property
    def shadows(self) -> bool:
        """True when the irradiance of these patches includes cast shadows (an ``occluder`` is set)."""
        return self.occluder is not None

    def with_shadows(self, occluder: RayEngine | None, face_index: ArrayLike | None = None) -> "Patches":
        """The same patches with cast shadows from ``occluder`` (None: without shadows)."""
        fi = None if (occluder is None or face_index is None) else np.asarray(face_index, dtype=np.intp)
        return replace(self, occluder=occluder, face_index=fi)

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


def facing_in_frame(centers: Array, normals: Array, camera: Any, cos_min: float
                    ) -> tuple[Array, NDArray[np.bool_], Array]:
    """(camera position, facing-and-in-frame flag, cos of the exit angle) of surface points (K, 3) with normals
    (K, 3): facing = cos >= ``cos_min``; in frame = in front of the camera and projecting inside the image (when
    ``camera`` can project; a bare position (3,) only gives the facing test)."""
    cam_pos = np.asarray(getattr(camera, "center_mm", camera), dtype=np.float64).reshape(3)
    cos_out = _cos_to(centers, normals, cam_pos)
    visible = cos_out >= cos_min
    if hasattr(camera, "project") and hasattr(camera, "width_px"):
        uv, z = camera.project(centers)
        visible &= (z > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= camera.width_px - 0.5) \
            & (uv[:, 1] >= -0.5) & (uv[:, 1] <= camera.height_px - 0.5)
    return cam_pos, visible, cos_out


def occluded_from(engine: RayEngine, points_mm: Array, target_mm: Array, own_face: NDArray[np.intp]
                  ) -> NDArray[np.bool_]:
    """True where a face of ``engine``'s mesh blocks the segment from a surface point (K, 3) on face
    ``own_face`` (K,) to ``target_mm`` (3,) (a camera or light position): one occlusion ray per point
    (:class:`estimation.rays.RayEngine`), started 1e-6 mesh diagonals off the point, passing through its own
    face, and stopped as far short of the target."""
    d = np.asarray(target_mm, dtype=np.float64).reshape(1, 3) - points_mm
    dist = np.linalg.norm(d, axis=1)
    eps = 1e-6 * engine.scale
    return engine.occluded(points_mm, d, dist - eps, min_dist=eps, own_face=own_face)


def patches_from_mesh(mesh: Any, camera: Any, *, cos_min: float = float(np.cos(np.radians(70.0))),
                      occlusion: Union[bool, str] = "auto", shadows: Union[bool, str] = "auto",
                      max_edge_mm: float | None = None) -> Patches:
    """Faces of a ``trimesh.Trimesh`` as patches (centroids, face normals, areas) with camera visibility.

    ``camera``: an object with ``center_mm`` (e.g. :class:`estimation.camera.PinholeCamera`, whose ``project``
    also restricts visibility to the image frame) or a camera position (3,) in mm. A patch is visible when it
    faces the camera with n.v >= ``cos_min`` (default cos 70 deg: grazing views are masked because dividing by
    F_t(w_o) explodes there), lies in the frame, and (``occlusion``) nothing blocks the segment to the camera
    (one ray per patch, :func:`occluded_from`): "auto" tests occlusion only for non-convex meshes (back-face
    culling is exact for convex ones).
    ``shadows``: cast shadows in :func:`patch_irradiance` (shadow rays against this mesh,
    :mod:`estimation.shadows`); "auto" = on for meshes that are not convex (:func:`estimation.shadows.is_convex_mesh`;
    a convex mesh casts none, and its irradiance stays exactly max(0, n.l)), True = always, False = never.
    ``max_edge_mm`` subdivides the mesh first (``trimesh.remesh.subdivide_to_size``).
    """
    import trimesh

    if max_edge_mm is not None:
        v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=float(max_edge_mm))
        mesh = trimesh.Trimesh(v, f, process=False)
    centers = np.asarray(mesh.triangles_center, dtype=np.float64)
    normals = np.asarray(mesh.face_normals, dtype=np.float64)
    areas = np.asarray(mesh.area_faces, dtype=np.float64)
    cam_pos, visible, cos_out = facing_in_frame(centers, normals, camera, cos_min)
    for name, value in (("occlusion", occlusion), ("shadows", shadows)):
        if not (value == "auto" or isinstance(value, (bool, np.bool_))):
            raise ValueError(f"patches_from_mesh: {name} must be 'auto', True or False; got {value!r}")
    convex: bool | None = None
    if occlusion == "auto" or shadows == "auto":
        convex = is_convex_mesh(mesh.vertices, mesh.faces)
    test = (not convex) if occlusion == "auto" else bool(occlusion)
    cast = (not convex) if shadows == "auto" else bool(shadows)
    engine = None
    if (test and visible.any()) or cast:
        engine = RayEngine(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces))
    if test and visible.any():
        assert engine is not None
        idx = np.flatnonzero(visible)
        blocked = occluded_from(engine, centers[idx], cam_pos, idx)
        visible[idx[blocked]] = False
    if cast:
        return Patches(centers, normals, areas, cos_out, visible, engine, np.arange(len(centers), dtype=np.intp))
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
    """Distant lights: unit directions towards the light (L, 3) and radiance x solid angle weights (L, C).

    ``grid_shape`` (H, W): the directions are the pixels of a lat-long environment map (any rotation of
    :meth:`EnvironmentMap.directions_and_weights`), row-major: cast shadows are then computed per visibility cell
    (``shadow_rows``, as for :class:`EnvironmentMap`) instead of one ray per direction."""

    directions: ArrayLike
    radiance_weights: ArrayLike
    grid_shape: tuple[int, int] | None = None
    shadow_rows: int = ENV_SHADOW_ROWS


@dataclass(frozen=True)
class EnvironmentMap:
    """Distant lat-long environment map, radiance (H, W, C), in the rig frame (+z up).

    Mapping: pixel (row i, column j) is the direction with polar angle theta = pi (i + 0.5)/H from +z (row 0 is
    straight up) and azimuth phi = 2 pi (j + 0.5)/W from +x towards +y:
    w = (sin theta cos phi, sin theta sin phi, cos theta), pointing from the object towards the environment.
    Solid angle of a pixel: sin theta (pi/H)(2 pi/W). Maps larger than ``max_size`` rows are box-downsampled
    (rows and columns by the same integer factor) before use. Cast shadows (patches with an ``occluder``):
    per-patch visibility of ``shadow_rows`` x 2 ``shadow_rows`` cells of the map
    (:func:`estimation.shadows.environment_irradiance`, its stated accuracy).
    """

    radiance: ArrayLike
    max_size: int = 64
    shadow_rows: int = ENV_SHADOW_ROWS

    def grid_shape(self) -> tuple[int, int]:
        """(rows, columns) of the map after downsampling: the grid of :meth:`directions_and_weights`."""
        img = np.asarray(self.radiance)
        h, w = img.shape[:2]
        f = max(1, int(np.ceil(h / self.max_size)))
        return (h // f, w // f) if f > 1 else (h, w)

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


def patch_irradiance(patches: Patches, lights: Lights, eta: float, *, shadows: bool = True) -> Array:
    """Fresnel-transmitted irradiance E_t per patch (K, C) (the seed's c_k / A_k, Eq. 12).

    ``lights``: :class:`PointLights`, :class:`DirectionalLights`, :class:`EnvironmentMap`, or an array (K, C)
    or (K,) that already is E_t per patch. Cast shadows (:mod:`estimation.shadows`) when the patches carry an
    ``occluder`` (:func:`patches_from_mesh` sets one for non-convex meshes) and ``shadows``: one shadow ray per
    patch and point or distant light, per-cell visibility for environment maps; otherwise max(0, n.l) only.
    """
    eng = patches.occluder if shadows else None
    own = patches.face_index
    if isinstance(lights, PointLights):
        vis = None if eng is None else point_light_visibility(eng, patches.centers_mm, patches.normals,
                                                               lights.positions_mm, own_face=own)
        return irradiance_point_lights(patches.centers_mm, patches.normals, lights.positions_mm, lights.intensity,
                                       eta, visibility=vis)
    if isinstance(lights, DirectionalLights):
        if eng is not None and lights.grid_shape is not None:
            return environment_irradiance(eng, patches.centers_mm, patches.normals, lights.directions,
                                          lights.radiance_weights, lights.grid_shape, eta, rows=lights.shadow_rows,
                                          own_face=own)
        vis = None if eng is None else direction_visibility(eng, patches.centers_mm, patches.normals,
                                                             lights.directions, own_face=own)
        return irradiance_directional(patches.normals, lights.directions, lights.radiance_weights, eta,
                                      visibility=vis)
    if isinstance(lights, EnvironmentMap):
        d, w = lights.directions_and_weights()
        if eng is not None:
            return environment_irradiance(eng, patches.centers_mm, patches.normals, d, w, lights.grid_shape(), eta,
                                          rows=lights.shadow_rows, own_face=own)
        return irradiance_directional(patches.normals, d, w, eta)
    e = np.asarray(lights, dtype=np.float64)
    if e.ndim == 1:
        e = e[:, None]
    if e.shape[0] != patches.centers_mm.shape[0]:
        raise ValueError(f"irradiance array has {e.shape[0]} rows, expected one per patch ({len(patches.areas_mm2)})")
    return e
