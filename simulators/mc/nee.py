"""Next-event estimation to point lights from a scattering vertex inside the medium (numba kernels).

For a vertex x reached by a camera walk travelling along d_cam, the in-scattered radiance due to an isotropic
point light of radiant intensity I at L is  p(cos) * E_perp(x), where E_perp is the flux density that reaches x
straight from L through the boundary and cos = (propagation of that light) . (-d_cam):

- index-matched boundary (eta = 1): E_perp = I exp(-sigma_t l_in) / |L - x|^2, l_in the length of the segment
  inside the medium (several pieces for non-convex meshes: occlusion is exact).
- smooth dielectric (eta != 1): the light reaches x only along the refracted ray(s) through the boundary point(s)
  b where Snell's law holds (stationary optical path, Fermat). Then E_perp = I F_t(eta, cos_1) exp(-sigma_t |x-b|) / J
  with J = dA_perp/dOmega the cross-section at x of the refracted ray tube per unit solid angle at L (the
  "generalized geometry term" of specular next-event estimation, Mitchell & Hanrahan 1992; Hanika, Droske,
  Fascione 2015 "Manifold next event estimation"). Planar faces (half-space, slab, box) have one closed-form
  solution per face:
      J = (h / cos_1 + z / (eta cos_2)) cos_2 (h / cos_1^2 + z cos_1 / (eta cos_2^3)),
  h the light's height over the face, z the vertex depth (J = |L - x|^2 at eta = 1). Spheres: all stationary
  points on the great circle through L, x and the centre (bracketed by a scan, refined by bisection), J by
  central finite differences of the refracted ray tube. Convex triangle meshes (a pyramid, a box given as a
  mesh, any convex polyhedron): coplanar triangles are merged into flat convex faces; one closed-form candidate
  per face that faces the light, kept iff its refraction point lies in the face, exactly like the box's faces;
  convexity makes both segments unoccluded (:func:`mesh_connections`). Non-convex meshes (at most
  :data:`.shapes.MAX_CONNECTION_PLANES` distinct face planes, :func:`.shapes.plane_table`): one closed-form
  candidate per plane that faces the light and has x on its inner side, kept iff two shadow rays of the BVH
  confirm it (:func:`nonconvex_mesh_connections`): x -> b meets the boundary first at b, on a face of that plane
  (b lies in a face, and the inside segment does not leave and re-enter the medium), and b -> L meets nothing
  (the light is not occluded by another part of the mesh). On a convex mesh this gives the same connections as
  the face table (tested to rounding).

Not captured (documented bias of the point-light estimator with eta != 1): light that reaches its first scattering
vertex only after a specular reflection inside the medium, bounded by F_r exp(-sigma_t * chord); zero for the
half-space, small for a sphere or box many mean free paths across, but not zero near edges: light refracted in
within ~a mean free path of an edge can meet the next face beyond the critical angle (total reflection). Measured
on the L-block at eta 1.3 (37 deg incidence, mean free path 0.4 mm): 1.9 +- 0.6 % darker than plain path tracing
of a map pixel, none at 0.08 mm (docs/monte-carlo.md; consistent with this blind spot, not proven the only cause). Non-convex meshes add light that crosses
the boundary more than once before it first scatters (refracted in, through a part of the object unscattered, out
and in again: a chain of specular vertices with no closed form), bounded by F_t^3 exp(-sigma_t * chord) for the
chord through the intervening part (for the L-block's 8 mm wall, exp(-8 sigma_t): < 1e-7 at sigma_t >= 2 / mm; the
eta = 1 branch counts it, which measures it: tests/simulators/test_mc_nonconvex_point_light.py).
"""
from __future__ import annotations

import math

from numba import njit

from .optics import fresnel_r, hg_phase, orthonormal_basis, refract
from .shapes import (BOX, BVH_CONNECTIONS, FACE_TABLE_START, HALF_SPACE, MESH, PLANE_TABLE, SLAB, SPHERE,
                     nearest_hit, surface_distance)

__all__ = ["point_light_nee", "light_contribution", "min_inside_length", "plane_connection", "sphere_connections",
           "sphere_min_inside_length", "mesh_connections", "mesh_min_inside_length", "nonconvex_mesh_connections",
           "bvh_mesh_connections", "connection_radius", "CUTOFF"]

_FD_STEP = 1e-6


