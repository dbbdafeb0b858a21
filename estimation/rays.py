"""Ray casting against a triangle mesh: first hits and occlusion, for every visibility question of the package.

One engine serves the three places that once tested every ray against every face: patch visibility of the
single-image method (:func:`estimation.single_image.patches_from_mesh`), the simulated camera's mesh objects
(``simulators.scene.MeshObject``) and the pixel-to-face maps of scene files (``rig.estimate.pixel_map.pixel_faces``).

Backends (``RayEngine(..., backend=...)``):

- ``"embree"`` (default when the ``embreex`` package imports): Intel Embree's BVH (Wald et al., "Embree: a kernel
  framework for efficient CPU ray tracing", ACM TOG 33(4), 2014), with trimesh's set-up (``trimesh.ray.
  ray_pyembree``: the mesh shifted and scaled to a ~100-unit box, because Embree works in float32: distances come
  out within ~1e-6 of the mesh size of float64 ones). ``embree_binding="direct"`` (the default where it works):
  the Embree 4 library ``embreex`` ships, called through ``ctypes`` (:mod:`estimation._embree4`: the scene reads
  our float32 arrays in place, rays go in packets of 16) — ``embreex``'s own ``TriangleMesh`` copies the mesh
  element by element through Python indexing, most of the engine's build time. ``"embreex"`` (the fallback where
  the library cannot be loaded): ``embreex``'s ``EmbreeScene``, one ray per call, with Embree's distance output
  rather than through trimesh's ``RayMeshIntersector`` (whose faces-and-points call ran at 0.51 x Embree's raw
  rate, this at 0.69 x; benchmarks/meshes.py, docs/visibility.md).
- ``"bvh"``: this module's own median-split bounding-volume hierarchy traversed by a numba kernel with the
  Moller-Trumbore test (Moller & Trumbore, "Fast, minimum storage ray-triangle intersection", J. Graphics Tools
  2(1), 1997), in float64: the fallback where Embree is not installed, and an independent check of it.

Neither culls back faces: a ray hits the first face it crosses from either side.
"""
from __future__ import annotations

import numpy as np
import numpy.typing as npt
from numba import njit

from ._embree4 import Embree4Scene

FloatArray = npt.NDArray[np.float64]
IndexArray = npt.NDArray[np.intp]

BACKENDS = ("embree", "bvh")
_STACK = 64          # BVH traversal stack (depth of a median-split tree of 2^60 leaves)
_LEAF_SIZE = 4


def embree_available() -> bool:
    """True when Embree's Python binding (package ``embreex``) imports."""
    try:
        from embreex import rtcore_scene  # noqa: F401
    except ImportError:
        return False
    return True


