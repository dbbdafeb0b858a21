"""Patch decimation: ~10k patches of a 100k-face scanned mesh, while visibility, the pixel-to-face map and cast
shadows stay on the full mesh (issue 17).

The single-image method needs patches well below the diffusion length l_d, not the scan's resolution; its cost
grows with the patches (observed x sources), a scanned mesh's faces do not have to. So:

1. **Patches** are the faces of a copy of the mesh decimated by quadric error metrics (Garland & Heckbert,
   "Surface simplification using quadric error metrics", SIGGRAPH 1997; ``trimesh.Trimesh.
   simplify_quadric_decimation`` over the ``fast-simplification`` package): the decimated face's normal and area
   are the patch's.
2. **Full faces -> patches**: every face of the full mesh belongs to the patch whose decimated face centre is
   nearest to its own centre (a k-d tree over the decimated centres, the nearest of :data:`ASSIGN_CANDIDATES`
   that faces the same side, n_full . n_patch > 0, so a thin part's other side is never taken): each patch owns
   the Voronoi cell of its centre on the full surface. Pixel -> full face (the ray-cast map) -> patch.
3. **Patch centres on the full surface.** A decimated face lies off the full surface by the decimation error (a
   chord of a convex patch lies *inside*: its centre ray would start under the full surface and every shadow or
   camera ray would be blocked by the patch's own surface — spurious self-shadowing). Each patch centre is moved
   along the patch normal onto the full surface: one ray from c - H n along +n against the full mesh, H = 2 x the
   patch's *decimation deviation* (the largest |distance| of its full faces' centres from its plane,
   ``deviation_mm``) + :data:`SNAP_MIN_WINDOW` mesh diagonals; the first hit within 2 H on a face that faces the
   same side gives the centre and the full face it lies on (``face_index``). Occlusion and shadow rays then start
   there exactly as for an undecimated mesh: SHADOW_OFFSET (1e-5 mesh diagonals) along the patch normal, passing
   through that face. A patch whose ray finds no such face (a sharp fold; counted as ``not_snapped``) keeps its
   decimated centre moved out by its deviation (``c + deviation n``: above the full surface within the patch).
4. **Observations** are gathered from the pixels that belong to each patch (:func:`gather_patch_pixels`): a
   least-squares plane through the values of the patch's valid pixels over their surface points' coordinates in
   the patch's tangent plane, evaluated at the patch centre (the pixels' centroid is not the centre: a plain mean
   would be biased by the radiance gradient across the patch; tangent-plane rather than image coordinates, which
   are foreshortened non-linearly near grazing views), with the standard error of that value from the per-pixel
   variances; the mean where the pixels are too few (< :data:`PATCH_PLANE_PIXELS`) or too collinear for a plane,
   nothing below :data:`PATCH_MIN_PIXELS`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Union

import numpy as np
from numpy.typing import NDArray

from ..rays import RayEngine
from ..shadows import is_convex_mesh
from .geometry import Patches, facing_in_frame, occluded_from

Array = NDArray[np.float64]

#: decimated-face centres considered per full face (the nearest that faces the same side is taken)
ASSIGN_CANDIDATES = 4
#: snapping window floor, in mesh bounding-box diagonals (patches whose faces all lie in their plane)
SNAP_MIN_WINDOW = 1e-4
#: a patch needs this many valid pixels (per channel) to be observed ...
PATCH_MIN_PIXELS = 4
#: ... and this many, spread along their narrowest direction at least PLANE_MIN_ASPECT x along the widest (rms), for
#: the plane fit (else their mean)
PATCH_PLANE_PIXELS = 8
PLANE_MIN_ASPECT = 0.2


@dataclass(frozen=True)
class DecimatedPatches:
    """Patches of a decimated copy of a mesh, seen and shadowed by the full mesh.

    ``patches``: centres on the full surface, normals and areas of the decimated faces, camera visibility and (when
    cast) the full mesh as ``occluder`` with ``face_index`` the full face each centre lies on;
    ``face_to_patch`` (F,) the patch of every full face; ``engine`` the full mesh's :class:`RayEngine` (for the
    pixel map); ``deviation_mm`` (K,) the decimation deviation of each patch (module docstring, 3);
    ``snapped`` (K,) True where the centre was moved onto the full surface; ``seconds`` the stages' wall times.
    """

    patches: Patches
    face_to_patch: NDArray[np.intp]
    engine: RayEngine
    deviation_mm: Array
    snapped: NDArray[np.bool_]
    mesh_faces: int
    seconds: dict[str, float] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        """JSON-able figures: faces, patches, deviation percentiles, snapped count, empty patches."""
        counts = np.bincount(self.face_to_patch, minlength=len(self.deviation_mm))
        dev = self.deviation_mm
        return {"mesh_faces": int(self.mesh_faces), "patches": int(len(dev)),
                "faces_per_patch_median": float(np.median(counts)), "patches_without_faces": int(np.sum(counts == 0)),
                "deviation_mm_median": float(np.median(dev)), "deviation_mm_p99": float(np.percentile(dev, 99)),
                "deviation_mm_max": float(dev.max()), "not_snapped": int(np.sum(~self.snapped)),
                "seconds": dict(self.seconds)}


def decimate_mesh(mesh: Any, patches: int) -> Any:
    """A copy of the ``trimesh.Trimesh`` decimated to about ``patches`` faces by quadric error metrics
    (``simplify_quadric_decimation``; needs the ``fast-simplification`` package). Raises ValueError for
    ``patches`` outside 4..faces."""
    n = len(mesh.faces)
    if not (isinstance(patches, (int, np.integer)) and 4 <= int(patches) <= n):
        raise ValueError(f"decimate_mesh: patches must be an integer in 4..{n} (the mesh's faces); got {patches!r}")
    if int(patches) == n:
        return mesh.copy()
    out = mesh.simplify_quadric_decimation(face_count=int(patches))
    areas = np.asarray(out.area_faces)
    keep = areas > 1e-12 * max(float(areas.max()), 1e-300)
    if not keep.all():
        out.update_faces(keep)
    return out


def assign_faces(full_centers_mm: Array, full_normals: Array, patch_centers_mm: Array, patch_normals: Array,
                 *, candidates: int = ASSIGN_CANDIDATES) -> NDArray[np.intp]:
    """The patch (K) of every full face (F,): the nearest of the ``candidates`` nearest patch centres whose normal
    faces the same side as the face's (n_f . n_k > 0), else the nearest."""
    from scipy.spatial import cKDTree

    tree = cKDTree(patch_centers_mm)
    _, near = tree.query(full_centers_mm, k=1, workers=-1)
    out = np.asarray(near, dtype=np.intp)
    redo = np.flatnonzero(np.einsum("fc,fc->f", full_normals, patch_normals[out]) <= 0.0)
    k = int(min(max(1, candidates), len(patch_centers_mm)))
    if len(redo) and k > 1:       # the nearest faces the other way (a thin part): the nearest that faces this way
        _, idx = tree.query(full_centers_mm[redo], k=k, workers=-1)
        idx = np.asarray(idx, dtype=np.intp).reshape(len(redo), k)
        same = np.einsum("fc,fkc->fk", full_normals[redo], patch_normals[idx]) > 0.0
        first = np.where(same.any(axis=1), np.argmax(same, axis=1), 0)
        out[redo] = idx[np.arange(len(idx)), first]
    return out


