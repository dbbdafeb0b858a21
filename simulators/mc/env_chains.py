"""Next-event estimation of a distant light through internal reflections of a convex faceted body (numba kernels).

The environment next-event estimation of :mod:`.walk` connects a scattering vertex x to a sun pixel's direction w
straight through the boundary (light refracted in at b, unscattered to x). Light that reaches x after one or more
internal (Fresnel or total) reflections is not connected: before this module the camera walks found it only when
a walk left x, reflected and happened to exit towards the sun (a 3.5 deg lobe), which made rare samples hundreds
of times the pixel's mean. Measured on the zoo's sun-lit boxes (z06, z13: a 5 x 20 x 40 mm ketchup box, eta 1.3,
128 spp, the sun alone): those lookups carried 7-17 % of the sun-lit image and 98-99 % of its variance
(docs/monte-carlo.md, "Sun lobes through internal reflections").

For a *distant* light and a *convex* polyhedron the missing chains have closed forms. Light from direction w that
enters through face f travels inside along d_0 = refract(-w, n_f) (one direction per face, independent of the entry
point), and after reflections at faces g_1 .. g_k along d_i = reflect(d_(i-1), n_(g_i)). It reaches x along d_k iff
the ray traced backwards from x along -d_k first leaves the body through face g_k, from that point along -d_(k-1)
through g_(k-1), ..., and finally along -d_0 through f (a convex body: the first crossing along a ray is the face of
smallest positive distance, so no edge tests are needed). Planar reflections keep the beam's cross-section, so the
flux density at x perpendicular to the beam is, per unit radiance / pdf of the sampled sun direction,

    E_perp = F_t(eta, cos_1) (cos_1 / cos_2) prod_i F_r(1/eta, d_(i-1).n_(g_i)) exp(-sigma_t L),

cos_1 = w.n_f, cos_2 = -d_0.n_f, L the chain's length inside (the k = 0 term is the straight connection of
:func:`.nee.plane_connection` with the light at infinity: J -> D^2 cos_2 / cos_1^3). Instead of enumerating every
face sequence (F^k of them), one sequence is drawn per collision: the entry face uniformly among the faces that
face w, then each reflecting face uniformly among the faces the current direction moves towards; every prefix of
length 1..K of the drawn sequence is evaluated and divided by its own probability (the prefix of a sequentially
drawn sequence is itself drawn with that probability), which is an unbiased estimate of the sum over all chains of
1..K reflections. Paths that scattered and left after at most K internal reflections since their last scattering
vertex therefore look the sun pixels up as 0 (:mod:`.render`, the split of escaping paths); paths with more
reflections, and paths that never scattered, still look them up.

References: Pharr, Jakob, Humphreys, PBR 3rd ed. sec. 14.2.4 (infinite lights sampled by a piecewise-constant
distribution) and sec. 8.2 (Fresnel, radiance across an interface); Walter et al. 2009, "Single scattering in
refractive media with triangle mesh boundaries" (closed-form connections through refracting faces); Veach 1997
sec. 9.2 (a path is unbiased under any sampling of its sequence of interactions divided by that probability).
"""
from __future__ import annotations

import math

from numba import njit

from .optics import fresnel_r, hg_phase, reflect, refract
from .rng import uniform
from .shapes import FACE_TABLE_START

__all__ = ["chain_nee", "MAX_CHAIN_REFLECTIONS"]

#: the longest chain of internal reflections connected (K above); 0 turns the chains off
MAX_CHAIN_REFLECTIONS: int = 6


@njit(cache=True, error_model="numpy")
def _exit_face(prm, px, py, pz, ux, uy, uz):
    """First crossing of the convex face table ``prm`` from interior p along unit u: (distance, record offset)."""
    best = math.inf
    best_o = -1
    o = FACE_TABLE_START
    for _ in range(int(prm[0])):
        un = ux * prm[o] + uy * prm[o + 1] + uz * prm[o + 2]
        if un > 0.0:
            dep = prm[o + 3] - (px * prm[o] + py * prm[o + 1] + pz * prm[o + 2])
            t = max(dep, 0.0) / un
            if t < best:
                best = t
                best_o = o
        o += 8 + 4 * int(prm[o + 7])
    return best, best_o


@njit(cache=True, error_model="numpy")
def _pick_face(prm, dx, dy, dz, u):
    """Uniform choice among the face records with d.n > 0 (``u`` in [0, 1)): (record offset or -1, count)."""
    n = 0
    o = FACE_TABLE_START
    for _ in range(int(prm[0])):
        if dx * prm[o] + dy * prm[o + 1] + dz * prm[o + 2] > 0.0:
            n += 1
        o += 8 + 4 * int(prm[o + 7])
    if n == 0:
        return -1, 0
    j = min(int(u * n), n - 1)
    o = FACE_TABLE_START
    for _ in range(int(prm[0])):
        if dx * prm[o] + dy * prm[o + 1] + dz * prm[o + 2] > 0.0:
            if j == 0:
                return o, n
            j -= 1
        o += 8 + 4 * int(prm[o + 7])
    return -1, n