class RayEngine:
    """First-hit and occlusion queries of rays against one triangle mesh (units of the vertices, e.g. mm).

    ``vertices`` (V, 3), ``faces`` (F, 3) vertex indices. ``backend``: ``"auto"`` (Embree if ``embreex``
    imports, else the numba BVH), ``"embree"`` or ``"bvh"``. ``embree_binding`` (Embree only): ``"auto"`` (Embree 4
    through ctypes, else ``embreex``'s classes), ``"direct"`` or ``"embreex"`` (module docstring); the one used is
    ``self.embree_binding``. Building the acceleration structure costs about as
    much as a few hundred thousand rays; build the engine once per mesh and query it with many rays at once.

    >>> import trimesh
    >>> box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    >>> face, dist = RayEngine(box.vertices, box.faces).first_hit([[0.0, 0.0, 5.0]], [[0.0, 0.0, -1.0]])
    >>> round(float(dist[0]), 5)
    4.0
    """

    def __init__(self, vertices: npt.ArrayLike, faces: npt.ArrayLike, *, backend: str = "auto",
                 embree_binding: str = "auto") -> None:
        v = np.ascontiguousarray(vertices, dtype=np.float64)
        f = np.ascontiguousarray(faces, dtype=np.int64)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
            raise ValueError(f"RayEngine: vertices must be (V, 3) and faces (F, 3); got {v.shape} and {f.shape}")
        if len(f) == 0:
            raise ValueError("RayEngine: the mesh has no faces")
        if f.min() < 0 or f.max() >= len(v):
            raise ValueError(f"RayEngine: face indices must lie in 0..{len(v) - 1}; got {f.min()}..{f.max()}")
        if not np.all(np.isfinite(v)):
            raise ValueError("RayEngine: vertices must be finite")
        if backend == "auto":
            backend = "embree" if embree_available() else "bvh"
        if embree_binding not in ("auto", "direct", "embreex"):
            raise ValueError(f"RayEngine: embree_binding must be 'auto', 'direct' or 'embreex'; got {embree_binding!r}")
        if backend not in BACKENDS:
            raise ValueError(f"RayEngine: backend must be 'auto' or one of {', '.join(BACKENDS)}; got {backend!r}")
        if backend == "embree" and not embree_available():
            raise ImportError("RayEngine: backend 'embree' needs the embreex package (pip install embreex)")
        self.backend: str = backend
        self.vertices, self.faces = v, f
        tri = v[f]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        self.face_normals: FloatArray = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)  # (F, 3)
        self.scale: float = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))   # bounding-box diagonal
        if backend == "embree":
            # as trimesh.ray.ray_pyembree._EmbreeWrap: shift to the box corner, scale to a ~100-unit box
            self._origin = v.min(axis=0)
            self._center = 0.5 * (v.min(axis=0) + v.max(axis=0))
            self._radius = 0.5 * self.scale
            self._to_box = 100.0 / max(self.scale, 1e-300)
            v_box = ((v - self._origin) * self._to_box).astype(np.float32)
            self._direct: Embree4Scene | None = None
            if embree_binding in ("auto", "direct"):
                try:          # Embree 4 through ctypes: shared buffers, 16-ray packets (estimation._embree4)
                    self._direct = Embree4Scene(v_box, f)
                except OSError:
                    if embree_binding == "direct":
                        raise
            if self._direct is None:   # embreex's own classes: per-element copy, one ray per call
                from embreex import rtcore_scene
                from embreex.mesh_construction import TriangleMesh

                self._scene = rtcore_scene.EmbreeScene()
                TriangleMesh(scene=self._scene, vertices=v_box, indices=f.astype(np.int32))
                self._scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))   # commit (build) now
            self.embree_binding: str = "direct" if self._direct is not None else "embreex"
        else:
            self._bvh = _build_bvh(tri, _LEAF_SIZE)

    @property
    def n_faces(self) -> int:
        return int(len(self.faces))

    def first_hit(self, origins: npt.ArrayLike, dirs: npt.ArrayLike, *, min_dist: float = 0.0
                  ) -> tuple[IndexArray, FloatArray]:
        """Nearest face hit by each ray o + t d/|d| with t > ``min_dist``: face index (...) or -1 for a miss, and
        the distance t (...) in vertex units along the unit direction (inf for a miss).

        ``origins``, ``dirs``: (..., 3), broadcast against each other; ``dirs`` need not be unit vectors.
        ``min_dist`` skips the surface a ray starts on (the ray starts at o + min_dist d/|d|)."""
        o, d, shape = _rays(origins, dirs)
        if len(o) == 0:
            return np.empty(shape, np.intp), np.empty(shape)
        if min_dist:
            o = o + float(min_dist) * d
        if self.backend == "embree":
            # float32 keeps ~7 digits of the scaled coordinates: rays from far away (a camera metres off, an
            # orthographic camera's ray start) first advance in float64 to the mesh's bounding sphere
            ob = o - self._center
            t0 = np.maximum(-np.einsum("ij,ij->i", ob, d) - self._radius, 0.0)
            if np.any(t0 > 0):
                ob += t0[:, None] * d
            else:
                t0 = None
            ob += self._center - self._origin
            ob *= self._to_box
            if self._direct is not None:        # packs the rays into float32 packets itself
                prim, tfar = self._direct.intersect(ob, d)
            else:
                res = self._scene.run(ob.astype(np.float32), d.astype(np.float32), output=1)
                prim, tfar = res["primID"], res["tfar"]
            face = prim.astype(np.intp)
            t = np.multiply(tfar, 1.0 / self._to_box, dtype=np.float64)
            if t0 is not None:
                t += t0
            t[face < 0] = np.inf
        else:
            boxes, nodes, tris, order = self._bvh
            face, t = _bvh_first_hit(boxes, nodes, tris, order, np.array(o, order="C"), np.array(d, order="C"))
        if min_dist:
            t += float(min_dist)
        return face.reshape(shape), t.reshape(shape)

    def occluded(self, origins: npt.ArrayLike, dirs: npt.ArrayLike, max_dist: npt.ArrayLike, *,
                 min_dist: float | None = None, own_face: npt.ArrayLike | None = None) -> npt.NDArray[np.bool_]:
        """True where a face lies on the ray o + t d/|d| with ``min_dist`` < t < ``max_dist`` (...).

        ``max_dist`` (...) in vertex units, e.g. the distance to a light or camera; ``min_dist`` defaults to
        1e-6 of the mesh's bounding-box diagonal (a point on the surface does not occlude itself).
        ``own_face`` (...): the face each ray starts on, passed through wherever it is hit (a grazing ray can
        meet its own face again beyond ``min_dist`` in Embree's float32 arithmetic)."""
        o, d, shape = _rays(origins, dirs)
        md = np.broadcast_to(np.asarray(max_dist, dtype=np.float64), shape).reshape(-1)
        eps = 1e-6 * self.scale if min_dist is None else float(min_dist)
        face, t = self.first_hit(o, d, min_dist=eps)
        if own_face is not None:
            own = np.broadcast_to(np.asarray(own_face, dtype=np.intp), shape).reshape(-1)
            for _ in range(4):    # past the own face: re-cast from just beyond the hit
                again = np.flatnonzero((face == own) & (t < md))
                if len(again) == 0:
                    break
                skip = t[again] + eps                       # per ray: just beyond its own face's hit
                f2, t2 = self.first_hit(o[again] + skip[:, None] * d[again], d[again])
                face[again], t[again] = f2, t2 + skip
        return (t < md).reshape(shape)


