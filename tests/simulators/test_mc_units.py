"""Unit tests of the Monte Carlo renderer's building blocks (simulators/mc): optics, random numbers, ray queries,
refracted next-event connections, API validation, and the calibration of the per-pixel standard error.

Tolerances: deterministic quantities are compared to rounding (1e-12) or to the truncation error of the method
they are checked against (finite differences: 1e-5 relative); sampled quantities to 4 standard errors."""
import math

import numpy as np
import pytest
import trimesh
from scipy import integrate
from numba import njit

from estimation.camera import PinholeCamera
from estimation.fresnel import fresnel_reflectance
from estimation.single_image import PointLights
from simulators.mc import (Box, GradientPattern, HalfSpace, Medium, Mesh, OrthographicCamera, Slab, Sphere,
                           render, uniform_environment)
from simulators.mc.nee import _sphere_f, light_contribution, plane_connection, sphere_connections
from simulators.mc.optics import fresnel_r, hg_phase, refract, sample_hg_cos
from simulators.mc.rng import stream, uniform
from simulators.mc.shapes import STACK_SIZE, nearest_hit


def test_fresnel_matches_estimation_fresnel():
    cos = np.linspace(0.0, 1.0, 201)
    for eta in (0.6, 1 / 1.4, 1.0, 1.3, 1.5, 2.4):
        ours = np.array([fresnel_r(eta, c) for c in cos])
        np.testing.assert_allclose(ours, fresnel_reflectance(eta, cos), atol=1e-12)


def test_refraction_obeys_snell_and_flags_total_internal_reflection():
    rng = np.random.default_rng(0)
    n = np.array([0.0, 0.0, 1.0])
    for _ in range(200):
        eta = rng.uniform(0.5, 2.5)
        th = rng.uniform(0, np.pi / 2 * 0.999)
        ph = rng.uniform(0, 2 * np.pi)
        d = np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), -np.cos(th)])  # towards -z
        ok, tx, ty, tz = refract(*d, *n, eta)
        if np.sin(th) / eta > 1:
            assert not ok
            continue
        assert ok and tz < 0
        t = np.array([tx, ty, tz])
        assert abs(np.linalg.norm(t) - 1) < 1e-12
        assert abs(eta * np.hypot(tx, ty) - np.sin(th)) < 1e-12       # n1 sin(i) = n2 sin(t)
        assert abs(np.cross(np.cross(d, n), np.cross(t, n)).sum()) < 1e-12  # same plane of incidence


@njit
def _sample_cos_moments(g, n, seed):
    s = stream(seed, 1, 2, 3)
    m1 = 0.0
    m2 = 0.0
    for _ in range(n):
        s, u = uniform(s)
        c = sample_hg_cos(g, u)
        m1 += c
        m2 += c * c
    return m1 / n, m2 / n


@pytest.mark.parametrize("g", [0.0, 0.3, 0.9, -0.5])
def test_henyey_greenstein_sampling_and_normalization(g):
    """<cos> = g and <cos^2> = (1 + 2 g^2)/3 for HG (Henyey & Greenstein 1941); the pdf integrates to 1."""
    n = 400_000
    m1, m2 = _sample_cos_moments(g, n, 7)
    var1 = m2 - m1 * m1
    assert abs(m1 - g) < 4 * math.sqrt(var1 / n) + 1e-12
    assert abs(m2 - (1 + 2 * g * g) / 3) < 4 * math.sqrt(1.0 / n)
    integral, _ = integrate.quad(lambda m: 2 * np.pi * hg_phase(g, m), -1, 1, points=[0.99], limit=200)
    assert abs(integral - 1) < 1e-9


@njit
def _uniform_moments(n, seed, a):
    s = stream(seed, a, 0, 0)
    m1 = 0.0
    m2 = 0.0
    lo = 1.0
    hi = 0.0
    for _ in range(n):
        s, u = uniform(s)
        m1 += u
        m2 += u * u
        lo = min(lo, u)
        hi = max(hi, u)
    return m1 / n, m2 / n, lo, hi