@njit(cache=True, error_model="numpy")
def plane_connection(p0x, p0y, p0z, nx, ny, nz, x, y, z, lx, ly, lz, eta):
    """Refraction point on the plane (p0, outward n) connecting interior x to exterior L.

    Returns (ok, bx, by, bz, J, cos_1, inside_len): J = dA_perp/dOmega [mm^2/sr], cos_1 the outside cosine.
    """
    h = (lx - p0x) * nx + (ly - p0y) * ny + (lz - p0z) * nz
    dep = (p0x - x) * nx + (p0y - y) * ny + (p0z - z) * nz
    if not (h > 0.0 and dep >= 0.0):
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    wx, wy, wz = x - lx, y - ly, z - lz
    wn = wx * nx + wy * ny + wz * nz
    wx, wy, wz = wx - wn * nx, wy - wn * ny, wz - wn * nz
    rho = math.sqrt(wx * wx + wy * wy + wz * wz)
    fx, fy, fz = lx - h * nx, ly - h * ny, lz - h * nz  # foot of L on the plane
    if rho <= 1e-14 * (h + dep):
        J = (h + dep / eta) ** 2
        return True, fx, fy, fz, J, 1.0, dep
    ux, uy, uz = wx / rho, wy / rho, wz / rho
    lo, hi = 0.0, rho
    a = min(max(eta * rho * h / (dep + eta * h), 0.0), rho)
    tol = 1e-14 * (rho + h + dep)
    for _ in range(100):
        s1 = math.sqrt(a * a + h * h)
        r2 = rho - a
        s2 = math.sqrt(r2 * r2 + dep * dep)
        f = a / s1 - eta * r2 / s2
        if f > 0.0:
            hi = a
        else:
            lo = a
        fp = h * h / (s1 * s1 * s1) + (eta * dep * dep / (s2 * s2 * s2) if s2 > 0.0 else 0.0)
        an = a - f / fp if fp > 0.0 else 0.5 * (lo + hi)
        if not (lo < an < hi):
            an = 0.5 * (lo + hi)
        if abs(an - a) <= tol:
            a = an
            break
        a = an
    s1 = math.sqrt(a * a + h * h)
    r2 = rho - a
    s2 = math.sqrt(r2 * r2 + dep * dep)
    c1 = h / s1
    c2 = dep / s2
    if c2 <= 0.0:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    J = (h / c1 + dep / (eta * c2)) * c2 * (h / (c1 * c1) + dep * c1 / (eta * c2 * c2 * c2))
    return True, fx + a * ux, fy + a * uy, fz + a * uz, J, c1, s2


@njit(cache=True, error_model="numpy")
def _sphere_f(phi, R, D, x1, x2, eta):
    """Snell residual t.u_in - eta t.u_ref at b(phi) on the great circle (2-D coordinates, L = (D, 0))."""
    cb = math.cos(phi)
    sb = math.sin(phi)
    bx, by = R * cb, R * sb
    ix, iy = bx - D, by
    il = math.sqrt(ix * ix + iy * iy)
    rx, ry = x1 - bx, x2 - by
    rl = math.sqrt(rx * rx + ry * ry)
    if rl <= 0.0:
        return 0.0
    return (-sb * ix + cb * iy) / il - eta * (-sb * rx + cb * ry) / rl


@njit(cache=True, error_model="numpy")
def _refract_sphere_to_plane(cx, cy, cz, R, lx, ly, lz, dx, dy, dz, eta, x, y, z, d0x, d0y, d0z):
    """Trace L + t d to the sphere, refract, and return the crossing with the plane through x normal to d0."""
    px, py, pz = lx - cx, ly - cy, lz - cz
    b = px * dx + py * dy + pz * dz
    c = px * px + py * py + pz * pz - R * R
    disc = b * b - c
    if disc < 0.0:
        return False, 0.0, 0.0, 0.0
    t = -b - math.sqrt(disc)
    hx, hy, hz = lx + t * dx, ly + t * dy, lz + t * dz
    nx, ny, nz = (hx - cx) / R, (hy - cy) / R, (hz - cz) / R
    ok, rx, ry, rz = refract(dx, dy, dz, nx, ny, nz, eta)
    if not ok:
        return False, 0.0, 0.0, 0.0
    den = rx * d0x + ry * d0y + rz * d0z
    if den <= 0.0:
        return False, 0.0, 0.0, 0.0
    s = ((x - hx) * d0x + (y - hy) * d0y + (z - hz) * d0z) / den
    return True, hx + s * rx, hy + s * ry, hz + s * rz


@njit(cache=True, error_model="numpy")
def _illinois(lo, hi, flo, fhi, R, D, x1, x2, eta):
    """Root of the Snell residual in [lo, hi] (sign change) by the Illinois variant of regula falsi."""
    side = 0
    for _ in range(100):
        den = fhi - flo
        m = hi - fhi * (hi - lo) / den if den != 0.0 else 0.5 * (lo + hi)
        if not (min(lo, hi) <= m <= max(lo, hi)):
            m = 0.5 * (lo + hi)
        fm = _sphere_f(m, R, D, x1, x2, eta)
        if fm == 0.0 or abs(hi - lo) < 1e-14:
            return m
        if (fm < 0.0) == (fhi < 0.0):
            hi, fhi = m, fm
            if side == -1:
                flo *= 0.5
            side = -1
        else:
            lo, flo = m, fm
            if side == 1:
                fhi *= 0.5
            side = 1
    return 0.5 * (lo + hi)


@njit(cache=True, error_model="numpy")
def _sphere_frame(cx, cy, cz, R, x, y, z, lx, ly, lz):
    """2-D frame of the plane (centre, L, x): D = |L - c|, e1 towards L, e2, x = (x1, x2 >= 0), psi, phi_v."""
    qx, qy, qz = lx - cx, ly - cy, lz - cz
    D = math.sqrt(qx * qx + qy * qy + qz * qz)
    e1x, e1y, e1z = qx / D, qy / D, qz / D
    rx, ry, rz = x - cx, y - cy, z - cz
    x1 = rx * e1x + ry * e1y + rz * e1z
    px, py, pz = rx - x1 * e1x, ry - x1 * e1y, rz - x1 * e1z
    x2 = math.sqrt(px * px + py * py + pz * pz)
    if x2 > 1e-12 * R:
        e2x, e2y, e2z = px / x2, py / x2, pz / x2
    else:
        t1, _t2 = orthonormal_basis(e1x, e1y, e1z)
        e2x, e2y, e2z = t1[0], t1[1], t1[2]
        x2 = 0.0
    phiv = math.acos(min(1.0, R / D)) * (1.0 - 1e-9)
    psi = math.atan2(x2, x1)
    return D, e1x, e1y, e1z, e2x, e2y, e2z, x1, x2, psi, phiv