def patch_deviation_mm(full_centers_mm: Array, face_to_patch: NDArray[np.intp], patch_centers_mm: Array,
                       patch_normals: Array) -> Array:
    """Per patch (K,): the largest |distance| of its full faces' centres from the patch's plane (0 if it owns
    none) — the local decimation error, plus the patch's curvature sag."""
    h = np.abs(np.einsum("fc,fc->f", full_centers_mm - patch_centers_mm[face_to_patch], patch_normals[face_to_patch]))
    out = np.zeros(len(patch_centers_mm))
    np.maximum.at(out, face_to_patch, h)
    return out


def snap_to_surface(engine: RayEngine, centers_mm: Array, normals: Array, deviation_mm: Array
                    ) -> tuple[Array, NDArray[np.intp], NDArray[np.bool_]]:
    """Move each centre along its normal onto the engine's surface (module docstring, 3): centres (K, 3), the full
    face each lies on (K,) (-1 where not snapped) and the snapped mask (K,)."""
    window = 2.0 * deviation_mm + SNAP_MIN_WINDOW * engine.scale
    start = centers_mm - window[:, None] * normals
    face, t = engine.first_hit(start, normals)
    ok = (face >= 0) & (t <= 2.0 * window)
    ok[ok] = np.einsum("kc,kc->k", engine.face_normals[face[ok]], normals[ok]) > 0.0
    out = centers_mm + deviation_mm[:, None] * normals          # not snapped: above the full surface
    out[ok] = start[ok] + t[ok, None] * normals[ok]
    return out, np.where(ok, face, -1).astype(np.intp), ok