def test_random_streams_are_uniform_deterministic_and_distinct():
    n = 1_000_000
    m1, m2, lo, hi = _uniform_moments(n, 3, 0)
    assert 0 < lo and hi < 1
    assert abs(m1 - 0.5) < 4 * math.sqrt(1 / 12 / n)
    assert abs(m2 - 1 / 3) < 4 * math.sqrt(4 / 45 / n)
    assert _uniform_moments(1000, 3, 0) == _uniform_moments(1000, 3, 0)
    assert _uniform_moments(1000, 3, 0) != _uniform_moments(1000, 3, 1)
    assert _uniform_moments(1000, 3, 0) != _uniform_moments(1000, 4, 0)


def _query(shape, o, d):
    g = shape.geometry()
    st = np.empty(STACK_SIZE, np.int64)
    return nearest_hit(g.kind, g.params, g.nodes_box, g.nodes_idx, g.triangles, *o, *d, g.eps_t, st)


def _brute_force_hit(mesh, o, d):
    """Nearest ray-triangle hit over all faces (vectorized Moller-Trumbore, no acceleration structure)."""
    tri = mesh.triangles
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = o - tri[:, 0]
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        v = (q @ d) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
    ok = (det != 0) & (u >= 0) & (u <= 1) & (v >= 0) & (u + v <= 1) & (t > 1e-12)
    if not ok.any():
        return math.inf, None
    k = np.flatnonzero(ok)[np.argmin(t[ok])]
    return t[k], mesh.face_normals[k]


def test_mesh_bvh_hits_agree_with_brute_force_and_with_the_analytic_box():
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=2.0)
    box_mesh = trimesh.creation.box(extents=(2.0, 3.0, 4.0))
    ours_sphere, ours_box, box = Mesh(mesh), Mesh(box_mesh), Box((-1, -1.5, -2), (1, 1.5, 2))
    rng = np.random.default_rng(1)
    n_hit = 0
    for _ in range(150):
        o = rng.normal(size=3)
        o = 6 * o / np.linalg.norm(o)
        d = -o / np.linalg.norm(o) + 0.25 * rng.normal(size=3)
        d /= np.linalg.norm(d)
        for start in (o, 0.2 * o):  # from outside, and from inside the icosphere
            t, *nrm = _query(ours_sphere, start, d)
            t_ref, n_ref = _brute_force_hit(mesh, start, d)
            if t_ref == math.inf:
                assert t == math.inf
            else:
                n_hit += 1
                assert abs(t - t_ref) < 1e-9
                np.testing.assert_allclose(nrm, n_ref, atol=1e-9)
        tb, *nb = _query(ours_box, o, d)
        ta, *na = _query(box, o, d)
        assert (tb == math.inf and ta == math.inf) or (abs(tb - ta) < 1e-9 and np.allclose(nb, na))
        if ta < math.inf:  # from inside towards the far wall
            p = o + (ta + 1e-6) * d
            t_in, *n_in = _query(box, p, d)
            t_in_m, *n_in_m = _query(ours_box, p, d)
            assert abs(t_in - t_in_m) < 1e-9 and np.dot(n_in, d) > 0
    assert n_hit > 200


def test_analytic_shapes_report_outward_normals_from_both_sides():
    cases = [(HalfSpace(0.0), (0, 0, -1.0)), (Slab(2.0), (0, 0, -1.0)), (Sphere((1, 2, 3), 2.0), (1, 2, 3)),
             (Box((-1, -1, -1), (1, 2, 3)), (0, 0, 0))]
    for shape, inside in cases:
        rng = np.random.default_rng(2)
        for _ in range(50):
            d = rng.normal(size=3)
            d /= np.linalg.norm(d)
            t, *n = _query(shape, np.asarray(inside, float), d)
            if t == math.inf:
                assert isinstance(shape, HalfSpace) and d[2] <= 0
                continue
            assert np.dot(n, d) > 0  # leaving: along the outward normal
            p = np.asarray(inside) + t * d
            t2, *n2 = _query(shape, p + 5 * d, -d)  # back in from outside
            assert abs(t2 - 5) < 1e-9 and np.dot(n2, -d) < 0


