"""True normals from a mesh named by the capture folder (issue 16: "a mesh given by the capture folder").

``[object] shape = "relief"`` with ``mesh_file`` (PLY, OBJ or STL in the rig frame; ``mesh_units`` mm / cm / m /
in, default mm; ``mesh_translation_mm``): the mesh is rendered into the folder's camera by one ray per pixel centre
(:func:`rig.estimate.pixel_map.pixel_faces`: Embree, or the numba BVH), and each pixel's normal is the mesh's
vertex normals (trimesh's face-angle-weighted average) interpolated barycentrically at the hit point -- a smooth
normal field, as a scanned mesh is meant to be, not the facets' own normals. Pixels whose ray misses the mesh or
hits the back of a face are NaN (unknown). The relief fit (:mod:`rig.estimate.folder_diffusion`) then uses these
normals exactly as a ``normals_file``. Documented in ``docs/capture-folder.md`` (``[object]``).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["mesh_normals_in_camera", "read_mesh_normals"]


def mesh_normals_in_camera(mesh: Any, camera: Any) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(normals (H, W, 3), points (H, W, 3)) of ``mesh`` (a ``trimesh.Trimesh``, mm, rig frame) seen by
    ``camera``: smooth (barycentric vertex-normal) unit normals and the surface points; NaN where no front face is
    seen."""
    from rig.estimate.pixel_map import pixel_faces

    H, W = camera.height_px, camera.width_px
    points = np.empty((H, W, 3))
    face = pixel_faces(mesh, camera, points=points)
    normals = np.full((H, W, 3), np.nan)
    hit = face >= 0
    if not hit.any():
        return normals, points
    f = np.asarray(mesh.faces)[face[hit]]                                 # (n, 3) vertex indices
    tri = np.asarray(mesh.vertices, dtype=np.float64)[f]                 # (n, 3, 3)
    p = points[hit]
    # barycentric coordinates of p in its triangle (Ericson, Real-Time Collision Detection, sec. 3.4)
    v0, v1, v2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], p - tri[:, 0]
    d00, d01, d11 = (v0 * v0).sum(-1), (v0 * v1).sum(-1), (v1 * v1).sum(-1)
    d20, d21 = (v2 * v0).sum(-1), (v2 * v1).sum(-1)
    den = d00 * d11 - d01 * d01
    b1 = (d11 * d20 - d01 * d21) / den
    b2 = (d00 * d21 - d01 * d20) / den
    bary = np.clip(np.stack([1.0 - b1 - b2, b1, b2], axis=-1), 0.0, 1.0)
    vn = np.asarray(mesh.vertex_normals, dtype=np.float64)[f]            # (n, 3, 3)
    n = np.einsum("nk,nkj->nj", bary, vn)
    fn = np.asarray(mesh.face_normals, dtype=np.float64)[face[hit]]
    n = np.where((np.einsum("nj,nj->n", n, fn) > 0)[:, None], n, fn)  # a vertex normal against its face: the face's
    normals[hit] = n / np.linalg.norm(n, axis=-1, keepdims=True)
    return normals, points


def read_mesh_normals(t: Any, folder: Path, shape: tuple[int, int], camera: Any) -> tuple[NDArray[np.float64], Path]:
    """``[object] mesh_file`` (+ ``mesh_units``, ``mesh_translation_mm``) of the table ``t`` rendered into
    ``camera``: (normals (H, W, 3), the file). Errors name the file and key (unreadable, not one triangle mesh,
    no pixel of the frames sees it)."""
    from rig.files.scene_spec import MESH_SUFFIXES, MESH_UNITS_MM, MeshFileError, load_triangle_mesh

    p = t.path("mesh_file", folder, "mesh (" + ", ".join(MESH_SUFFIXES) + ")")
    if p.suffix.lower() not in MESH_SUFFIXES:
        raise t.err("mesh_file", "a mesh file with a suffix among " + ", ".join(MESH_SUFFIXES), p.name)
    units = t.str("mesh_units", "mm", choices=tuple(MESH_UNITS_MM))
    shift = t.vec("mesh_translation_mm", 3, [0.0, 0.0, 0.0])
    try:
        mesh = load_triangle_mesh(p)
    except MeshFileError as exc:
        raise t.err("mesh_file", exc.expected, exc.found) from None
    mesh.apply_scale(MESH_UNITS_MM[units])
    mesh.apply_translation(shift)
    normals, _ = mesh_normals_in_camera(mesh, camera)
    if tuple(normals.shape[:2]) != tuple(shape):
        raise t.err("mesh_file", f"a camera of the frames' size {shape[1]} x {shape[0]} px", normals.shape[:2])
    if not np.isfinite(normals).all(-1).any():
        raise t.err("mesh_file", "a mesh that the camera sees (in the rig frame, mm x mesh_units; no pixel's ray "
                    "hits a front face)", p.name)
    return normals, p
