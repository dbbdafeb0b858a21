"""Shapes that bound a homogeneous medium: half-space, slab, sphere, axis-aligned box and closed triangle meshes.

Every shape is reduced to a :class:`Geometry` record of plain arrays for the numba kernels:
``kind`` (one of :data:`HALF_SPACE`, :data:`SLAB`, :data:`SPHERE`, :data:`BOX`, :data:`MESH`), float ``params``,
and for meshes a bounding-volume hierarchy (binned SAH, leaves of <= 4 triangles, :mod:`.bvh`)
built in numba and traversed by :func:`nearest_hit` in numba (no trimesh/embree call inside the walk).

:func:`nearest_hit` is the one query the kernels need: the first crossing of the boundary along a ray with
t > eps_t, from inside or outside, with the *outward* unit normal there (:func:`nearest_hit_below`: the same when
only crossings before a free flight's end matter; a mesh's BVH is then pruned there). Positions are nudged by ``nudge`` along
the normal after a boundary event so that the next query does not find the same crossing again.

Conventions: millimetres; the half-space is z <= top_z_mm (surface normal +z) and the slab
top_z_mm - thickness_mm <= z <= top_z_mm, so a camera or light above z = top_z_mm sees the surface.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, NamedTuple, Union

import numpy as np
import numpy.typing as npt
from numba import njit

from .bvh import build_bvh

__all__ = ["HALF_SPACE", "SLAB", "SPHERE", "BOX", "MESH", "Geometry", "HalfSpace", "Slab", "Sphere", "Box",
           "Mesh", "Shape", "nearest_hit", "surface_distance", "convex_polyhedron", "convex_face_table",
           "FACE_TABLE_START", "STACK_SIZE", "plane_table", "MAX_CONNECTION_PLANES", "PLANE_TABLE", "BVH_CONNECTIONS",
           "refracted_point_lights_supported"]

HALF_SPACE, SLAB, SPHERE, BOX, MESH = 0, 1, 2, 3, 4
STACK_SIZE = 64
_INF = math.inf

FloatArray = npt.NDArray[np.float64]


class Geometry(NamedTuple):
    """Arrays describing one shape to the kernels (see module docstring)."""

    kind: int
    params: FloatArray          # (8,); convex meshes: (8 + ...,) the face table of :func:`convex_face_table`
    nodes_box: FloatArray       # (N, 6) min xyz, max xyz (meshes; (1, 6) dummy otherwise)
    nodes_idx: npt.NDArray[np.int64]  # (N, 4) left, right, first triangle (inner: split axis), count (> 0: leaf)
    triangles: FloatArray       # (M, 12) v0, e1 = v1 - v0, e2 = v2 - v0, outward unit normal
    eps_t: float                # minimum hit distance
    nudge: float                # offset along the normal after a boundary event
    convex: bool                # a ray leaving the medium never re-enters it
    scale_mm: float             # size and distance from the origin (sets eps_t = 1e-12 and nudge = 1e-9 of it)


def _dummy_bvh() -> tuple[FloatArray, npt.NDArray[np.int64], FloatArray]:
    return np.zeros((1, 6)), np.zeros((1, 4), dtype=np.int64), np.zeros((1, 12))


def _geometry(kind: int, params: list[float] | FloatArray, scale: float, convex: bool = True,
              bvh: tuple[FloatArray, npt.NDArray[np.int64], FloatArray] | None = None) -> Geometry:
    p = np.zeros(max(8, len(params)))
    p[:len(params)] = params
    nb, ni, tr = bvh if bvh is not None else _dummy_bvh()
    scale = max(1.0, float(scale))
    return Geometry(kind, p, nb, ni, tr, 1e-12 * scale, 1e-9 * scale, convex, scale)


@dataclass(frozen=True)
class HalfSpace:
    """The medium z <= top_z_mm (surface normal +z)."""

    top_z_mm: float = 0.0

    def geometry(self) -> Geometry:
        return _geometry(HALF_SPACE, [self.top_z_mm], abs(self.top_z_mm))

    def contains(self, points_mm: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        return np.asarray(points_mm, float)[..., 2] <= self.top_z_mm


@dataclass(frozen=True)
class Slab:
    """The medium top_z_mm - thickness_mm <= z <= top_z_mm (an infinite plane-parallel layer)."""

    thickness_mm: float
    top_z_mm: float = 0.0

    def __post_init__(self) -> None:
        if not self.thickness_mm > 0:
            raise ValueError("thickness_mm must be > 0")

    @property
    def bottom_z_mm(self) -> float:
        return self.top_z_mm - self.thickness_mm

    def geometry(self) -> Geometry:
        return _geometry(SLAB, [self.top_z_mm, self.bottom_z_mm],
                         max(abs(self.top_z_mm), abs(self.bottom_z_mm), self.thickness_mm))

    def contains(self, points_mm: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        z = np.asarray(points_mm, float)[..., 2]
        return (z <= self.top_z_mm) & (z >= self.bottom_z_mm)


@dataclass(frozen=True)
class Sphere:
    center_mm: tuple[float, float, float]
    radius_mm: float

    def __post_init__(self) -> None:
        if not self.radius_mm > 0:
            raise ValueError("radius_mm must be > 0")

    def geometry(self) -> Geometry:
        c = [float(v) for v in self.center_mm]
        return _geometry(SPHERE, c + [float(self.radius_mm)], self.radius_mm + max(abs(v) for v in c))

    def contains(self, points_mm: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        d = np.asarray(points_mm, float) - np.asarray(self.center_mm, float)
        return np.sum(d * d, axis=-1) <= self.radius_mm ** 2


@dataclass(frozen=True)
class Box:
    """Axis-aligned box [min_mm, max_mm]."""

    min_mm: tuple[float, float, float]
    max_mm: tuple[float, float, float]

    def __post_init__(self) -> None:
        if not np.all(np.asarray(self.max_mm, float) > np.asarray(self.min_mm, float)):
            raise ValueError("max_mm must exceed min_mm on every axis")

    def geometry(self) -> Geometry:
        lo = [float(v) for v in self.min_mm]
        hi = [float(v) for v in self.max_mm]
        return _geometry(BOX, lo + hi, max(abs(v) for v in lo + hi))

    def contains(self, points_mm: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        p = np.asarray(points_mm, float)
        return np.all((p >= np.asarray(self.min_mm)) & (p <= np.asarray(self.max_mm)), axis=-1)


def _unit_face_normals(vertices: npt.ArrayLike, faces: npt.ArrayLike
                       ) -> tuple[FloatArray, npt.NDArray[np.int64], npt.NDArray[np.int64], FloatArray, float]:
    """(vertices, faces, indices of the non-degenerate faces, their outward unit normals, bounding-box diagonal);
    a face is degenerate when twice its area is below 1e-12 diagonal^2."""
    v = np.asarray(vertices, float)
    f = np.asarray(faces, dtype=np.int64)
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(n, axis=1)
    diag = float(np.linalg.norm(np.ptp(v, axis=0)))
    keep = np.flatnonzero(area2 > 1e-12 * max(diag, 1e-300) ** 2)
    return v, f, keep, n[keep] / area2[keep, None], diag


def convex_polyhedron(vertices: npt.ArrayLike, faces: npt.ArrayLike, rel_tol: float = 1e-6) -> bool:
    """True when every vertex lies on the inner side of every (non-degenerate) face plane, within ``rel_tol``
    times the bounding-box diagonal, for outward-wound ``faces``: the closed mesh then bounds the intersection of
    its faces' inner half-spaces (a convex polyhedron). This is the property the refracted point-light connections
    of :mod:`.nee` rely on (a face that faces the light sees it unoccluded from outside and every interior point
    unoccluded from inside). Cost O(faces x vertices), in chunks; stops at the first violating chunk."""
    v, f, keep, n, diag = _unit_face_normals(vertices, faces)
    if not keep.size:
        return False
    off = np.einsum("ij,ij->i", n, v[f[keep, 0]])
    tol = rel_tol * diag
    chunk = max(1, 1_000_000 // max(1, len(v)))
    for s in range(0, len(n), chunk):
        if float((v @ n[s:s + chunk].T - off[s:s + chunk]).max()) > tol:
            return False
    return True


FACE_TABLE_START = 8  # params[0] = number of faces; face records from params[8] on


def _hull_2d(q: FloatArray) -> npt.NDArray[np.int64]:
    """Indices of the 2-D convex hull of points q (K, 2), counter-clockwise, collinear points dropped (Andrew's
    monotone chain)."""
    order = np.lexsort((q[:, 1], q[:, 0]))

    def cross(o: int, a: int, b: int) -> float:
        return float((q[a, 0] - q[o, 0]) * (q[b, 1] - q[o, 1]) - (q[a, 1] - q[o, 1]) * (q[b, 0] - q[o, 0]))

    lower: list[int] = []
    for i in order:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], i) <= 0:
            lower.pop()
        lower.append(int(i))
    upper: list[int] = []
    for i in order[::-1]:
        while len(upper) >= 2 and cross(upper[-2], upper[-1], i) <= 0:
            upper.pop()
        upper.append(int(i))
    return np.asarray(lower[:-1] + upper[:-1], dtype=np.int64)


def convex_face_table(vertices: npt.ArrayLike, faces: npt.ArrayLike, normal_tol: float = 1e-6) -> FloatArray:
    """The flat faces of a convex polyhedron (outward-wound triangles ``faces``) packed for the kernels.

    Triangles whose outward unit normals agree within ``normal_tol`` form one face (a convex polyhedron has one
    face per outward normal). A face is stored as its unit normal n, offset c = n.p of its plane, a point p0 on it,
    and its boundary as the 2-D convex hull of its vertices in the plane: edges (m, d) with in-plane inward unit
    normal m, inside iff m.q >= d. Layout (floats): [F, 0 x 7, then per face: nx, ny, nz, c, p0x, p0y, p0z,
    n_edges, then per edge: mx, my, mz, d]. Degenerate triangles (zero area) are ignored."""
    v, f, keep, nrm, _ = _unit_face_normals(vertices, faces)
    label = np.full(len(keep), -1, dtype=np.int64)
    groups: list[npt.NDArray[np.int64]] = []
    for i in range(len(keep)):
        if label[i] >= 0:
            continue
        same = np.flatnonzero((label < 0) & (np.linalg.norm(nrm - nrm[i], axis=1) <= normal_tol))
        label[same] = len(groups)
        groups.append(same)
    out: list[float] = [float(len(groups))] + [0.0] * (FACE_TABLE_START - 1)
    for g in groups:
        n = nrm[g].mean(axis=0)
        n /= np.linalg.norm(n)
        idx = np.unique(f[keep[g]].ravel())
        pts = v[idx]
        c = float(np.mean(pts @ n))
        p0 = pts.mean(axis=0)
        p0 = p0 + (c - float(p0 @ n)) * n
        a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(n, a)
        q = np.stack([(pts - p0) @ a, (pts - p0) @ b], axis=1)
        hull = _hull_2d(q)
        out += [*n, c, *p0, float(len(hull))]
        for k in range(len(hull)):
            q0, q1 = q[hull[k]], q[hull[(k + 1) % len(hull)]]
            t = q1 - q0
            m2 = np.array([-t[1], t[0]]) / np.linalg.norm(t)    # left of a counter-clockwise edge: inside
            m = m2[0] * a + m2[1] * b
            out += [*m, float(m2 @ q0 + m @ p0)]
    return np.asarray(out, dtype=np.float64)


#: params[1] of a mesh's Geometry: 0 = convex face table (or none), PLANE_TABLE = the distinct face planes of a
#: non-convex mesh (:func:`plane_table`), BVH_CONNECTIONS = non-convex with more than MAX_CONNECTION_PLANES planes
#: (refracted connections from candidate triangles found by the BVH, :func:`simulators.mc.nee.bvh_mesh_connections`)
PLANE_TABLE, BVH_CONNECTIONS = 1.0, -1.0
NO_PLANE_TABLE = BVH_CONNECTIONS       # the former name (before issue 17's BVH connections)
#: refracted point-light connections through a non-convex mesh of at most this many distinct face planes try
#: every plane (:func:`simulators.mc.nee.nonconvex_mesh_connections`); beyond it (a scanned mesh: one plane per
#: triangle) the candidates are the triangles near the scattering vertex, found by the BVH
MAX_CONNECTION_PLANES: int = 512


def plane_table(vertices: npt.ArrayLike, faces: npt.ArrayLike, normal_tol: float = 1e-6, offset_rel_tol: float = 1e-6,
                max_planes: int = MAX_CONNECTION_PLANES) -> FloatArray | None:
    """The distinct planes of a (non-convex) mesh's faces, in the layout of :func:`convex_face_table` with no edges
    (each record: nx, ny, nz, c, p0x, p0y, p0z, 0) and params[1] = :data:`PLANE_TABLE`; None when there are more
    than ``max_planes``. Triangles join the first plane whose unit normal agrees within ``normal_tol`` and offset
    within ``offset_rel_tol`` x the bounding-box diagonal (greedy, so two planes' normals or offsets always differ
    by more than that: a connection point b is found on one plane only). Used by
    :func:`simulators.mc.nee.nonconvex_mesh_connections`, which finds the face that holds b by a ray cast."""
    v, f, keep, nrm, diag = _unit_face_normals(vertices, faces)
    off = np.einsum("ij,ij->i", nrm, v[f[keep, 0]])
    # a cheap upper bound first (rounding only splits planes): skip the greedy pass for scanned meshes
    coarse = np.unique(np.round(np.c_[nrm / (100 * normal_tol), off / (100 * offset_rel_tol * diag)]), axis=0)
    if len(coarse) > 8 * max_planes:
        return None
    label = np.full(len(keep), -1, dtype=np.int64)
    out: list[float] = [0.0, PLANE_TABLE] + [0.0] * (FACE_TABLE_START - 2)
    n_planes = 0
    for i in range(len(keep)):
        if label[i] >= 0:
            continue
        same = np.flatnonzero((label < 0) & (np.linalg.norm(nrm - nrm[i], axis=1) <= normal_tol)
                              & (np.abs(off - off[i]) <= offset_rel_tol * diag))
        label[same] = n_planes
        n_planes += 1
        if n_planes > max_planes:
            return None
        n = nrm[same].mean(axis=0)
        n /= np.linalg.norm(n)
        pts = v[np.unique(f[keep[same]].ravel())]
        c = float(np.mean(pts @ n))
        p0 = pts.mean(axis=0)
        p0 = p0 + (c - float(p0 @ n)) * n
        out += [*n, c, *p0, 0.0]
    out[0] = float(n_planes)
    return np.asarray(out, dtype=np.float64)


def refracted_point_lights_supported(geometry: Geometry) -> bool:
    """Can :func:`simulators.mc.render` connect point lights through this shape's boundary at eta != 1? Every
    shape since issue 17: analytic shapes, convex meshes (face table), non-convex meshes of at most
    :data:`MAX_CONNECTION_PLANES` face planes (plane table) and larger ones (:data:`BVH_CONNECTIONS`)."""
    return geometry.kind != MESH or geometry.convex or geometry.params[1] in (PLANE_TABLE, BVH_CONNECTIONS)


@dataclass(frozen=True)
class Mesh:
    """A closed (watertight) triangle mesh; face winding gives the outward normals (inverted if the signed volume
    is negative). Needs ``trimesh`` only to read the mesh; ray queries use this module's BVH. ``geometry().convex``
    is trimesh's ``is_convex`` and :func:`convex_polyhedron`; a convex mesh's ``params`` hold its flat faces
    (:func:`convex_face_table`) for the refracted point-light connections, a non-convex one's its distinct face
    planes (:func:`plane_table`; point lights with eta != 1 need it, :func:`refracted_point_lights_supported`)."""

    mesh: Any  # trimesh.Trimesh
    leaf_size: int = 4
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not bool(self.mesh.is_watertight):
            raise ValueError("the mesh must be watertight (closed) to bound a medium")

    def geometry(self) -> Geometry:
        if "g" not in self._cache:
            v = np.asarray(self.mesh.vertices, float)
            f = np.asarray(self.mesh.faces, dtype=np.int64)
            if float(self.mesh.volume) < 0:
                f = f[:, ::-1]
            bvh = build_bvh(v, f, self.leaf_size)
            scale = float(np.abs(v).max() + np.ptp(v, axis=0).max())
            convex = bool(self.mesh.is_convex) and convex_polyhedron(v, f)
            if convex:
                prm = convex_face_table(v, f)
            else:
                table = plane_table(v, f)
                prm = table if table is not None else [0.0, BVH_CONNECTIONS]
            self._cache["g"] = _geometry(MESH, prm, scale, convex, bvh)
        return self._cache["g"]

    def contains(self, points_mm: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        """Inside test by the parity of boundary crossings along a fixed oblique ray (this module's BVH)."""
        g = self.geometry()
        p = np.atleast_2d(np.asarray(points_mm, float)).reshape(-1, 3)
        d = np.array([0.5773, 0.5774, 0.5775])
        d /= np.linalg.norm(d)
        stack = np.empty(STACK_SIZE, np.int64)
        out = np.zeros(len(p), dtype=bool)
        for i, q in enumerate(p):
            o = q.copy()
            n = 0
            while n < 10_000:
                t, *_ = nearest_hit(g.kind, g.params, g.nodes_box, g.nodes_idx, g.triangles, *o, *d, g.eps_t, stack)
                if t == _INF:
                    break
                n += 1
                o = o + (t + g.nudge) * d
            out[i] = n % 2 == 1
        return out


Shape = Union[HalfSpace, Slab, Sphere, Box, Mesh]


# ------------------------------------------------------------------------------------------------ numba queries
@njit(cache=True, error_model="numpy")
def _hit_sphere(prm, ox, oy, oz, dx, dy, dz, eps_t):
    cx, cy, cz, r = prm[0], prm[1], prm[2], prm[3]
    px, py, pz = ox - cx, oy - cy, oz - cz
    b = px * dx + py * dy + pz * dz
    c = px * px + py * py + pz * pz - r * r
    disc = b * b - c
    if disc < 0.0:
        return _INF, 0.0, 0.0, 0.0
    sq = math.sqrt(disc)
    q = -(b + sq) if b > 0.0 else -(b - sq)  # stable roots q and c/q
    t1 = q
    t2 = c / q if q != 0.0 else 0.0
    if t1 > t2:
        t1, t2 = t2, t1
    t = t1 if t1 > eps_t else t2
    if not t > eps_t:
        return _INF, 0.0, 0.0, 0.0
    inv = 1.0 / r
    return t, (px + t * dx) * inv, (py + t * dy) * inv, (pz + t * dz) * inv


@njit(cache=True, error_model="numpy")
def _hit_box(prm, ox, oy, oz, dx, dy, dz, eps_t):
    o = (ox, oy, oz)
    d = (dx, dy, dz)
    t_near = -_INF
    t_far = _INF
    ax_near = -1
    ax_far = -1
    s_near = 0.0
    s_far = 0.0
    for a in range(3):
        lo = prm[a]
        hi = prm[3 + a]
        if d[a] == 0.0:
            if o[a] < lo or o[a] > hi:
                return _INF, 0.0, 0.0, 0.0
            continue
        inv = 1.0 / d[a]
        t0 = (lo - o[a]) * inv
        t1 = (hi - o[a]) * inv
        # entering through lo when d > 0 (outward normal -e_a), through hi when d < 0 (+e_a)
        if t0 < t1:
            if t0 > t_near:
                t_near, ax_near, s_near = t0, a, -1.0
            if t1 < t_far:
                t_far, ax_far, s_far = t1, a, 1.0
        else:
            if t1 > t_near:
                t_near, ax_near, s_near = t1, a, 1.0
            if t0 < t_far:
                t_far, ax_far, s_far = t0, a, -1.0
    if t_near > t_far:
        return _INF, 0.0, 0.0, 0.0
    if t_near > eps_t and ax_near >= 0:
        t, a, s = t_near, ax_near, s_near
    elif t_far > eps_t and ax_far >= 0:
        t, a, s = t_far, ax_far, s_far
    else:
        return _INF, 0.0, 0.0, 0.0
    n0 = s if a == 0 else 0.0
    n1 = s if a == 1 else 0.0
    n2 = s if a == 2 else 0.0
    return t, n0, n1, n2


@njit(cache=True, error_model="numpy")
def _hit_mesh(nbox, nidx, tris, ox, oy, oz, dx, dy, dz, eps_t, stack):
    return _hit_mesh_below(nbox, nidx, tris, ox, oy, oz, dx, dy, dz, eps_t, stack, _INF)


@njit(cache=True, error_model="numpy")
def _hit_mesh_below(nbox, nidx, tris, ox, oy, oz, dx, dy, dz, eps_t, stack, t_max):
    """The BVH query of :func:`_hit_mesh` for crossings with t < ``t_max`` only (inf if none): nodes whose box is
    entered beyond ``t_max`` are never opened, so a short free flight deep inside a large mesh costs a few box
    tests instead of a descent to the far surface. The nearest crossing below ``t_max`` is the same (same
    triangles, same arithmetic) as the unbounded query's."""
    ix = 1.0 / dx
    iy = 1.0 / dy
    iz = 1.0 / dz
    best = t_max
    found = False
    bn0 = 0.0
    bn1 = 0.0
    bn2 = 0.0
    sp = 0
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        node = stack[sp]
        # slab test against the node box
        tx0 = (nbox[node, 0] - ox) * ix
        tx1 = (nbox[node, 3] - ox) * ix
        if tx0 > tx1:
            tx0, tx1 = tx1, tx0
        ty0 = (nbox[node, 1] - oy) * iy
        ty1 = (nbox[node, 4] - oy) * iy
        if ty0 > ty1:
            ty0, ty1 = ty1, ty0
        tz0 = (nbox[node, 2] - oz) * iz
        tz1 = (nbox[node, 5] - oz) * iz
        if tz0 > tz1:
            tz0, tz1 = tz1, tz0
        tmin = max(tx0, max(ty0, tz0))
        tmax = min(tx1, min(ty1, tz1))
        if tmax < tmin or tmax < eps_t or tmin > best:  # NaN (0 * inf) never skips
            continue
        cnt = nidx[node, 3]
        if cnt > 0:
            first = nidx[node, 2]
            for k in range(first, first + cnt):
                # Moller-Trumbore
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
                if t > eps_t and t < best:
                    best = t
                    found = True
                    bn0, bn1, bn2 = tris[k, 9], tris[k, 10], tris[k, 11]
        else:
            if sp + 2 <= stack.shape[0]:
                # the child nearer along the split axis is popped first: its hits shrink ``best`` early
                ax = nidx[node, 2]
                dax = dx if ax == 0 else (dy if ax == 1 else dz)
                if dax < 0.0:
                    stack[sp] = nidx[node, 0]
                    stack[sp + 1] = nidx[node, 1]
                else:
                    stack[sp] = nidx[node, 1]
                    stack[sp + 1] = nidx[node, 0]
                sp += 2
    if not found:
        return _INF, 0.0, 0.0, 0.0
    return best, bn0, bn1, bn2


@njit(cache=True, error_model="numpy")
def nearest_hit(kind, prm, nbox, nidx, tris, ox, oy, oz, dx, dy, dz, eps_t, stack):
    """First boundary crossing along the ray o + t d with t > eps_t: (t, outward normal); t = inf if none."""
    if kind == HALF_SPACE:
        if dz == 0.0:
            return _INF, 0.0, 0.0, 0.0
        t = (prm[0] - oz) / dz
        if t > eps_t:
            return t, 0.0, 0.0, 1.0
        return _INF, 0.0, 0.0, 0.0
    if kind == SLAB:
        if dz == 0.0:
            return _INF, 0.0, 0.0, 0.0
        t_top = (prm[0] - oz) / dz
        t_bot = (prm[1] - oz) / dz
        best = _INF
        nz = 0.0
        if t_top > eps_t:
            best, nz = t_top, 1.0
        if t_bot > eps_t and t_bot < best:
            best, nz = t_bot, -1.0
        return best, 0.0, 0.0, nz
    if kind == SPHERE:
        return _hit_sphere(prm, ox, oy, oz, dx, dy, dz, eps_t)
    if kind == BOX:
        return _hit_box(prm, ox, oy, oz, dx, dy, dz, eps_t)
    return _hit_mesh(nbox, nidx, tris, ox, oy, oz, dx, dy, dz, eps_t, stack)


@njit(cache=True, error_model="numpy")
def nearest_hit_below(kind, prm, nbox, nidx, tris, ox, oy, oz, dx, dy, dz, eps_t, stack, t_max):
    """:func:`nearest_hit` when only crossings closer than ``t_max`` matter (a free flight of length t_max): the
    same crossing when it is closer than ``t_max``, else possibly (meshes: always) t = inf. Analytic shapes answer
    exactly as :func:`nearest_hit`; meshes prune the BVH at ``t_max`` (:func:`_hit_mesh_below`)."""
    if kind == MESH:
        return _hit_mesh_below(nbox, nidx, tris, ox, oy, oz, dx, dy, dz, eps_t, stack, t_max)
    return nearest_hit(kind, prm, nbox, nidx, tris, ox, oy, oz, dx, dy, dz, eps_t, stack)


@njit(cache=True, error_model="numpy")
def surface_distance(kind, prm, x, y, z):
    """A lower bound on the distance from an interior point to the boundary (0 when unknown: meshes)."""
    if kind == HALF_SPACE:
        return max(0.0, prm[0] - z)
    if kind == SLAB:
        return max(0.0, min(prm[0] - z, z - prm[1]))
    if kind == SPHERE:
        dx, dy, dz = x - prm[0], y - prm[1], z - prm[2]
        return max(0.0, prm[3] - math.sqrt(dx * dx + dy * dy + dz * dz))
    if kind == BOX:
        m = min(x - prm[0], prm[3] - x)
        m = min(m, min(y - prm[1], prm[4] - y))
        m = min(m, min(z - prm[2], prm[5] - z))
        return max(0.0, m)
    return 0.0