@njit(cache=True, error_model="numpy")
def sphere_min_inside_length(cx, cy, cz, R, x, y, z, lx, ly, lz):
    """Lower bound on |x - b| over the cap of the sphere visible from L (bounds the transmittance)."""
    D, e1x, e1y, e1z, e2x, e2y, e2z, x1, x2, psi, phiv = _sphere_frame(cx, cy, cz, R, x, y, z, lx, ly, lz)
    if D <= R:
        return 0.0
    if psi <= phiv:
        return max(0.0, R - math.sqrt(x1 * x1 + x2 * x2))
    bx, by = R * math.cos(phiv), R * math.sin(phiv)
    return math.sqrt((x1 - bx) ** 2 + (x2 - by) ** 2)


@njit(cache=True, error_model="numpy")
def _sphere_term(phi, cx, cy, cz, R, e1x, e1y, e1z, e2x, e2y, e2z, x, y, z, lx, ly, lz, eta, sigma_t, g,
                 dcx, dcy, dcz):
    cb, sb = math.cos(phi), math.sin(phi)
    bx = cx + R * (cb * e1x + sb * e2x)
    by = cy + R * (cb * e1y + sb * e2y)
    bz = cz + R * (cb * e1z + sb * e2z)
    ix, iy, iz = bx - lx, by - ly, bz - lz
    il = math.sqrt(ix * ix + iy * iy + iz * iz)
    ix, iy, iz = ix / il, iy / il, iz / il
    ux, uy, uz = x - bx, y - by, z - bz
    ul = math.sqrt(ux * ux + uy * uy + uz * uz)
    if ul <= 0.0:
        return 0.0
    ux, uy, uz = ux / ul, uy / ul, uz / ul
    nbx, nby, nbz = (bx - cx) / R, (by - cy) / R, (bz - cz) / R
    cos1 = -(ix * nbx + iy * nby + iz * nbz)
    # ray-tube cross-section at x per unit solid angle at L (central differences)
    a1, a2 = orthonormal_basis(ix, iy, iz)
    okp1, q1x, q1y, q1z = _fd_point(cx, cy, cz, R, lx, ly, lz, ix, iy, iz, a1[0], a1[1], a1[2],
                                    _FD_STEP, eta, x, y, z, ux, uy, uz)
    okm1, r1x, r1y, r1z = _fd_point(cx, cy, cz, R, lx, ly, lz, ix, iy, iz, a1[0], a1[1], a1[2],
                                    -_FD_STEP, eta, x, y, z, ux, uy, uz)
    okp2, q2x, q2y, q2z = _fd_point(cx, cy, cz, R, lx, ly, lz, ix, iy, iz, a2[0], a2[1], a2[2],
                                    _FD_STEP, eta, x, y, z, ux, uy, uz)
    okm2, r2x, r2y, r2z = _fd_point(cx, cy, cz, R, lx, ly, lz, ix, iy, iz, a2[0], a2[1], a2[2],
                                    -_FD_STEP, eta, x, y, z, ux, uy, uz)
    if not (okp1 and okm1 and okp2 and okm2):
        return 0.0
    s = 0.5 / _FD_STEP
    g1x, g1y, g1z = (q1x - r1x) * s, (q1y - r1y) * s, (q1z - r1z) * s
    g2x, g2y, g2z = (q2x - r2x) * s, (q2y - r2y) * s, (q2z - r2z) * s
    cxp = g1y * g2z - g1z * g2y
    cyp = g1z * g2x - g1x * g2z
    czp = g1x * g2y - g1y * g2x
    J = math.sqrt(cxp * cxp + cyp * cyp + czp * czp)
    if not J > 0.0:
        return 0.0
    ft = 1.0 - fresnel_r(eta, cos1)
    cs = -(ux * dcx + uy * dcy + uz * dcz)
    return hg_phase(g, cs) * ft * math.exp(-sigma_t * ul) / J


@njit(cache=True, error_model="numpy")
def sphere_connections(cx, cy, cz, R, x, y, z, lx, ly, lz, eta, sigma_t, g, dcx, dcy, dcz, n_scan):
    """Sum over refraction points b on the sphere of p(cos) F_t exp(-sigma_t |x - b|) / J (per unit intensity).

    When x lies inside the cone of the visible cap (angle psi <= phi_v from the axis centre -> L) there is exactly
    one stationary point, bracketed by [0, psi] (checked numerically over eta in [0.5, 3] in the tests); beyond
    it (the region behind the sphere's limb, reachable through refraction caustics) up to three exist, found by a
    scan of ``n_scan`` intervals over the visible arc.
    """
    D, e1x, e1y, e1z, e2x, e2y, e2z, x1, x2, psi, phiv = _sphere_frame(cx, cy, cz, R, x, y, z, lx, ly, lz)
    if D <= R:
        return 0.0
    if psi <= phiv:
        f0 = _sphere_f(0.0, R, D, x1, x2, eta)
        f1 = _sphere_f(psi, R, D, x1, x2, eta)
        if f0 == 0.0:
            phi = 0.0
        elif f1 == 0.0:
            phi = psi
        elif (f0 < 0.0) != (f1 < 0.0):
            phi = _illinois(0.0, psi, f0, f1, R, D, x1, x2, eta)
        else:
            return 0.0
        return _sphere_term(phi, cx, cy, cz, R, e1x, e1y, e1z, e2x, e2y, e2z, x, y, z, lx, ly, lz, eta, sigma_t,
                            g, dcx, dcy, dcz)
    total = 0.0
    f_prev = _sphere_f(-phiv, R, D, x1, x2, eta)
    a_prev = -phiv
    for k in range(1, n_scan + 1):
        a_k = -phiv + 2.0 * phiv * k / n_scan
        f_k = _sphere_f(a_k, R, D, x1, x2, eta)
        if f_k == 0.0 or (f_prev != 0.0 and (f_prev < 0.0) != (f_k < 0.0)):
            phi = a_k if f_k == 0.0 else _illinois(a_prev, a_k, f_prev, f_k, R, D, x1, x2, eta)
            total += _sphere_term(phi, cx, cy, cz, R, e1x, e1y, e1z, e2x, e2y, e2z, x, y, z, lx, ly, lz, eta,
                                  sigma_t, g, dcx, dcy, dcz)
        f_prev, a_prev = f_k, a_k
    return total