def _fd_tube_area_plane(L, x, eta, b, step=1e-6):
    """dA_perp/dOmega by central differences of rays from L refracted by the plane z = 0."""
    n = np.array([0.0, 0.0, 1.0])
    i0 = (b - L) / np.linalg.norm(b - L)
    u0 = (x - b) / np.linalg.norm(x - b)
    a1 = np.cross(i0, [0.3, 0.5, 0.7])
    a1 /= np.linalg.norm(a1)
    a2 = np.cross(i0, a1)

    def point(v):
        d = v / np.linalg.norm(v)
        h = L + (-L[2] / d[2]) * d
        ok, *t = refract(*d, *n, eta)
        t = np.asarray(t)
        s = np.dot(x - h, u0) / np.dot(t, u0)
        return h + s * t

    g1 = (point(i0 + step * a1) - point(i0 - step * a1)) / (2 * step)
    g2 = (point(i0 + step * a2) - point(i0 - step * a2)) / (2 * step)
    return np.linalg.norm(np.cross(g1, g2))


def test_planar_refracted_connection_closed_form():
    """Snell's law holds at the connection point, J = |L - x|^2 at eta = 1, and the closed-form J agrees with
    finite differences of the refracted ray tube (relative 1e-5)."""
    rng = np.random.default_rng(3)
    for _ in range(40):
        L = np.array([*rng.normal(size=2) * 20, rng.uniform(0.5, 50)])
        x = np.array([*rng.normal(size=2) * 5, -rng.uniform(0.01, 5)])
        for eta in (1.0, 1.33, 1.5, 0.8):
            ok, bx, by, bz, J, c1, l_in = plane_connection(0, 0, 0, 0, 0, 1.0, *x, *L, eta)
            assert ok
            b = np.array([bx, by, bz])
            i = (b - L) / np.linalg.norm(b - L)
            t = (x - b) / np.linalg.norm(x - b)
            assert abs(np.hypot(*i[:2]) - eta * np.hypot(*t[:2])) < 1e-9          # sin1 = eta sin2
            assert np.dot(np.cross(i, t), [0, 0, 1]) == pytest.approx(0, abs=1e-9)  # coplanar with the normal
            assert abs(l_in - np.linalg.norm(x - b)) < 1e-9 and abs(c1 + i[2]) < 1e-12
            if eta == 1.0:
                assert J == pytest.approx(np.sum((L - x) ** 2), rel=1e-10)
            if abs(np.hypot(*(b - x)[:2])) > 1e-3:
                assert J == pytest.approx(_fd_tube_area_plane(L, x, eta, b), rel=1e-5)


def test_sphere_connections_reduce_to_plane_and_to_straight_line():
    """A sphere of radius 1e5 seen from 10 mm looks flat (agreement with the planar solution to 1e-3); with
    eta -> 1 the refracted connection tends to the straight one (eta = 1 + 1e-7: relative 1e-5)."""
    geo_hs = HalfSpace(0.0).geometry()
    st = np.empty(STACK_SIZE, np.int64)
    R = 1e5
    rng = np.random.default_rng(4)
    for _ in range(20):
        L = np.array([*rng.normal(size=2) * 5, rng.uniform(2, 10)])
        x = np.array([*rng.normal(size=2), -rng.uniform(0.05, 2)])
        dc = rng.normal(size=3)
        dc /= np.linalg.norm(dc)
        plane = light_contribution(geo_hs.kind, geo_hs.params, geo_hs.nodes_box, geo_hs.nodes_idx,
                                   geo_hs.triangles, geo_hs.eps_t, st, *x, *dc, *L, 1.0, 0.3, 1.4, 32)
        sph = sphere_connections(0, 0, -R, R, *x, *L, 1.4, 1.0, 0.3, *dc, 32)
        assert sph == pytest.approx(plane, rel=1e-3)
    geo = Sphere((0, 0, 0), 2.0).geometry()
    for _ in range(20):
        L = rng.normal(size=3)
        L = L / np.linalg.norm(L) * rng.uniform(2.5, 20)
        x = rng.normal(size=3)
        x = x / np.linalg.norm(x) * rng.uniform(0, 1.9)
        dc = rng.normal(size=3)
        dc /= np.linalg.norm(dc)
        straight = light_contribution(geo.kind, geo.params, geo.nodes_box, geo.nodes_idx, geo.triangles,
                                      geo.eps_t, st, *x, *dc, *L, 0.7, 0.5, 1.0, 32)
        nearly = sphere_connections(0, 0, 0, 2.0, *x, *L, 1.0 + 1e-7, 0.7, 0.5, *dc, 32)
        assert nearly == pytest.approx(straight, rel=1e-5)