def patches_from_decimated(mesh: Any, patch_mesh: Any, camera: Any, *,
                           cos_min: float = float(np.cos(np.radians(70.0))), occlusion: Union[bool, str] = "auto",
                           shadows: Union[bool, str] = "auto", engine: RayEngine | None = None) -> DecimatedPatches:
    """Patches of ``patch_mesh`` (a decimated copy of ``mesh``, e.g. :func:`decimate_mesh`) with visibility and cast
    shadows against the full ``mesh`` (module docstring). ``camera``, ``cos_min``, ``occlusion``, ``shadows`` as in
    :func:`estimation.single_image.patches_from_mesh` ("auto": tested on the full mesh's convexity); ``engine``:
    the full mesh's :class:`RayEngine` if already built."""
    for name, value in (("occlusion", occlusion), ("shadows", shadows)):
        if not (value == "auto" or isinstance(value, (bool, np.bool_))):
            raise ValueError(f"patches_from_decimated: {name} must be 'auto', True or False; got {value!r}")
    sec: dict[str, float] = {}
    t0 = time.perf_counter()
    if engine is None:
        engine = RayEngine(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces))
        sec["engine_build"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    pc = np.asarray(patch_mesh.triangles_center, dtype=np.float64)
    pn = np.asarray(patch_mesh.face_normals, dtype=np.float64)
    areas = np.asarray(patch_mesh.area_faces, dtype=np.float64)
    fc = np.asarray(mesh.triangles_center, dtype=np.float64)
    f2p = assign_faces(fc, np.asarray(mesh.face_normals, dtype=np.float64), pc, pn)
    dev = patch_deviation_mm(fc, f2p, pc, pn)
    sec["patch_map"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    centers, own, snapped = snap_to_surface(engine, pc, pn, dev)
    sec["snap"] = time.perf_counter() - t0
    cam_pos, visible, cos_out = facing_in_frame(centers, pn, camera, cos_min)
    convex: bool | None = None
    if occlusion == "auto" or shadows == "auto":
        t0 = time.perf_counter()
        convex = is_convex_mesh(mesh.vertices, mesh.faces)
        sec["convexity"] = time.perf_counter() - t0
    test = (not convex) if occlusion == "auto" else bool(occlusion)
    cast = (not convex) if shadows == "auto" else bool(shadows)
    if test and visible.any():
        t0 = time.perf_counter()
        idx = np.flatnonzero(visible)
        visible[idx[occluded_from(engine, centers[idx], cam_pos, own[idx])]] = False
        sec["occlusion"] = time.perf_counter() - t0
    p = Patches(centers, pn, areas, cos_out, visible)
    if cast:
        p = p.with_shadows(engine, own)
    return DecimatedPatches(p, f2p, engine, dev, snapped, int(len(mesh.faces)), sec)


def gather_patch_pixels(image: Array, variance: Array, valid: NDArray[np.bool_], pixel_face: NDArray[np.integer],
                        face_to_patch: NDArray[np.intp], pixel_points_mm: Array, centers_mm: Array, normals: Array
                        ) -> tuple[Array, Array, NDArray[np.intp]]:
    """Radiance of each patch from its pixels (module docstring, 4): ``image``, ``variance``, ``valid`` (H, W, C),
    ``pixel_face`` (H, W) the full face seen by each pixel (-1: background), ``face_to_patch`` (F,),
    ``pixel_points_mm`` (H, W, 3) the surface point of each pixel (e.g. ``rig.estimate.pixel_map.pixel_faces(..., points=)``), the
    patches'
    ``centers_mm`` and unit ``normals`` (K, 3). A least-squares plane over the patch's tangent-plane coordinates
    of its valid pixels' surface points (linear along the surface, not in the foreshortened image), evaluated at
    the centre. Returns the value (K, C), its standard error (K, C) (NaN where fewer than :data:`PATCH_MIN_PIXELS` valid
    pixels) and the valid pixels per patch (K, C)."""
    n_ch = image.shape[2]
    k = len(centers_mm)
    pf = np.asarray(pixel_face).reshape(-1)
    idx = np.flatnonzero(pf >= 0)
    patch = np.asarray(face_to_patch, dtype=np.intp)[pf[idx]]
    # tangent axes of each patch (any orthonormal pair perpendicular to its normal)
    nrm = np.asarray(normals, dtype=np.float64)
    helper = np.where(np.abs(nrm[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    e1 = np.cross(nrm, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(nrm, e1)
    rel = np.asarray(pixel_points_mm, dtype=np.float64).reshape(-1, 3)[idx] - centers_mm[patch]
    du = np.einsum("ic,ic->i", rel, e1[patch])
    dv = np.einsum("ic,ic->i", rel, e2[patch])
    obs = np.full((k, n_ch), np.nan)
    sig = np.full((k, n_ch), np.nan)
    count = np.zeros((k, n_ch), dtype=np.intp)
    img = image.reshape(-1, n_ch)
    var = variance.reshape(-1, n_ch)
    ok_all = valid.reshape(-1, n_ch)
    for c in range(n_ch):
        ok = ok_all[idx, c]
        p, x, y = patch[ok], du[ok], dv[ok]
        val, vv = img[idx[ok], c], var[idx[ok], c]

        def s(wt: Array | None) -> Array:
            return np.bincount(p, weights=wt, minlength=k).astype(np.float64)

        n = s(None)
        count[:, c] = n.astype(np.intp)
        basis = (np.ones_like(x), x, y)
        a = np.empty((k, 3, 3))
        b = np.empty((k, 3, 3))
        for i in range(3):
            for j in range(i, 3):
                a[:, i, j] = a[:, j, i] = s(basis[i] * basis[j])
                b[:, i, j] = b[:, j, i] = s(vv * basis[i] * basis[j])
        yv = np.stack([s(val * bi) for bi in basis], axis=1)                       # (K, 3)
        has = n >= PATCH_MIN_PIXELS
        nn = np.maximum(n, 1.0)
        mu, mv = a[:, 0, 1] / nn, a[:, 0, 2] / nn
        cuu, cvv, cuv = a[:, 1, 1] / nn - mu ** 2, a[:, 2, 2] / nn - mv ** 2, a[:, 1, 2] / nn - mu * mv
        root = np.sqrt(np.maximum(0.25 * (cuu - cvv) ** 2 + cuv ** 2, 0.0))
        lam_min, lam_max = 0.5 * (cuu + cvv) - root, 0.5 * (cuu + cvv) + root
        plane = has & (n >= PATCH_PLANE_PIXELS) & (lam_min >= PLANE_MIN_ASPECT ** 2 * lam_max) & (lam_max > 0)
        mean = has & ~plane
        obs[mean, c] = yv[mean, 0] / n[mean]
        sig[mean, c] = np.sqrt(b[mean, 0, 0]) / n[mean]
        if plane.any():
            ai = np.linalg.inv(a[plane])
            beta = np.einsum("kij,kj->ki", ai, yv[plane])
            obs[plane, c] = beta[:, 0]
            cov = np.einsum("kij,kjl,klm->kim", ai, b[plane], ai)
            sig[plane, c] = np.sqrt(np.maximum(cov[:, 0, 0], 0.0))
    return obs, sig, count
