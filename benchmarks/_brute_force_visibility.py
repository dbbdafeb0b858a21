"""The brute-force visibility that issue 17 replaced, kept verbatim (bar names) as the baseline of
benchmarks/meshes.py. Not used by the package.

- :func:`occluded_brute_force`: every patch-to-camera segment against every face (vectorized Moller-Trumbore),
  formerly ``estimation.single_image.geometry._occluded``;
- :func:`hits_brute_force`: every ray against every face, nearest hit, formerly
  ``simulators.scene.MeshObject._hits`` (here a function of the triangles);
- :func:`pixel_faces_painters_order`: front faces rasterized back to front by centroid depth
  (``cv2.fillConvexPoly``), formerly ``rig.estimate.sessions.pixel_faces`` — not exact on non-convex meshes.
"""
from __future__ import annotations

import numpy as np

Array = np.ndarray


def occluded_brute_force(origins: Array, target: Array, vertices: Array, faces: Array, skip_face: Array,
                         chunk: int = 256) -> Array:
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


def hits_brute_force(tri: Array, origins: Array, dirs: Array) -> tuple[Array, Array, Array, Array]:
    """Nearest hit of each ray (M, 3): t (inf if none), face index, barycentrics (b1, b2) (Moller-Trumbore)."""
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    M = origins.shape[0]
    best = np.full(M, np.inf)
    face = np.full(M, -1, np.intp)
    bb1 = np.zeros(M)
    bb2 = np.zeros(M)
    step = max(1, 500_000 // max(len(tri), 1))  # (step, F, 3) float64 temporaries of ~12 MB
    with np.errstate(divide="ignore", invalid="ignore"):
        for s in range(0, M, step):
            o, d = origins[s:s + step, None, :], dirs[s:s + step, None, :]
            pv = np.cross(d, e2[None])
            det = np.sum(e1[None] * pv, -1)
            inv = 1.0 / det
            tv = o - v0[None]
            b1 = np.sum(tv * pv, -1) * inv
            qv = np.cross(tv, e1[None])
            b2 = np.sum(d * qv, -1) * inv
            t = np.sum(e2[None] * qv, -1) * inv
            ok = (np.abs(det) > 1e-12) & (b1 >= 0) & (b2 >= 0) & (b1 + b2 <= 1) & (t > 1e-9)
            t = np.where(ok, t, np.inf)
            j = np.argmin(t, axis=1)
            r = np.arange(t.shape[0])
            best[s:s + step] = t[r, j]
            face[s:s + step] = j
            bb1[s:s + step] = b1[r, j]
            bb2[s:s + step] = b2[r, j]
    return best, face, bb1, bb2


def pixel_faces_painters_order(mesh, camera) -> np.ndarray:
    """Index of the mesh face seen by each pixel (H, W), -1 where no face covers the pixel centre.

    Front-facing faces are rasterized back to front (painter's order by centroid depth) into a face-ID
    buffer with OpenCV, at 1/256 px sub-pixel precision.
    """
    import cv2

    verts = np.asarray(mesh.vertices, float)
    faces = np.asarray(mesh.faces)
    uv, depth = camera.project(verts)
    centers = verts[faces].mean(axis=1)
    normals = np.asarray(mesh.face_normals, float)
    facing = np.sum(normals * (camera.C - centers), axis=1) > 0
    in_front = np.all(depth[faces] > 0, axis=1)
    idx = np.flatnonzero(facing & in_front)
    order = idx[np.argsort(-camera.project(centers[idx])[1])]      # far to near
    buf = np.full((camera.height_px, camera.width_px), -1, np.int32)
    shift = 8
    pts = np.round((uv[faces[order]] + 0.0) * (1 << shift)).astype(np.int32)   # pixel centres at integers
    for f, tri in zip(order, pts):
        cv2.fillConvexPoly(buf, tri, int(f), lineType=cv2.LINE_8, shift=shift)
    return buf
