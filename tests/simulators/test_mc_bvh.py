"""The mesh BVH of simulators.mc (issue 19: binned SAH build, near-child-first traversal).

Checks: (1) structure on the relief slab of benchmarks/mc_vs_mitsuba.py, a subdivided icosphere and a scanned-like
noisy sphere: every triangle in exactly one leaf, every node box holds its children's boxes / its triangles, depth
small enough for the traversal stacks; (2) the ray queries against brute force over all triangles (Moller-Trumbore
on every triangle): nearest_hit (unbounded) and nearest_hit_below (bounded by a free flight) give the same t and
the same normal at random rays from inside, from just below the surface and from outside; (3) the SAH split keeps
the relief's top surface apart from its 5 mm tall side walls and bottom fan (the median split mixed them: leaf
boxes spanned the slab's depth).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from simulators.mc import Mesh
from simulators.mc.bvh import MAX_SAH_DEPTH, build_bvh
from simulators.mc.shapes import STACK_SIZE, nearest_hit, nearest_hit_below


def _relief() -> trimesh.Trimesh:
    from simulators.mc_capture import relief_mesh
    from simulators.scene import BumpySlabObject
    obj = BumpySlabObject((0.0, 0.0, 0.0), (0.74, 0.88, 1.01), (0.032, 0.17, 0.48), 1.3, normal=(0.0, 0.0, 1.0),
                          extent_mm=20.0, patch_mm=0.5)
    return relief_mesh(obj, 0.5, 5.0)


def _noisy_sphere() -> trimesh.Trimesh:
    m = trimesh.creation.icosphere(subdivisions=4, radius=5.0)
    rng = np.random.default_rng(4)
    v = m.vertices * (1.0 + 0.05 * rng.standard_normal((len(m.vertices), 1)))
    return trimesh.Trimesh(v, m.faces, process=False)


MESHES = {"relief": _relief, "icosphere": lambda: trimesh.creation.icosphere(subdivisions=3, radius=5.0),
          "noisy_sphere": _noisy_sphere}


def _depths(idx: np.ndarray) -> np.ndarray:
    depth = np.zeros(len(idx), dtype=np.int64)
    for i in range(len(idx)):                 # children always come after their parent
        if idx[i, 3] == 0:
            depth[idx[i, 0]] = depth[i] + 1
            depth[idx[i, 1]] = depth[i] + 1
    return depth


@pytest.mark.parametrize("name", sorted(MESHES))
def test_structure(name: str) -> None:
    m = MESHES[name]()
    boxes, idx, tris = build_bvh(m.vertices, m.faces)
    assert len(tris) == len(m.faces)
    leaf = idx[:, 3] > 0
    cover = np.zeros(len(tris), dtype=np.int64)
    for i in np.flatnonzero(leaf):
        s, n = idx[i, 2], idx[i, 3]
        assert n <= 4
        cover[s:s + n] += 1
        v = np.concatenate([tris[s:s + n, 0:3], tris[s:s + n, 0:3] + tris[s:s + n, 3:6],
                            tris[s:s + n, 0:3] + tris[s:s + n, 6:9]])
        assert np.all(v >= boxes[i, :3] - 1e-12) and np.all(v <= boxes[i, 3:] + 1e-12)
    assert np.all(cover == 1)
    for i in np.flatnonzero(~leaf):
        for c in idx[i, :2]:
            assert c > i
            assert np.all(boxes[c, :3] >= boxes[i, :3]) and np.all(boxes[c, 3:] <= boxes[i, 3:])
        assert 0 <= idx[i, 2] <= 2
    depth = _depths(idx).max()
    assert depth <= MAX_SAH_DEPTH + math.ceil(math.log2(len(tris))) and depth + 2 <= STACK_SIZE // 2


def _brute(tris: np.ndarray, o: np.ndarray, d: np.ndarray, eps: float, t_max: float) -> tuple[float, np.ndarray]:
    v0, e1, e2, nrm = tris[:, 0:3], tris[:, 3:6], tris[:, 6:9], tris[:, 9:12]
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = o - v0
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        v = (q @ d) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
    ok = (det != 0) & (u >= 0) & (u <= 1) & (v >= 0) & (u + v <= 1) & (t > eps) & (t < t_max)
    if not ok.any():
        return math.inf, np.zeros(3)
    k = np.flatnonzero(ok)[np.argmin(t[ok])]
    return float(t[k]), nrm[k]


@pytest.mark.parametrize("name", sorted(MESHES))
def test_queries_equal_brute_force(name: str) -> None:
    geo = Mesh(MESHES[name]()).geometry()
    tris = geo.triangles
    rng = np.random.default_rng(11)
    stack = np.empty(STACK_SIZE, np.int64)
    lo, hi = tris[:, 0:3].min(axis=0), tris[:, 0:3].max(axis=0)
    n = 250
    # origins: uniform in the padded box (inside and outside), and just below random surface points
    k = rng.integers(0, len(tris), n)
    a, b = rng.random(n), rng.random(n)
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    surf = tris[k, 0:3] + a[:, None] * tris[k, 3:6] + b[:, None] * tris[k, 6:9] - 1e3 * geo.nudge * tris[k, 9:12]
    origins = np.concatenate([rng.uniform(lo - 2.0, hi + 2.0, (n, 3)), surf])
    dirs = rng.standard_normal((2 * n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    flights = rng.exponential(2.0, 2 * n)
    hits = 0
    for o, d, s in zip(origins, dirs, flights):
        for t_max in (math.inf, s):
            t_ref, n_ref = _brute(tris, o, d, geo.eps_t, t_max)
            if t_max == math.inf:
                t, *nrm = nearest_hit(geo.kind, geo.params, geo.nodes_box, geo.nodes_idx, tris, *o, *d, geo.eps_t,
                                      stack)
            else:
                t, *nrm = nearest_hit_below(geo.kind, geo.params, geo.nodes_box, geo.nodes_idx, tris, *o, *d,
                                            geo.eps_t, stack, t_max)
            if t_ref == math.inf:
                assert t == math.inf
            else:
                hits += 1
                assert t == pytest.approx(t_ref, rel=1e-12, abs=1e-12)
                assert np.allclose(nrm, n_ref, atol=1e-12)
    assert hits > n            # the rays do meet the mesh


def test_relief_top_kept_apart_from_walls_and_bottom() -> None:
    m = _relief()
    boxes, idx, tris = build_bvh(m.vertices, m.faces)
    leaf = idx[:, 3] > 0
    z = np.stack([tris[:, 2], tris[:, 2] + tris[:, 5], tris[:, 2] + tris[:, 8]], axis=1)
    top = np.all(z > -2.0, axis=1)           # relief heights are ~0.1-0.5 mm; walls reach -5 mm
    mixed = 0
    for i in np.flatnonzero(leaf):
        s, n = idx[i, 2], idx[i, 3]
        if top[s:s + n].any() and not top[s:s + n].all():
            mixed += 1
    # a leaf mixing the top relief with a wall or fan triangle spans the slab's depth
    assert mixed <= 0.02 * leaf.sum()