def test_sphere_has_one_refraction_point_in_the_bracket_used():
    """For a vertex within the visible cap's cone (psi <= phi_v) the Snell residual has exactly one root on the
    visible arc and it lies in [0, psi] -- the fast path of nee.sphere_connections relies on it."""
    rng = np.random.default_rng(5)
    for _ in range(250):
        D = 1.0 + 10 ** rng.uniform(-3, 2)
        phiv = math.acos(1 / D) * (1 - 1e-9)
        r = rng.uniform(0, 1) ** (1 / 3)
        psi = rng.uniform(0, phiv)
        x1, x2 = r * math.cos(psi), r * math.sin(psi)
        eta = float(rng.choice([0.5, 0.8, 1.1, 1.3, 1.5, 2.0, 3.0]))
        ph = np.linspace(-phiv, phiv, 801)
        f = np.array([_sphere_f(p, 1.0, D, x1, x2, eta) for p in ph])
        roots = ph[np.flatnonzero(np.sign(f[1:]) != np.sign(f[:-1]))]
        assert len(roots) == 1 and -2e-3 <= roots[0] <= psi + 2e-3


def test_render_validates_its_inputs():
    cam = PinholeCamera.looking_at(width_px=4, height_px=4, fx_px=10, position_mm=(0, -10, 0), target_mm=(0, 0, 0))
    m = Medium(1.0, 0.1, 0.0, 1.3)
    with pytest.raises(ValueError, match="outside"):
        render(Sphere((0, 0, 0), 1.0), m, cam, PointLights([[0, 0, 0.5]], [1.0]), spp=2)
    with pytest.raises(ValueError, match="eta"):
        render(Sphere((0, 0, 0), 1.0), [m, Medium(1.0, 0.1, 0.0, 1.5)], cam, uniform_environment(), spp=2)
    with pytest.raises(ValueError, match="watertight"):
        Mesh(trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0], [0, 1, 0]], faces=[[0, 1, 2]]))
    with pytest.raises(ValueError):
        Medium(1.0, 0.1, g=1.0)
    with pytest.raises(ValueError):
        GradientPattern("w")
    with pytest.raises(TypeError):
        render(Sphere((0, 0, 0), 1.0), m, cam, "sun", spp=2)


def test_per_pixel_standard_error_predicts_the_spread_between_seeds():
    """z = (I_seed1 - I_seed2) / sqrt(se1^2 + se2^2) over ~190 lit pixels must have a standard deviation near 1
    (accepted 0.75-1.3: the sampling spread of a standard deviation from ~190 values is ~0.05, and spp = 64
    standard errors are themselves estimated to ~10%)."""
    cam = OrthographicCamera.looking_at(width_px=16, height_px=16, pixel_size_mm=0.35, direction=(0.2, 0.3, -1.0),
                                        up=(0, 1, 0))
    m = Medium.from_reduced(1.0, 0.02, g=0.5, eta=1.3)
    lights = PointLights([[1.0, -2.0, 4.0]], [20.0])
    a = render(Sphere((0, 0, -3), 3.0), m, cam, lights, spp=64, seed=1)
    b = render(Sphere((0, 0, -3), 3.0), m, cam, lights, spp=64, seed=2)
    ok = a.mask & (a.radiance[..., 0] > 0) & (a.stderr[..., 0] > 0)
    z = (a.radiance - b.radiance)[ok, 0] / np.hypot(a.stderr, b.stderr)[ok, 0]
    assert ok.sum() > 150
    assert 0.75 < np.std(z) < 1.3
    assert abs(np.mean(z)) < 4 / math.sqrt(ok.sum()) * 1.3