@njit(cache=True, error_model="numpy")
def _fd_point(cx, cy, cz, R, lx, ly, lz, ix, iy, iz, ax, ay, az, step, eta, x, y, z, ux, uy, uz):
    """Perturbed ray normalize(i + step a) from L, refracted by the sphere, crossing the plane at x normal to u."""
    dx, dy, dz = ix + step * ax, iy + step * ay, iz + step * az
    s = 1.0 / math.sqrt(dx * dx + dy * dy + dz * dz)
    return _refract_sphere_to_plane(cx, cy, cz, R, lx, ly, lz, dx * s, dy * s, dz * s, eta, x, y, z, ux, uy, uz)


@njit(cache=True, error_model="numpy")
def _plane_term(p0x, p0y, p0z, nx, ny, nz, x, y, z, lx, ly, lz, eta, sigma_t, g, dcx, dcy, dcz,
                bounded, lo0, hi0, lo1, hi1, ax0, ax1, tol):
    ok, bx, by, bz, J, c1, l_in = plane_connection(p0x, p0y, p0z, nx, ny, nz, x, y, z, lx, ly, lz, eta)
    if not ok or J <= 0.0:
        return 0.0
    if bounded:
        b = (bx, by, bz)
        if b[ax0] < lo0 - tol or b[ax0] > hi0 + tol or b[ax1] < lo1 - tol or b[ax1] > hi1 + tol:
            return 0.0
    return _connection_term(x, y, z, bx, by, bz, J, c1, l_in, nx, ny, nz, eta, sigma_t, g, dcx, dcy, dcz)


@njit(cache=True, error_model="numpy")
def _connection_term(x, y, z, bx, by, bz, J, c1, l_in, nx, ny, nz, eta, sigma_t, g, dcx, dcy, dcz):
    """p(cos) F_t(eta, cos_1) exp(-sigma_t l_in) / J of one refracted connection x <- b <- L (outward normal n)."""
    ux, uy, uz = x - bx, y - by, z - bz
    if l_in > 0.0:
        ux, uy, uz = ux / l_in, uy / l_in, uz / l_in
    else:
        ux, uy, uz = -nx, -ny, -nz
    cs = -(ux * dcx + uy * dcy + uz * dcz)
    return hg_phase(g, cs) * (1.0 - fresnel_r(eta, c1)) * math.exp(-sigma_t * l_in) / J


@njit(cache=True, error_model="numpy")
def _face_candidate(prm, o, x, y, z, lx, ly, lz):
    """Can the face record at prm[o] (:func:`.shapes.convex_face_table`) carry a refracted connection x <- b <- L?
    It must face the light (h > 0), hold x on its inner side, and the segment F..P that contains b (F the foot of
    L, P the projection of x on the plane; b is a convex combination of the two) must not lie entirely beyond one
    boundary edge (tolerance ``tol``, also used by the inside test of b). Returns (ok, depth of x below the
    plane, tol, offset of the next record)."""
    nx, ny, nz, c = prm[o], prm[o + 1], prm[o + 2], prm[o + 3]
    ne = int(prm[o + 7])
    nxt = o + 8 + 4 * ne
    h = lx * nx + ly * ny + lz * nz - c
    dep = c - (x * nx + y * ny + z * nz)
    tol = 1e-12 * (abs(h) + abs(dep) + abs(c))
    if not (h > 0.0 and dep >= 0.0):
        return False, dep, tol, nxt
    fx, fy, fz = lx - h * nx, ly - h * ny, lz - h * nz
    px, py, pz = x + dep * nx, y + dep * ny, z + dep * nz
    for e in range(ne):
        q = o + 8 + 4 * e
        if (prm[q] * fx + prm[q + 1] * fy + prm[q + 2] * fz < prm[q + 3] - tol
                and prm[q] * px + prm[q + 1] * py + prm[q + 2] * pz < prm[q + 3] - tol):
            return False, dep, tol, nxt
    return True, dep, tol, nxt


@njit(cache=True, error_model="numpy")
def mesh_min_inside_length(prm, x, y, z, lx, ly, lz):
    """Lower bound on |x - b| over the refracted connections through a convex mesh (:func:`mesh_connections`):
    the smallest depth of x below the plane of a face that can carry one (|x - b| >= that depth); inf if none."""
    best = math.inf
    o = FACE_TABLE_START
    for _ in range(int(prm[0])):
        ok, dep, _tol, o_next = _face_candidate(prm, o, x, y, z, lx, ly, lz)
        if ok:
            best = min(best, dep)
        o = o_next
    return best