def _rays(origins: npt.ArrayLike, dirs: npt.ArrayLike) -> tuple[FloatArray, FloatArray, tuple[int, ...]]:
    o, d = np.broadcast_arrays(np.asarray(origins, dtype=np.float64), np.asarray(dirs, dtype=np.float64))
    if o.shape[-1:] != (3,):
        raise ValueError(f"ray origins and directions must be (..., 3); got {np.shape(origins)} and {np.shape(dirs)}")
    shape = o.shape[:-1]
    o = o.reshape(-1, 3)
    d = d.reshape(-1, 3)
    norm2 = np.einsum("ij,ij->i", d, d)
    if not (np.all(norm2 > 0) and np.isfinite(norm2.sum()) and np.isfinite(o.sum())):
        raise ValueError("ray directions must be finite and non-zero, origins finite")
    if np.all(np.abs(norm2 - 1.0) < 1e-12):      # unit already (camera pixel rays): no copy
        return o, d, shape
    return o, d / np.sqrt(norm2)[:, None], shape


# ---------------------------------------------------------------------------------------------- numba BVH
def _build_bvh(tri: FloatArray, leaf_size: int) -> tuple[FloatArray, npt.NDArray[np.int64], FloatArray,
                                                          npt.NDArray[np.int64]]:
    """Median-split BVH over triangles (M, 3, 3): node boxes (N, 6), nodes (N, 4) = (left, right, first, count)
    (count > 0 for leaves), triangles reordered as (M, 9) = (v0, e1, e2), and the permutation to face indices."""
    cent = tri.mean(axis=1)
    lo_t, hi_t = tri.min(axis=1), tri.max(axis=1)
    order = np.arange(len(tri))
    boxes: list[FloatArray] = [np.zeros(6)]
    nodes: list[list[int]] = [[-1, -1, 0, 0]]
    todo = [(0, 0, len(tri))]
    while todo:
        node, s, e = todo.pop()
        sel = order[s:e]
        boxes[node] = np.concatenate([lo_t[sel].min(axis=0), hi_t[sel].max(axis=0)])
        if e - s <= leaf_size:
            nodes[node] = [-1, -1, s, e - s]
            continue
        c = cent[sel]
        axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
        mid = (e - s) // 2
        order[s:e] = sel[np.argpartition(c[:, axis], mid)]
        left = len(boxes)
        boxes += [np.zeros(6), np.zeros(6)]
        nodes += [[-1, -1, 0, 0], [-1, -1, 0, 0]]
        nodes[node] = [left, left + 1, 0, 0]
        todo += [(left, s, s + mid), (left + 1, s + mid, e)]
    t = tri[order]
    tris = np.concatenate([t[:, 0], t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]], axis=1)
    return np.asarray(boxes), np.asarray(nodes, dtype=np.int64), np.ascontiguousarray(tris), order.astype(np.int64)


