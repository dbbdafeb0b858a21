"""Bounding-volume hierarchy over a mesh's triangles for the numba ray queries of :mod:`.shapes` (issue 19: a
binned surface-area-heuristic build replaces the median split).

Layout (unchanged for the kernels): ``nodes_box`` (N, 6) min xyz, max xyz; ``nodes_idx`` (N, 4) left child, right
child, first triangle, triangle count (count > 0: a leaf owning triangles [first, first + count)); an inner node
stores its split axis in column 2 (the left child holds the smaller centroids along it, so a traversal pops the
child nearer along the ray first); ``triangles`` (M, 12) v0, e1 = v1 - v0, e2 = v2 - v0, outward unit normal, in
leaf order. Node 0 is the root.

Split choice: centroids binned into ``_BINS`` bins per axis, the split minimizing the surface-area heuristic
A_left N_left + A_right N_right (MacDonald & Booth 1990; binned as in Wald 2007, "On fast construction of
SAH-based bounding volume hierarchies"). Why: the median split on the longest centroid axis put the relief slab's
bottom fan and side walls (5 mm tall) into the same nodes as its top relief, so boxes near the top surface spanned
the slab's depth and a short flight near the surface opened many of them (docs/monte-carlo.md). Depth is capped at
:data:`MAX_SAH_DEPTH` (below it, median splits: depth stays logarithmic), so a traversal's stack of
``STACK_SIZE`` // 2 entries (the connection kernels halve it) never overflows.
"""
from __future__ import annotations

import numpy as np
import numpy.typing as npt
from numba import njit

__all__ = ["build_bvh", "MAX_SAH_DEPTH"]

FloatArray = npt.NDArray[np.float64]

_BINS = 16
#: nodes deeper than this split at the median (depth <= MAX_SAH_DEPTH + log2(M / leaf_size))
MAX_SAH_DEPTH = 12


@njit(cache=True)
def _area(lo0, lo1, lo2, hi0, hi1, hi2):
    a, b, c = hi0 - lo0, hi1 - lo1, hi2 - lo2
    if a < 0.0:
        return 0.0
    return a * b + b * c + c * a