@njit(cache=True, error_model="numpy")
def mesh_connections(prm, x, y, z, lx, ly, lz, eta, sigma_t, g, dcx, dcy, dcz):
    """Sum over the refracted connections x <- b <- L through the flat faces of a CONVEX closed mesh of
    p(cos) F_t exp(-sigma_t |x - b|) / J (per unit intensity); ``prm`` is the face table of
    :func:`.shapes.convex_face_table` (coplanar triangles merged into convex polygons).

    For a convex body every face that faces the light (h > 0) lies in a plane with exactly one stationary point b
    (:func:`plane_connection`, as for the box's faces); the connection exists iff b lies in the face polygon
    (tolerance 1e-12 of the scale, like the box's), and then both segments are unoccluded: x -> b inside
    (convexity) and b -> L in the open outer half-space of the face plane, which the body does not reach.
    Cost per call: O(faces + boundary edges) plus one plane solution per candidate face. Non-convex meshes:
    :func:`nonconvex_mesh_connections`.
    """
    tot = 0.0
    o = FACE_TABLE_START
    for _ in range(int(prm[0])):
        cand, _dep, tol, o_next = _face_candidate(prm, o, x, y, z, lx, ly, lz)
        if cand:
            nx, ny, nz = prm[o], prm[o + 1], prm[o + 2]
            ok, bx, by, bz, J, c1, l_in = plane_connection(prm[o + 4], prm[o + 5], prm[o + 6], nx, ny, nz,
                                                           x, y, z, lx, ly, lz, eta)
            if ok and J > 0.0:
                inside = True
                for e in range(int(prm[o + 7])):
                    q = o + 8 + 4 * e
                    if prm[q] * bx + prm[q + 1] * by + prm[q + 2] * bz < prm[q + 3] - tol:
                        inside = False
                        break
                if inside:
                    tot += _connection_term(x, y, z, bx, by, bz, J, c1, l_in, nx, ny, nz, eta, sigma_t, g,
                                            dcx, dcy, dcz)
        o = o_next
    return tot


@njit(cache=True, error_model="numpy")
def _shadowed_connection_term(prm, nbox, nidx, tris, eps_t, stack, tol_t, nudge, x, y, z, bx, by, bz, J, c1, l_in,
                              nx, ny, nz, lx, ly, lz, eta, sigma_t, g, dcx, dcy, dcz):
    """A refracted connection x -> b -> L through a non-convex mesh's face plane (normal n), confirmed by two
    shadow rays: inside, x -> b must first meet the boundary at b on a face of that plane; outside, b -> L must be
    free. Its :func:`_connection_term`, or 0 when either ray is blocked (used by :func:`nonconvex_mesh_connections`
    and :func:`bvh_mesh_connections`)."""
    ux, uy, uz = (bx - x) / l_in, (by - y) / l_in, (bz - z) / l_in
    t, hx, hy, hz = nearest_hit(MESH, prm, nbox, nidx, tris, x, y, z, ux, uy, uz, eps_t, stack)
    if not (abs(t - l_in) <= tol_t and hx * nx + hy * ny + hz * nz >= 1.0 - 1e-8):
        return 0.0
    ox, oy, oz = bx + nudge * nx, by + nudge * ny, bz + nudge * nz
    vx, vy, vz = lx - ox, ly - oy, lz - oz
    dl = math.sqrt(vx * vx + vy * vy + vz * vz)
    t2, _a, _b, _c = nearest_hit(MESH, prm, nbox, nidx, tris, ox, oy, oz, vx / dl, vy / dl, vz / dl, eps_t, stack)
    if t2 < dl:
        return 0.0
    return _connection_term(x, y, z, bx, by, bz, J, c1, l_in, nx, ny, nz, eta, sigma_t, g, dcx, dcy, dcz)


@njit(cache=True, error_model="numpy")
def nonconvex_mesh_connections(prm, nbox, nidx, tris, eps_t, stack, x, y, z, lx, ly, lz, eta, sigma_t, g,
                               dcx, dcy, dcz):
    """Sum over the refracted connections x <- b <- L through a NON-CONVEX closed mesh of
    p(cos) F_t exp(-sigma_t |x - b|) / J (per unit intensity); ``prm`` the plane table of
    :func:`.shapes.plane_table` (distinct face planes, no edges).

    Per plane that faces the light with x on its inner side, :func:`plane_connection` gives the one stationary
    point b of the plane (Snell's law; the generalized geometry term J of Mitchell & Hanrahan 1992). It is a
    connection of the mesh iff (1) the ray x -> b first meets the boundary at distance |x - b| (to 1e-7 of the
    scale) on a triangle of that plane's orientation: b lies on a face of the plane and the segment stays inside,
    and (2) the ray from b (nudged 1e-9 of the scale outwards) towards L meets no triangle before L: no other
    part of the object shadows it. Cost: O(planes) plus two BVH rays per candidate plane."""
    tot = 0.0
    tol_t = 1e5 * eps_t          # eps_t = 1e-12 x scale (:func:`.shapes._geometry`)
    nudge = 1e3 * eps_t
    o = FACE_TABLE_START
    for _ in range(int(prm[0])):
        cand, _dep, _tol, o_next = _face_candidate(prm, o, x, y, z, lx, ly, lz)
        if cand:
            nx, ny, nz = prm[o], prm[o + 1], prm[o + 2]
            ok, bx, by, bz, J, c1, l_in = plane_connection(prm[o + 4], prm[o + 5], prm[o + 6], nx, ny, nz,
                                                           x, y, z, lx, ly, lz, eta)
            if ok and J > 0.0 and l_in > 0.0:
                tot += _shadowed_connection_term(prm, nbox, nidx, tris, eps_t, stack, tol_t, nudge, x, y, z, bx, by,
                                                 bz, J, c1, l_in, nx, ny, nz, lx, ly, lz, eta, sigma_t, g, dcx, dcy,
                                                 dcz)
        o = o_next
    return tot