def test_mesh_inside_test_by_crossing_parity():
    """Non-convex annulus: the hole and points above it are outside, the ring inside (no rtree/embree needed)."""
    m = Mesh(trimesh.creation.annulus(r_min=2.0, r_max=5.0, height=2.0))
    inside = m.contains([[0, 0, 0], [3.5, 0, 0], [0, -3.5, 0.5], [0, 0, 3], [6, 0, 0], [-4.9, 0, -0.9]])
    assert inside.tolist() == [False, True, True, False, False, True]
    cam = PinholeCamera.looking_at(width_px=4, height_px=4, fx_px=10, position_mm=(0, -20, 0), target_mm=(0, 0, 0))
    with pytest.raises(ValueError, match="outside"):
        render(m, Medium(1.0, 0.1), cam, PointLights([[3.5, 0, 0]], [1.0]), spp=2)
    img = render(m, Medium(1.0, 0.1), cam, PointLights([[0, 0, 0]], [1.0]), spp=2)  # light in the hole: fine
    assert np.all(np.isfinite(img.radiance))


def test_environment_map_orientation_matches_the_gradient_patterns():
    """Lat-long convention of estimation.single_image.EnvironmentMap (row 0 = +z, azimuth from +x towards +y): a map
    rasterizing (w_i + 1)/2 renders like the analytic pattern "x"/"y"/"z" (same seed, so the same paths; the only
    difference is the map's piecewise-constant discretization, <= 0.5 * 2 pi / 512 ~ 0.006), while the pattern and
    its complement differ by O(0.1)."""
    from estimation.single_image import EnvironmentMap

    h, w = 256, 512
    th = np.pi * (np.arange(h) + 0.5) / h
    ph = 2 * np.pi * (np.arange(w) + 0.5) / w
    T, P = np.meshgrid(th, ph, indexing="ij")
    dirs = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1)
    cam = PinholeCamera.looking_at(width_px=8, height_px=8, fx_px=12, position_mm=(3, -20, 6), target_mm=(0, 0, 0))
    m = Medium.from_reduced(1.0, 0.05, g=0.3, eta=1.3)
    sph = Sphere((0, 0, 0), 4.0)
    for axis, name in enumerate("xyz"):
        env = EnvironmentMap((dirs[..., axis] + 1) / 2)
        a = render(sph, m, cam, env, spp=4, seed=3)
        b = render(sph, m, cam, GradientPattern(name), spp=4, seed=3)
        c = render(sph, m, cam, GradientPattern(name + "_c"), spp=4, seed=3)
        assert np.max(np.abs(a.radiance - b.radiance)) < 0.01
        assert np.max(np.abs(c.radiance - b.radiance)) > 0.05


def test_bounded_query_is_the_nearest_crossing_below_t_max():
    """nearest_hit_below (the walk's query, bounded by the sampled free flight): the same crossing and normal as
    nearest_hit when it is closer than t_max, infinity for a mesh when it is not; analytic shapes answer exactly as
    nearest_hit."""
    from simulators.mc.shapes import nearest_hit_below

    mesh = Mesh(trimesh.creation.icosphere(subdivisions=3, radius=2.0))
    sphere = Sphere((0.0, 0.0, 0.0), 2.0)
    stack = np.zeros(STACK_SIZE, dtype=np.int64)
    rng = np.random.default_rng(5)
    n_below = n_above = 0
    for _ in range(200):
        o = rng.uniform(-1.2, 1.2, 3)
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        t_max = float(rng.uniform(0.05, 4.0))
        for shape in (mesh, sphere):
            g = shape.geometry()
            args = (g.kind, g.params, g.nodes_box, g.nodes_idx, g.triangles, *o, *d, g.eps_t, stack)
            t, *n = nearest_hit(*args)
            tb, *nb = nearest_hit_below(*args, t_max)
            if t < t_max or shape is sphere:
                assert tb == t and nb == n
                n_below += shape is mesh
            else:
                assert tb == math.inf
                n_above += 1
    assert n_below > 20 and n_above > 20
