"""Point lights through a refracting (eta != 1) CONVEX triangle mesh (issue 8 item 5): simulators.mc.nee
``mesh_connections`` -- one refracted connection per triangle that faces the light, kept iff its refraction point
lies in the triangle (Mitchell & Hanrahan 1992 generalized geometry term, as for the analytic box).

Checks:
1. deterministic: the mesh connections of a box given as a triangle mesh equal the analytic Box's (to rounding),
   also for the box rotated off the axes (generic face planes) and subdivided (32 coplanar triangles per face),
   and the mesh's roulette bound (min_inside_length) is never below the box's, i.e. still a lower bound of |x - b|;
2. deterministic, independent: at eta = 1 + 1e-9 the refracted connections through a pyramid equal the eta = 1
   straight-line connections with BVH occlusion (a different code path) -- one face per line, no coplanar
   double counting, no gaps;
3. Monte Carlo: images of the box as a mesh and as the analytic Box under the same point light at eta 1.3
   (independent seeds) agree within their standard errors (pixel z-scores, total ratio within 4 standard errors);
4. a pyramid mesh at eta 1.3 renders finite and non-negative, and at eta = 1 + 1e-6 matches the eta = 1 render of
   the same seed with every connection evaluated (nee_tau -> 0; the paths are the same up to Fresnel events of
   probability ~1e-13);
5. a non-convex mesh of more than MAX_CONNECTION_PLANES face planes + point light + eta 1.3 raises ValueError; the
   MC capture bridge uses point lights for convex meshes and non-convex ones of few planes, and falls back to
   distant light beyond (non-convex meshes of few planes: tests/simulators/test_mc_nonconvex_point_light.py).

Timing (2 shared cores, numba caches warm): ~1-3 s per test; a cold numba cache adds ~40-60 s of compilation to the
first render test.
"""
import math

import numpy as np
import pytest
import trimesh

from estimation.camera import PinholeCamera
from estimation.single_image import PointLights
from simulators.mc import Box, Medium, Mesh, render
from simulators.mc.nee import light_contribution, min_inside_length
from simulators.mc.shapes import BVH_CONNECTIONS, MAX_CONNECTION_PLANES, PLANE_TABLE, STACK_SIZE
from test_mc_frames_single_image import pyramid_mesh

LO_MM = np.array([-2.0, -3.0, -2.5])
HI_MM = np.array([2.0, 3.0, 2.5])


def _pyramid() -> trimesh.Trimesh:
    """A 6 mm square pyramid, 4.5 mm high, centroid at the origin."""
    return pyramid_mesh(6.0, 4.5)


def _rotation(seed):
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _contribution(geo, x, d, light, sigma_t, g, eta):
    stack = np.empty(STACK_SIZE, np.int64)
    return light_contribution(geo.kind, geo.params, geo.nodes_box, geo.nodes_idx, geo.triangles, geo.eps_t, stack,
                              *x, *d, *light, sigma_t, g, eta, 32)


def _random_configuration(rng, contains):
    while True:
        x = rng.uniform(LO_MM, HI_MM)
        if contains(x):
            break
    light = rng.normal(size=3)
    light *= rng.uniform(6.0, 30.0) / np.linalg.norm(light)
    d = rng.normal(size=3)
    return x, d / np.linalg.norm(d), light, rng.uniform(0.1, 2.0), rng.uniform(-0.5, 0.8)