#: relative weight exp(-sigma_t R) below which a refracted connection is dropped by
#: :func:`bvh_mesh_connections` (sets its search radius R, :func:`connection_radius`)
CUTOFF = 1e-6


@njit(cache=True, error_model="numpy")
def connection_radius(sigma_t):
    """Search radius R [mm] = ln(1 / CUTOFF) / sigma_t (inf for sigma_t <= 0)."""
    if not sigma_t > 0.0:
        return math.inf
    return math.log(1.0 / CUTOFF) / sigma_t


@njit(cache=True, error_model="numpy")
def _triangle_candidate(v0x, v0y, v0z, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz, x, y, z, lx, ly, lz):
    """Can the triangle (v0, v0 + e1, v0 + e2; outward unit normal n) hold a refracted connection x <- b <- L? Its
    plane must face the light with x on its inner side, and the segment F..P that contains b (F the foot of L,
    P the projection of x on the plane) must not lie entirely beyond one edge (as :func:`_face_candidate` for
    the convex faces; no tolerance: the barycentric test of b decides)."""
    h = (lx - v0x) * nx + (ly - v0y) * ny + (lz - v0z) * nz
    dep = (v0x - x) * nx + (v0y - y) * ny + (v0z - z) * nz
    if not (h > 0.0 and dep >= 0.0):
        return False
    fx, fy, fz = lx - h * nx, ly - h * ny, lz - h * nz
    px, py, pz = x + dep * nx, y + dep * ny, z + dep * nz
    # edges a -> a + e in counter-clockwise order about n; inward normal n x e
    for ax, ay, az, ex, ey, ez in ((v0x, v0y, v0z, e1x, e1y, e1z),
                                   (v0x + e1x, v0y + e1y, v0z + e1z, e2x - e1x, e2y - e1y, e2z - e1z),
                                   (v0x + e2x, v0y + e2y, v0z + e2z, -e2x, -e2y, -e2z)):
        mx, my, mz = ny * ez - nz * ey, nz * ex - nx * ez, nx * ey - ny * ex
        if ((fx - ax) * mx + (fy - ay) * my + (fz - az) * mz < 0.0
                and (px - ax) * mx + (py - ay) * my + (pz - az) * mz < 0.0):
            return False
    return True