@njit(cache=True, error_model="numpy")
def _bvh_first_hit(boxes, nodes, tris, order, origins, dirs):  # pragma: no cover - compiled
    n = origins.shape[0]
    face = np.full(n, -1, np.intp)
    dist = np.full(n, np.inf)
    stack = np.empty(_STACK, np.int64)
    for r in range(n):
        ox, oy, oz = origins[r, 0], origins[r, 1], origins[r, 2]
        dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        ix, iy, iz = 1.0 / dx, 1.0 / dy, 1.0 / dz
        best = np.inf
        bf = -1
        stack[0] = 0
        sp = 1
        while sp > 0:
            sp -= 1
            node = stack[sp]
            tx0 = (boxes[node, 0] - ox) * ix
            tx1 = (boxes[node, 3] - ox) * ix
            if tx0 > tx1:
                tx0, tx1 = tx1, tx0
            ty0 = (boxes[node, 1] - oy) * iy
            ty1 = (boxes[node, 4] - oy) * iy
            if ty0 > ty1:
                ty0, ty1 = ty1, ty0
            tz0 = (boxes[node, 2] - oz) * iz
            tz1 = (boxes[node, 5] - oz) * iz
            if tz0 > tz1:
                tz0, tz1 = tz1, tz0
            tmin = max(tx0, max(ty0, tz0))
            tmax = min(tx1, min(ty1, tz1))
            if tmax < tmin or tmax < 0.0 or tmin > best:  # NaN (0 * inf on a box face) never skips
                continue
            cnt = nodes[node, 3]
            if cnt > 0:
                first = nodes[node, 2]
                for k in range(first, first + cnt):
                    e1x, e1y, e1z = tris[k, 3], tris[k, 4], tris[k, 5]
                    e2x, e2y, e2z = tris[k, 6], tris[k, 7], tris[k, 8]
                    px = dy * e2z - dz * e2y
                    py = dz * e2x - dx * e2z
                    pz = dx * e2y - dy * e2x
                    det = e1x * px + e1y * py + e1z * pz
                    if det == 0.0:
                        continue
                    inv = 1.0 / det
                    sx, sy, sz = ox - tris[k, 0], oy - tris[k, 1], oz - tris[k, 2]
                    u = (sx * px + sy * py + sz * pz) * inv
                    if u < 0.0 or u > 1.0:
                        continue
                    qx = sy * e1z - sz * e1y
                    qy = sz * e1x - sx * e1z
                    qz = sx * e1y - sy * e1x
                    v = (dx * qx + dy * qy + dz * qz) * inv
                    if v < 0.0 or u + v > 1.0:
                        continue
                    t = (e2x * qx + e2y * qy + e2z * qz) * inv
                    if t > 0.0 and t < best:
                        best = t
                        bf = order[k]
            elif sp + 2 <= _STACK:
                stack[sp] = nodes[node, 0]
                stack[sp + 1] = nodes[node, 1]
                sp += 2
        face[r] = bf
        dist[r] = best
    return face, dist