@njit(cache=True, error_model="numpy")
def chain_nee(prm, x, y, z, dcx, dcy, dcz, wx, wy, wz, eta, sigma_t, g, max_refl, work, state):
    """Sum over the drawn chain's prefixes of 1..``max_refl`` internal reflections (module docstring) of
    p(cos) E_perp / pdf-weight, per unit radiance / pdf of the sun direction w (unit, from the body towards the
    light); ``dc`` the camera walk's direction at x; ``work`` a (max_refl + 1, 5) scratch array.

    Returns (value, sum over prefixes of value_k x L_k (the derivative -d value / d sigma_t of the attenuation),
    state). 0 for eta = 1 (no internal reflections) or when no face faces w."""
    if abs(eta - 1.0) < 1e-12 or max_refl <= 0:
        return 0.0, 0.0, state
    state, u = uniform(state)
    of, m = _pick_face(prm, wx, wy, wz, u)
    if of < 0:
        return 0.0, 0.0, state
    nfx, nfy, nfz = prm[of], prm[of + 1], prm[of + 2]
    c1 = wx * nfx + wy * nfy + wz * nfz
    ok, d0x, d0y, d0z = refract(-wx, -wy, -wz, nfx, nfy, nfz, eta)
    if not ok:
        return 0.0, 0.0, state
    c2 = -(d0x * nfx + d0y * nfy + d0z * nfz)
    if not c2 > 0.0:
        return 0.0, 0.0, state
    base = (1.0 - fresnel_r(eta, c1)) * c1 / c2 * m     # / pmf of the entry face (1/m)
    inv_eta = 1.0 / eta
    dx, dy, dz = d0x, d0y, d0z
    total = 0.0
    total_len = 0.0
    for k in range(1, max_refl + 1):
        state, u = uniform(state)
        og, c = _pick_face(prm, dx, dy, dz, u)
        if og < 0:
            break
        ngx, ngy, ngz = prm[og], prm[og + 1], prm[og + 2]
        fr = fresnel_r(inv_eta, dx * ngx + dy * ngy + dz * ngz)
        if fr <= 0.0:
            break
        base *= c                                          # / pmf of this reflecting face (1/c)
        dx, dy, dz = reflect(dx, dy, dz, ngx, ngy, ngz)
        work[k, 0], work[k, 1], work[k, 2], work[k, 3], work[k, 4] = dx, dy, dz, float(og), fr
        # the chain of this prefix traced backwards from x: along -d_k out through g_k, ..., along -d_0 through f
        px, py, pz = x, y, z
        length = 0.0
        frp = 1.0
        valid = True
        for j in range(k, -1, -1):
            if j > 0:
                ux, uy, uz, want = -work[j, 0], -work[j, 1], -work[j, 2], int(work[j, 3])
            else:
                ux, uy, uz, want = -d0x, -d0y, -d0z, of
            t, oh = _exit_face(prm, px, py, pz, ux, uy, uz)
            if oh != want or t == math.inf:
                valid = False
                break
            px, py, pz = px + t * ux, py + t * uy, pz + t * uz
            length += t
            if j > 0:
                frp *= work[j, 4]
        if not valid:
            continue
        cs = -(dx * dcx + dy * dcy + dz * dcz)
        v = hg_phase(g, cs) * base * frp * math.exp(-sigma_t * length)
        total += v
        total_len += v * length
    return total, total_len, state


@njit(cache=True, error_model="numpy")
def distant_face_connections(prm, x, y, z, dcx, dcy, dcz, wx, wy, wz, eta, sigma_t, g):
    """The straight (k = 0) connections of x to a distant light in direction w (unit, towards the light) through
    the flat faces of a convex face table: per face that faces w with x on its inner side, light refracted in
    travels along d_0 = refract(-w, n); it reaches x through b = x - (depth / cos_2) d_0 iff b lies in the face
    polygon. Sum of p(cos) F_t(eta, cos_1) (cos_1 / cos_2) exp(-sigma_t |x - b|) per unit radiance / pdf (module
    docstring), and the same weighted by |x - b|. The closed form of :func:`.nee.plane_connection` with the light at
    infinity (no Newton solve per face: ~40 flops per face, so a 255-face icosphere costs what the far point light
    cost a box)."""
    tot = 0.0
    tot_len = 0.0
    o = FACE_TABLE_START
    for _ in range(int(prm[0])):
        nx, ny, nz, c = prm[o], prm[o + 1], prm[o + 2], prm[o + 3]
        ne = int(prm[o + 7])
        nxt = o + 8 + 4 * ne
        c1 = wx * nx + wy * ny + wz * nz
        dep = c - (x * nx + y * ny + z * nz)
        if c1 > 0.0 and dep >= 0.0:
            ok, d0x, d0y, d0z = refract(-wx, -wy, -wz, nx, ny, nz, eta)
            c2 = -(d0x * nx + d0y * ny + d0z * nz)
            if ok and c2 > 0.0:
                t = dep / c2
                bx, by, bz = x - t * d0x, y - t * d0y, z - t * d0z
                tol = 1e-12 * (abs(dep) + abs(c) + 1.0)
                inside = True
                for e in range(ne):
                    q = o + 8 + 4 * e
                    if prm[q] * bx + prm[q + 1] * by + prm[q + 2] * bz < prm[q + 3] - tol:
                        inside = False
                        break
                if inside:
                    cs = -(d0x * dcx + d0y * dcy + d0z * dcz)
                    v = hg_phase(g, cs) * (1.0 - fresnel_r(eta, c1)) * c1 / c2 * math.exp(-sigma_t * t)
                    tot += v
                    tot_len += v * t
        o = nxt
    return tot, tot_len