def test_box_mesh_connections_equal_the_analytic_box_also_rotated():
    box = Box(tuple(LO_MM), tuple(HI_MM))
    gb = box.geometry()
    rot = _rotation(3)
    mesh = trimesh.creation.box(extents=HI_MM - LO_MM)
    rotated = mesh.copy()
    rotated.apply_transform(np.block([[rot, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]))
    fine = mesh.subdivide().subdivide()                       # 192 triangles, 32 per flat face
    gm, gr, gf = Mesh(mesh).geometry(), Mesh(rotated).geometry(), Mesh(fine).geometry()
    assert gm.convex and gr.convex and gf.convex
    assert gm.params[0] == gr.params[0] == gf.params[0] == 6    # coplanar triangles merged into 6 faces
    rng = np.random.default_rng(0)
    n_lit = 0
    for _ in range(1500):
        x, d, light, sigma_t, g = _random_configuration(rng, lambda p: True)
        eta = float(rng.choice([0.7, 1.3, 1.5]))
        ref = _contribution(gb, x, d, light, sigma_t, g, eta)
        n_lit += ref > 0
        assert _contribution(gm, x, d, light, sigma_t, g, eta) == pytest.approx(ref, rel=1e-12, abs=1e-300)
        assert _contribution(gf, x, d, light, sigma_t, g, eta) == pytest.approx(ref, rel=1e-12, abs=1e-300)
        assert _contribution(gr, rot @ x, rot @ d, rot @ light, sigma_t, g, eta) == pytest.approx(ref, rel=1e-9,
                                                                                                abs=1e-300)
        assert (min_inside_length(gm.kind, gm.params, *x, *light, eta)
                >= min_inside_length(gb.kind, gb.params, *x, *light, eta) - 1e-12)
    assert n_lit > 1000


def test_pyramid_connections_at_eta_near_one_equal_the_straight_line_connections():
    """eta = 1 + 1e-9: b is on the straight line x-L to ~1e-9, J = |L - x|^2 (1 + O(1e-9)), F_t = 1 except within
    ~1e-4 rad of grazing; the eta = 1 branch ray-casts the BVH instead (exact occlusion)."""
    pyr = Mesh(_pyramid())
    geo = pyr.geometry()
    assert geo.convex
    rng = np.random.default_rng(1)
    n_lit = 0
    for _ in range(1500):
        x, d, light, sigma_t, g = _random_configuration(rng, lambda p: bool(pyr.contains(p)[0]))
        ref = _contribution(geo, x, d, light, sigma_t, g, 1.0)
        n_lit += ref > 0
        assert _contribution(geo, x, d, light, sigma_t, g, 1.0 + 1e-9) == pytest.approx(ref, rel=1e-6, abs=1e-300)
    assert n_lit > 1000


def _camera(n_px):
    return PinholeCamera.looking_at(width_px=n_px, height_px=n_px, fx_px=1.6 * n_px, position_mm=(9, -12, 10),
                                    target_mm=(0, 0, 0))


def test_box_mesh_image_matches_the_analytic_box_under_a_point_light_at_eta_1_3():
    """Independent seeds; per pixel z = (mesh - box) / sqrt(se_mesh^2 + se_box^2). Measured (32 x 32 px, 512 spp,
    344 pixels, per-pixel relative se 4.5 %; seed pairs (3, 4), (10, 11), (20, 21), (30, 31)): z mean -0.04,
    +0.10, +0.03, +0.03; z sd 1.01, 1.06, 0.96, 0.98; total ratio 0.9960, 1.0060, 1.0014, 1.0034 (+- 0.0036,
    1 se); median pixel ratio 0.997, 1.006, 0.999, 1.000."""
    cam = _camera(32)
    light = PointLights([[-6.0, -8.0, 9.0]], [100.0])   # lights the -x, -y, +z faces; the camera sees +x, -y, +z
    medium = Medium.from_reduced(1.0, 0.02, eta=1.3)
    a = render(Box(tuple(LO_MM), tuple(HI_MM)), medium, cam, light, spp=512, seed=3)
    b = render(Mesh(trimesh.creation.box(extents=HI_MM - LO_MM)), medium, cam, light, spp=512, seed=4)
    mask = a.mask & b.mask
    assert np.array_equal(a.mask, b.mask) and mask.sum() > 300
    ra, rb = a.radiance[mask, 0], b.radiance[mask, 0]
    se = np.hypot(a.stderr[mask, 0], b.stderr[mask, 0])
    assert np.all(ra > 0) and np.all(rb > 0) and a.truncated_fraction == b.truncated_fraction == 0
    z = (rb - ra) / se
    ratio = rb.sum() / ra.sum()
    ratio_se = math.sqrt(float(np.sum(se ** 2))) / ra.sum()
    print(f"mesh box vs Box: z mean {z.mean():+.3f}, z sd {z.std():.3f} ({len(z)} px), total ratio {ratio:.4f} "
          f"+- {ratio_se:.4f}, median pixel ratio {np.median(rb / ra):.4f}; {a.seconds:.1f} s + {b.seconds:.1f} s")
    assert abs(z.mean()) < 4 / math.sqrt(len(z))          # 4 standard errors of a mean of unit-variance z
    assert 0.8 < z.std() < 1.25                             # the standard errors are calibrated for both
    assert abs(ratio - 1) < 4 * ratio_se
    assert abs(np.median(rb / ra) - 1) < 0.02               # ~4.5 se of the median (6.4 % per pixel difference)


def test_pyramid_under_a_point_light_at_eta_1_3_and_its_eta_1_limit():
    pyr = Mesh(_pyramid())
    cam = _camera(24)
    light = PointLights([[-6.0, -8.0, 9.0]], [100.0])
    img = render(pyr, Medium.from_reduced(1.0, 0.02, eta=1.3), cam, light, spp=64, seed=1)
    rad = img.radiance[img.mask, 0]
    assert img.mask.sum() > 100 and np.all(np.isfinite(rad)) and np.all(rad >= 0) and np.mean(rad > 0) > 0.99
    assert np.all(np.isfinite(img.stderr[img.mask]))
    # nee_tau -> 0: every connection is evaluated (the two branches' roulette bounds differ)
    one = render(pyr, Medium.from_reduced(1.0, 0.02, eta=1.0), cam, light, spp=64, seed=1, nee_tau=1e-30)
    near = render(pyr, Medium.from_reduced(1.0, 0.02, eta=1.0 + 1e-6), cam, light, spp=64, seed=1, nee_tau=1e-30)
    m = one.mask
    rel = np.abs(near.radiance[m, 0] - one.radiance[m, 0]) / one.radiance[m, 0]
    print(f"pyramid eta 1.3: mean radiance {rad.mean():.4g}; eta 1+1e-6 vs 1: max rel diff {rel.max():.2e}, "
          f"median rel se {np.median(one.stderr[m, 0] / one.radiance[m, 0]):.3f}")
    assert rel.max() < 1e-4


def test_non_convex_mesh_of_many_planes_with_point_lights_and_eta_renders():
    """Non-convex meshes of few face planes are connected plane by plane (tests/simulators/
    test_mc_nonconvex_point_light.py); beyond MAX_CONNECTION_PLANES distinct planes (refused before issue 17's
    BVH connections) through the triangles the BVH finds near each vertex (tests/simulators/
    test_mc_bvh_connections.py)."""
    annulus = Mesh(trimesh.creation.annulus(r_min=2.0, r_max=5.0, height=2.0, sections=2 * MAX_CONNECTION_PLANES))
    assert not annulus.geometry().convex
    cam = _camera(4)
    light = PointLights([[0.0, -9.0, 3.0]], [1.0])
    for eta in (1.3, 1.0):                                  # eta = 1: exact occlusion by straight segments
        img = render(annulus, Medium(1.0, 0.1, 0.0, eta), cam, light, spp=2)
        assert np.all(np.isfinite(img.radiance)) and img.radiance[img.mask].max() > 0


def test_capture_bridge_uses_point_lights_for_any_mesh():
    from simulators.mc_capture import MCSettings, led_lights, mc_shape
    from simulators.scene import MeshObject

    pos, em = np.array([[0.0, -300.0, 300.0]]), np.ones((1, 3))
    many = trimesh.creation.annulus(r_min=2.0, r_max=5.0, height=2.0, sections=2 * MAX_CONNECTION_PLANES)
    # a convex mesh (face table), a non-convex one of few planes (plane table), one of many (BVH connections)
    for mesh, table in ((_pyramid(), 0.0), (trimesh.creation.annulus(r_min=2.0, r_max=5.0, height=2.0), PLANE_TABLE),
                        (many, BVH_CONNECTIONS)):
        obj = MeshObject(mesh, (1.0,) * 3, (0.02,) * 3, 1.3)
        shape = mc_shape(obj)
        assert isinstance(shape, Mesh)
        assert shape.geometry().params[1] == table
        assert led_lights(obj, shape, pos, em, MCSettings())[1] == "points"   # the many-plane one too (issue 17)