@njit(cache=True, error_model="numpy")
def bvh_mesh_connections(prm, nbox, nidx, tris, eps_t, stack, x, y, z, lx, ly, lz, eta, sigma_t, g,
                         dcx, dcy, dcz, radius):
    """Sum over the refracted connections x <- b <- L through a NON-CONVEX closed mesh of any size with
    |x - b| <= ``radius`` of p(cos) F_t exp(-sigma_t |x - b|) / J (per unit intensity). ``stack``: its first half
    for the BVH descent, its second half for the shadow rays.

    :func:`nonconvex_mesh_connections` solves Snell's law once per distinct face plane: exact, but O(planes) per
    scattering vertex, and a scanned mesh has one plane per triangle. Here the candidates are the triangles of the
    BVH leaves within ``radius`` of x (boxes farther away are not opened):

    - a connection with |x - b| > R weighs less than exp(-sigma_t R) of the same connection through the surface
      at x; light_contribution passes R = :func:`connection_radius` = ln(1 / CUTOFF) / sigma_t (13.8 mean free
      paths at CUTOFF = 1e-6), dropping those: the design's one approximation, a truncation of far connections at
      a stated relative weight (nothing is dropped when the ball holds the whole mesh);
    - per candidate triangle whose plane faces the light with x on its inner side, :func:`plane_connection` gives
      the plane's one stationary point b; it is a connection iff b lies in that triangle (barycentric test without
      tolerance: b on an edge shared by coplanar triangles is a measure-zero event), |x - b| <= R, and the two
      shadow rays of :func:`nonconvex_mesh_connections` confirm it (x -> b meets the boundary first at b, on a face
      of that orientation; b -> L meets nothing).

    Every connection the all-planes path finds within R is found here (its b lies in a triangle of its plane
    within R of x), none twice (b lies in one triangle). Like the all-planes path it misses light that crosses the
    boundary more than once before it first scatters (module docstring). Cost: the BVH descent over the ball plus
    one plane solution per triangle in it and two BVH rays per connection found: local, not O(faces), once the
    ball is smaller than the mesh (tests/simulators/test_mc_bvh_connections.py compares both paths)."""
    tot = 0.0
    tol_t = 1e5 * eps_t          # as nonconvex_mesh_connections: eps_t = 1e-12 x scale
    nudge = 1e3 * eps_t
    r2 = radius * radius
    ray_stack = stack[stack.shape[0] // 2:]
    stack = stack[:stack.shape[0] // 2]
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        node = stack[sp]
        # squared distance from x to the node box
        qx = min(max(x, nbox[node, 0]), nbox[node, 3]) - x
        qy = min(max(y, nbox[node, 1]), nbox[node, 4]) - y
        qz = min(max(z, nbox[node, 2]), nbox[node, 5]) - z
        d2 = qx * qx + qy * qy + qz * qz
        if d2 > r2:
            continue
        cnt = nidx[node, 3]
        if cnt == 0:
            if sp + 2 <= stack.shape[0]:
                stack[sp] = nidx[node, 0]
                stack[sp + 1] = nidx[node, 1]
                sp += 2
            continue
        first = nidx[node, 2]
        for k in range(first, first + cnt):
            v0x, v0y, v0z = tris[k, 0], tris[k, 1], tris[k, 2]
            nx, ny, nz = tris[k, 9], tris[k, 10], tris[k, 11]
            e1x, e1y, e1z = tris[k, 3], tris[k, 4], tris[k, 5]
            e2x, e2y, e2z = tris[k, 6], tris[k, 7], tris[k, 8]
            if not _triangle_candidate(v0x, v0y, v0z, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz, x, y, z, lx, ly, lz):
                continue
            ok, bx, by, bz, J, c1, l_in = plane_connection(v0x, v0y, v0z, nx, ny, nz, x, y, z, lx, ly, lz, eta)
            if not (ok and J > 0.0 and 0.0 < l_in <= radius):
                continue
            # b in this triangle (barycentric coordinates in the plane)
            wx, wy, wz = bx - v0x, by - v0y, bz - v0z
            d00 = e1x * e1x + e1y * e1y + e1z * e1z
            d01 = e1x * e2x + e1y * e2y + e1z * e2z
            d11 = e2x * e2x + e2y * e2y + e2z * e2z
            d20 = wx * e1x + wy * e1y + wz * e1z
            d21 = wx * e2x + wy * e2y + wz * e2z
            den = d00 * d11 - d01 * d01
            if not den > 0.0:
                continue
            u = (d11 * d20 - d01 * d21) / den
            v = (d00 * d21 - d01 * d20) / den
            if u < 0.0 or v < 0.0 or u + v > 1.0:
                continue
            # the shadow rays of nonconvex_mesh_connections: inside x -> b, outside b -> L
            tot += _shadowed_connection_term(prm, nbox, nidx, tris, eps_t, ray_stack, tol_t, nudge, x, y, z, bx, by,
                                             bz, J, c1, l_in, nx, ny, nz, lx, ly, lz, eta, sigma_t, g, dcx, dcy, dcz)
    return tot


@njit(cache=True, error_model="numpy")
def min_inside_length(kind, prm, x, y, z, lx, ly, lz, eta):
    """Lower bound on the length inside the medium of any connection from x to the light (for roulette)."""
    if abs(eta - 1.0) < 1e-12:
        return surface_distance(kind, prm, x, y, z)
    if kind == HALF_SPACE:
        return max(0.0, prm[0] - z)
    if kind == SLAB:
        return max(0.0, prm[0] - z) if lz > prm[0] else max(0.0, z - prm[1])
    if kind == BOX:
        p = (x, y, z)
        l = (lx, ly, lz)
        best = math.inf
        for a in range(3):
            if l[a] > prm[3 + a]:
                best = min(best, prm[3 + a] - p[a])
            if l[a] < prm[a]:
                best = min(best, p[a] - prm[a])
        return max(0.0, best) if best < math.inf else 0.0
    if kind == SPHERE:
        return sphere_min_inside_length(prm[0], prm[1], prm[2], prm[3], x, y, z, lx, ly, lz)
    if kind == MESH:
        if prm[1] == BVH_CONNECTIONS:   # no plane list: 0 bounds every connection's inside length
            return 0.0
        # inf: no face can connect (q = 0); a plane table (non-convex) has no edges: min depth over the planes
        # that face L with x inside, still <= |x - b| of every connection
        return mesh_min_inside_length(prm, x, y, z, lx, ly, lz)
    return 0.0


@njit(cache=True, error_model="numpy")
def light_contribution(kind, prm, nbox, nidx, tris, eps_t, stack, x, y, z, dcx, dcy, dcz, lx, ly, lz,
                       sigma_t, g, eta, n_scan):
    """p(cos) E_perp / I at x for a unit-intensity point light at L (see module docstring)."""
    if abs(eta - 1.0) < 1e-12:
        ux, uy, uz = lx - x, ly - y, lz - z
        dist = math.sqrt(ux * ux + uy * uy + uz * uz)
        if dist <= 0.0:
            return 0.0
        ux, uy, uz = ux / dist, uy / dist, uz / dist
        px, py, pz = x, y, z
        remaining = dist
        inside = True
        l_in = 0.0
        for _ in range(256):
            t, nx_, ny_, nz_ = nearest_hit(kind, prm, nbox, nidx, tris, px, py, pz, ux, uy, uz, eps_t, stack)
            if t >= remaining:
                if inside:
                    l_in += remaining
                break
            if inside:
                l_in += t
            inside = not inside
            px, py, pz = px + t * ux, py + t * uy, pz + t * uz
            remaining -= t
        if inside:  # the light is inside the medium: not a valid configuration
            return 0.0
        cs = ux * dcx + uy * dcy + uz * dcz
        return hg_phase(g, cs) * math.exp(-sigma_t * l_in) / (dist * dist)
    if kind == HALF_SPACE:
        return _plane_term(0.0, 0.0, prm[0], 0.0, 0.0, 1.0, x, y, z, lx, ly, lz, eta, sigma_t, g, dcx, dcy, dcz,
                           False, 0.0, 0.0, 0.0, 0.0, 0, 1, 0.0)
    if kind == SLAB:
        tot = 0.0
        if lz > prm[0]:
            tot += _plane_term(0.0, 0.0, prm[0], 0.0, 0.0, 1.0, x, y, z, lx, ly, lz, eta, sigma_t, g,
                               dcx, dcy, dcz, False, 0.0, 0.0, 0.0, 0.0, 0, 1, 0.0)
        if lz < prm[1]:
            tot += _plane_term(0.0, 0.0, prm[1], 0.0, 0.0, -1.0, x, y, z, lx, ly, lz, eta, sigma_t, g,
                               dcx, dcy, dcz, False, 0.0, 0.0, 0.0, 0.0, 0, 1, 0.0)
        return tot
    if kind == BOX:
        tot = 0.0
        l = (lx, ly, lz)
        tol = eps_t
        for a in range(3):
            a0 = (a + 1) % 3
            a1 = (a + 2) % 3
            for side in range(2):
                s = 1.0 if side == 1 else -1.0
                plane = prm[3 + a] if side == 1 else prm[a]
                if s * (l[a] - plane) <= 0.0:
                    continue
                n0 = s if a == 0 else 0.0
                n1 = s if a == 1 else 0.0
                n2 = s if a == 2 else 0.0
                p0x = plane if a == 0 else 0.0
                p0y = plane if a == 1 else 0.0
                p0z = plane if a == 2 else 0.0
                tot += _plane_term(p0x, p0y, p0z, n0, n1, n2, x, y, z, lx, ly, lz, eta, sigma_t, g,
                                   dcx, dcy, dcz, True, prm[a0], prm[3 + a0], prm[a1], prm[3 + a1], a0, a1, tol)
        return tot
    if kind == SPHERE:
        return sphere_connections(prm[0], prm[1], prm[2], prm[3], x, y, z, lx, ly, lz, eta, sigma_t, g,
                                  dcx, dcy, dcz, n_scan)
    if kind == MESH:
        if prm[1] == PLANE_TABLE:
            return nonconvex_mesh_connections(prm, nbox, nidx, tris, eps_t, stack, x, y, z, lx, ly, lz, eta,
                                              sigma_t, g, dcx, dcy, dcz)
        if prm[1] == BVH_CONNECTIONS:
            return bvh_mesh_connections(prm, nbox, nidx, tris, eps_t, stack, x, y, z, lx, ly, lz, eta, sigma_t, g,
                                        dcx, dcy, dcz, connection_radius(sigma_t))
        return mesh_connections(prm, x, y, z, lx, ly, lz, eta, sigma_t, g, dcx, dcy, dcz)
    return 0.0


@njit(cache=True, error_model="numpy")
def _rouletted_contribution(kind, prm, nbox, nidx, tris, eps_t, stack, x, y, z, dcx, dcy, dcz, lx, ly, lz,
                            sigma_t, g, eta, n_scan, nee_tau, u_rr, sigma_t_eval):
    """:func:`light_contribution` evaluated with probability q = min(1, exp(-sigma_t l_min) / nee_tau) and
    divided by q (unbiased); l_min bounds the connection's length inside the medium from below. The connection
    itself is evaluated at ``sigma_t_eval`` (= ``sigma_t`` except for the derivative estimates of
    :func:`.walk.walk`, which keep the roulette decision of ``sigma_t`` fixed: it is part of the sampling)."""
    q = min(1.0, math.exp(-sigma_t * min_inside_length(kind, prm, x, y, z, lx, ly, lz, eta)) / nee_tau)
    if not u_rr < q:
        return 0.0
    return light_contribution(kind, prm, nbox, nidx, tris, eps_t, stack, x, y, z, dcx, dcy, dcz, lx, ly, lz,
                              sigma_t_eval, g, eta, n_scan) / q


@njit(cache=True, error_model="numpy")
def point_light_nee(kind, prm, nbox, nidx, tris, eps_t, stack, x, y, z, dcx, dcy, dcz, sigma_t, g, eta,
                    light_pos, light_int, light_cdf, sample_one, n_scan, nee_tau, u_rr, u_pick, sigma_t_eval):
    """Sum over lights (or one light drawn with probability proportional to its intensity, ``sample_one``, using
    ``u_pick``) of I p(cos) E_perp / I, each connection Russian-rouletted with ``u_rr`` (see
    :func:`_rouletted_contribution`) and evaluated at the extinction ``sigma_t_eval`` (normally ``sigma_t``)."""
    n = light_pos.shape[0]
    if n == 0:
        return 0.0
    if not sample_one:
        tot = 0.0
        for k in range(n):
            if light_int[k] > 0.0:
                tot += light_int[k] * _rouletted_contribution(
                    kind, prm, nbox, nidx, tris, eps_t, stack, x, y, z, dcx, dcy, dcz, light_pos[k, 0],
                    light_pos[k, 1], light_pos[k, 2], sigma_t, g, eta, n_scan, nee_tau, u_rr, sigma_t_eval)
        return tot
    lo, hi = 0, n - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if light_cdf[mid] < u_pick:
            lo = mid + 1
        else:
            hi = mid
    pmf = light_cdf[lo] - (light_cdf[lo - 1] if lo > 0 else 0.0)
    if pmf <= 0.0:
        return 0.0
    return light_int[lo] / pmf * _rouletted_contribution(
        kind, prm, nbox, nidx, tris, eps_t, stack, x, y, z, dcx, dcy, dcz, light_pos[lo, 0], light_pos[lo, 1],
        light_pos[lo, 2], sigma_t, g, eta, n_scan, nee_tau, u_rr, sigma_t_eval)