@njit(cache=True)
def _build(lo_t, hi_t, cent, leaf_size):
    m = lo_t.shape[0]
    order = np.arange(m)
    cap = 2 * m + 1
    boxes = np.zeros((cap, 6))
    idx = np.zeros((cap, 4), dtype=np.int64)
    st_node = np.zeros(cap, dtype=np.int64)
    st_s = np.zeros(cap, dtype=np.int64)
    st_e = np.zeros(cap, dtype=np.int64)
    st_d = np.zeros(cap, dtype=np.int64)
    st_node[0], st_s[0], st_e[0], st_d[0] = 0, 0, m, 0
    sp = 1
    n_nodes = 1
    bin_box = np.empty((_BINS, 6))
    bin_cnt = np.zeros(_BINS, dtype=np.int64)
    right_area = np.zeros(_BINS)
    right_cnt = np.zeros(_BINS, dtype=np.int64)
    key = np.empty(m)
    while sp > 0:
        sp -= 1
        node, s, e, depth = st_node[sp], st_s[sp], st_e[sp], st_d[sp]
        blo = np.full(3, np.inf)
        bhi = np.full(3, -np.inf)
        clo = np.full(3, np.inf)
        chi = np.full(3, -np.inf)
        for i in range(s, e):
            t = order[i]
            for a in range(3):
                blo[a] = min(blo[a], lo_t[t, a])
                bhi[a] = max(bhi[a], hi_t[t, a])
                clo[a] = min(clo[a], cent[t, a])
                chi[a] = max(chi[a], cent[t, a])
        for a in range(3):
            boxes[node, a] = blo[a]
            boxes[node, 3 + a] = bhi[a]
        n = e - s
        if n <= leaf_size:
            idx[node, 0], idx[node, 1], idx[node, 2], idx[node, 3] = -1, -1, s, n
            continue
        best_cost = np.inf
        best_axis = -1
        best_bin = -1
        if depth < MAX_SAH_DEPTH:
            for a in range(3):
                ext = chi[a] - clo[a]
                if not ext > 0.0:
                    continue
                scale = _BINS / ext
                for b in range(_BINS):
                    bin_cnt[b] = 0
                    for q in range(3):
                        bin_box[b, q] = np.inf
                        bin_box[b, 3 + q] = -np.inf
                for i in range(s, e):
                    t = order[i]
                    b = min(_BINS - 1, int((cent[t, a] - clo[a]) * scale))
                    bin_cnt[b] += 1
                    for q in range(3):
                        bin_box[b, q] = min(bin_box[b, q], lo_t[t, q])
                        bin_box[b, 3 + q] = max(bin_box[b, 3 + q], hi_t[t, q])
                # right sweep: area and count of bins b.._BINS-1
                r0, r1, r2, r3, r4, r5 = np.inf, np.inf, np.inf, -np.inf, -np.inf, -np.inf
                rc = 0
                for b in range(_BINS - 1, 0, -1):
                    r0, r1, r2 = min(r0, bin_box[b, 0]), min(r1, bin_box[b, 1]), min(r2, bin_box[b, 2])
                    r3, r4, r5 = max(r3, bin_box[b, 3]), max(r4, bin_box[b, 4]), max(r5, bin_box[b, 5])
                    rc += bin_cnt[b]
                    right_area[b] = _area(r0, r1, r2, r3, r4, r5)
                    right_cnt[b] = rc
                l0, l1, l2, l3, l4, l5 = np.inf, np.inf, np.inf, -np.inf, -np.inf, -np.inf
                lc = 0
                for b in range(_BINS - 1):          # split between bin b and b + 1
                    l0, l1, l2 = min(l0, bin_box[b, 0]), min(l1, bin_box[b, 1]), min(l2, bin_box[b, 2])
                    l3, l4, l5 = max(l3, bin_box[b, 3]), max(l4, bin_box[b, 4]), max(l5, bin_box[b, 5])
                    lc += bin_cnt[b]
                    if lc == 0 or right_cnt[b + 1] == 0:
                        continue
                    cost = _area(l0, l1, l2, l3, l4, l5) * lc + right_area[b + 1] * right_cnt[b + 1]
                    if cost < best_cost:
                        best_cost, best_axis, best_bin = cost, a, b
        mid = s
        if best_axis >= 0:
            a = best_axis
            scale = _BINS / (chi[a] - clo[a])
            i, j = s, e - 1
            while i <= j:                           # partition: bins <= best_bin to the left
                if min(_BINS - 1, int((cent[order[i], a] - clo[a]) * scale)) <= best_bin:
                    i += 1
                else:
                    order[i], order[j] = order[j], order[i]
                    j -= 1
            mid = i
        if mid <= s or mid >= e:
            # median split on the longest centroid axis (deep nodes, or all centroids in one bin)
            a = 0
            for q in range(1, 3):
                if chi[q] - clo[q] > chi[a] - clo[a]:
                    a = q
            for i in range(s, e):
                key[i] = cent[order[i], a]
            perm = np.argsort(key[s:e], kind="mergesort")
            order[s:e] = order[s:e][perm]
            mid = s + n // 2
            best_axis = a
        left, right = n_nodes, n_nodes + 1
        n_nodes += 2
        idx[node, 0], idx[node, 1], idx[node, 2], idx[node, 3] = left, right, best_axis, 0
        st_node[sp], st_s[sp], st_e[sp], st_d[sp] = right, mid, e, depth + 1
        st_node[sp + 1], st_s[sp + 1], st_e[sp + 1], st_d[sp + 1] = left, s, mid, depth + 1
        sp += 2
    return boxes[:n_nodes].copy(), idx[:n_nodes].copy(), order


def build_bvh(vertices: npt.ArrayLike, faces: npt.ArrayLike, leaf_size: int = 4
              ) -> tuple[FloatArray, npt.NDArray[np.int64], FloatArray]:
    """SAH BVH over triangles: (nodes_box (N, 6), nodes_idx (N, 4), triangles (M, 12)) (module docstring)."""
    tri = np.asarray(vertices, float)[np.asarray(faces)]            # (M, 3, 3)
    if len(tri) == 0:
        raise ValueError("mesh has no faces")
    if leaf_size < 1:
        raise ValueError(f"leaf_size must be >= 1, got {leaf_size}")
    boxes, idx, order = _build(np.ascontiguousarray(tri.min(axis=1)), np.ascontiguousarray(tri.max(axis=1)),
                               np.ascontiguousarray(tri.mean(axis=1)), int(leaf_size))
    t = tri[order]
    e1 = t[:, 1] - t[:, 0]
    e2 = t[:, 2] - t[:, 0]
    n = np.cross(e1, e2)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    tris = np.concatenate([t[:, 0], e1, e2, n], axis=1)
    return boxes, idx, np.ascontiguousarray(tris)
