"""Point lights through a refracting (eta != 1) NON-CONVEX triangle mesh (issue 17 part 3):
simulators.mc.nee ``nonconvex_mesh_connections`` -- one closed-form refracted connection per face plane that faces
the light, kept iff a shadow ray inside (x -> b meets the boundary first at b, on a face of that plane) and one
outside (b -> L meets nothing) confirm it.

Checks:
1. deterministic, against the existing convex path: on convex meshes (a subdivided box, a rotated pyramid) the
   plane-table connections with shadow rays equal the convex face-table connections (to rounding);
2. deterministic, against an independent code path: on the L-block at eta = 1 + 1e-9 they equal the eta = 1
   straight-line connections (BVH occlusion, exact) wherever the straight segment x -> L crosses the boundary once,
   and are 0 where it crosses more than once (shadowed, or through the wall: the multi-crossing chains the
   estimator does not capture at eta != 1, module docstring of simulators.mc.nee; their share of the eta = 1
   connections is printed);
3. Monte Carlo, against the existing convex path: a box mesh plus a tiny far tetrahedron (non-convex: plane table)
   renders the same image as the box mesh alone (face table) at eta 1.3 within the standard errors;
4. Monte Carlo, independent brute force: the L-block at eta 1.3 under one pixel of an environment map, rendered by
   plain path tracing (escaping walks look the map up; no light sampling for refracting non-convex meshes), equals
   the render under 16 far point lights that stratify the pixel's solid angle (next-event estimation through the
   new connections), within the standard errors;
5. the L-block under a point light at eta 1.3: dark where the wall shadows the slab's top (x < 17 mm by the
   geometry), lit beyond;
6. a non-convex mesh of more than MAX_CONNECTION_PLANES face planes gets no plane table (it is connected by the
   BVH search instead, tests/simulators/test_mc_bvh_connections.py).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from estimation.camera import OrthographicCamera, PinholeCamera
from estimation.single_image import EnvironmentMap, PointLights
from simulators.mc import Medium, Mesh, render
from simulators.mc.nee import light_contribution, min_inside_length
from simulators.mc.shapes import (BVH_CONNECTIONS, MAX_CONNECTION_PLANES, MESH, STACK_SIZE, nearest_hit,
                                  plane_table)
from simulators.scene import wall_on_slab_mesh
from test_mc_frames_single_image import pyramid_mesh


def _contribution(geo, x, d, light, sigma_t, g, eta):
    stack = np.empty(STACK_SIZE, np.int64)
    return light_contribution(geo.kind, geo.params, geo.nodes_box, geo.nodes_idx, geo.triangles, geo.eps_t, stack,
                              *x, *d, *light, sigma_t, g, eta, 32)


def _crossings(geo, x, light) -> int:
    """Boundary crossings of the segment x -> light (BVH)."""
    stack = np.empty(STACK_SIZE, np.int64)
    u = np.asarray(light, float) - x
    dist = float(np.linalg.norm(u))
    u /= dist
    p, n, left = np.asarray(x, float), 0, dist
    while True:
        t, *_ = nearest_hit(geo.kind, geo.params, geo.nodes_box, geo.nodes_idx, geo.triangles, *p, *u, geo.eps_t,
                            stack)
        if t >= left:
            return n
        n += 1
        p = p + t * u
        left -= t


def _as_plane_table(mesh: trimesh.Trimesh):
    geo = Mesh(mesh).geometry()
    assert geo.convex
    f = np.asarray(mesh.faces) if float(mesh.volume) > 0 else np.asarray(mesh.faces)[:, ::-1]
    table = plane_table(np.asarray(mesh.vertices, float), f)
    return geo, geo._replace(params=table, convex=False)


def test_plane_table_connections_equal_the_convex_face_table():
    rot, _ = np.linalg.qr(np.random.default_rng(5).normal(size=(3, 3)))
    rot *= np.sign(np.linalg.det(rot))
    pyr = pyramid_mesh(6.0, 4.5)
    pyr.apply_transform(np.block([[rot, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]))
    rng = np.random.default_rng(0)
    for mesh in (trimesh.creation.box(extents=(4.0, 6.0, 5.0)).subdivide().subdivide(), pyr):
        conv, planes = _as_plane_table(mesh)
        assert planes.params[0] == conv.params[0]           # the same flat faces: 6 (box), 5 (pyramid)
        inside = Mesh(mesh)
        n_lit = 0
        for _ in range(800):
            while True:
                x = rng.uniform(mesh.bounds[0], mesh.bounds[1])
                if inside.contains(x)[0]:
                    break
            light = rng.normal(size=3)
            light *= rng.uniform(8.0, 30.0) / np.linalg.norm(light)
            d = rng.normal(size=3)
            d /= np.linalg.norm(d)
            sigma_t, g, eta = rng.uniform(0.1, 2.0), rng.uniform(-0.5, 0.8), float(rng.choice([0.7, 1.3, 1.5]))
            ref = _contribution(conv, x, d, light, sigma_t, g, eta)
            n_lit += ref > 0
            assert _contribution(planes, x, d, light, sigma_t, g, eta) == pytest.approx(ref, rel=1e-9, abs=1e-300)
            # the plane table's roulette bound (no edges) is still a lower bound: never above the face table's
            assert (min_inside_length(MESH, planes.params, *x, *light, eta)
                    <= min_inside_length(MESH, conv.params, *x, *light, eta) + 1e-12)
        assert n_lit > 400


def test_l_block_connections_at_eta_near_one_equal_the_straight_line_connections():
    """eta = 1 + 1e-9: b lies on the straight line to ~1e-9 and J = |L - x|^2 (1 + O(1e-9 / cos^k)); the eta = 1 branch
    ray-casts the segment instead and sums its pieces inside (exact occlusion, light through the wall included)."""
    block = Mesh(wall_on_slab_mesh())
    geo = block.geometry()
    assert not geo.convex and geo.params[0] == 8             # 8 face planes: 6 sides of the L + 2 caps
    rng = np.random.default_rng(2)
    n_one = n_multi = 0
    multi_share = []
    for _ in range(1500):
        while True:
            x = rng.uniform((0.0, -10.0, 0.0), (30.0, 10.0, 20.0))
            if block.contains(x)[0]:
                break
        while True:
            light = rng.uniform((-60.0, -40.0, -20.0), (90.0, 40.0, 80.0))
            if not block.contains(light)[0]:
                break
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        sigma_t, g = rng.uniform(0.05, 0.5), rng.uniform(-0.5, 0.8)
        ref = _contribution(geo, x, d, light, sigma_t, g, 1.0)
        new = _contribution(geo, x, d, light, sigma_t, g, 1.0 + 1e-9)
        if _crossings(geo, x, light) == 1:
            n_one += 1
            # measured: max relative difference 1.0e-5, at exits ~1.3 deg from grazing (J and F_t at eta = 1 + 1e-9
            # there carry 1e-9 / cos^k); a wrong face, occlusion or geometry term would be O(1)
            assert new == pytest.approx(ref, rel=1e-4, abs=1e-300)
        else:
            n_multi += 1
            assert new == 0.0
            multi_share.append(ref)
    print(f"L-block: {n_one} single-crossing connections equal, {n_multi} multi-crossing ones 0 at eta != 1 "
          f"(at eta = 1 they carry {np.mean(np.asarray(multi_share) > 0):.2f} > 0, at sigma_t 0.05-0.5 / mm)")
    assert n_one > 1000 and n_multi > 100             # measured 1352 and 148


def _camera(n_px: int) -> PinholeCamera:
    return PinholeCamera.looking_at(width_px=n_px, height_px=n_px, fx_px=1.6 * n_px, position_mm=(9, -12, 10),
                                    target_mm=(0, 0, 0))


def test_box_with_a_far_speck_renders_like_the_convex_box():
    """Independent seeds; per pixel z = (plane table - face table) / sqrt(se^2 + se^2)."""
    box = trimesh.creation.box(extents=(4.0, 6.0, 5.0))
    speck = trimesh.creation.box(extents=(0.01, 0.01, 0.01))
    speck.apply_translation((0.0, 60.0, -60.0))             # behind the box, away from the light and camera
    both = trimesh.util.concatenate([box, speck])
    g2 = Mesh(both).geometry()
    assert not g2.convex and g2.params[0] == 12
    cam = _camera(32)
    light = PointLights([[-6.0, -8.0, 9.0]], [100.0])
    medium = Medium.from_reduced(1.0, 0.02, eta=1.3)
    a = render(Mesh(box), medium, cam, light, spp=256, seed=3)
    b = render(Mesh(both), medium, cam, light, spp=256, seed=4)
    mask = a.mask & b.mask
    assert np.array_equal(a.mask, b.mask) and mask.sum() > 300
    ra, rb = a.radiance[mask, 0], b.radiance[mask, 0]
    se = np.hypot(a.stderr[mask, 0], b.stderr[mask, 0])
    assert np.all(ra > 0) and np.all(rb > 0)
    z = (rb - ra) / se
    ratio = rb.sum() / ra.sum()
    ratio_se = math.sqrt(float(np.sum(se ** 2))) / ra.sum()
    print(f"box + speck (plane table) vs box (face table): z mean {z.mean():+.3f}, z sd {z.std():.3f} "
          f"({len(z)} px), total ratio {ratio:.4f} +- {ratio_se:.4f}; {a.seconds:.1f} s + {b.seconds:.1f} s")
    assert abs(z.mean()) < 4 / math.sqrt(len(z))
    assert 0.8 < z.std() < 1.25
    assert abs(ratio - 1) < 4 * ratio_se


# the L-block's brute-force check: one pixel of a 12 x 24 lat-long map (15 deg), theta 30-45 deg, phi 180-195 deg
_ROWS, _COLS, _ROW, _COL = 12, 24, 2, 12
_MEDIUM = Medium(10.0, 2.5, 0.0, 1.3)                      # albedo 0.8: short walks; mean free path 0.08 mm
_L_CAM = PinholeCamera.looking_at(width_px=40, height_px=30, fx_px=100.0, position_mm=(70.0, -40.0, 80.0),
                                  target_mm=(18.0, 0.0, 6.0))


def _pixel_point_lights(radiance: float, k: int = 4, far_mm: float = 1e6) -> PointLights:
    """k x k far point lights at the centres of equal-solid-angle cells of the map pixel (uniform in cos theta and
    phi), each of intensity radiance x Omega / k^2 x far^2 (the irradiance of the pixel, split)."""
    c0, c1 = math.cos(math.pi * _ROW / _ROWS), math.cos(math.pi * (_ROW + 1) / _ROWS)
    p0, p1 = 2 * math.pi * _COL / _COLS, 2 * math.pi * (_COL + 1) / _COLS
    omega = (c0 - c1) * (p1 - p0)
    pos = []
    for i in range(k):
        ct = c0 + (i + 0.5) / k * (c1 - c0)
        st = math.sqrt(1 - ct * ct)
        for j in range(k):
            ph = p0 + (j + 0.5) / k * (p1 - p0)
            pos.append((far_mm * st * math.cos(ph), far_mm * st * math.sin(ph), far_mm * ct))
    return PointLights(np.array(pos), np.full(k * k, radiance * omega / k ** 2 * far_mm ** 2))


def test_l_block_point_lights_match_path_traced_map_pixel():
    """Measured (6144 / 128 spp, seed pairs (7, 8), (17, 18), (27, 28), (37, 38), (47, 48)): sigma_t = 12.5 / mm:
    0.986, 0.970, 1.027, 0.987, 1.018 (+- 0.015 each; at 4096 spp, this test: 0.968 +- 0.018); at sigma_t = 2.5 / mm
    (mean free path 0.4 mm), six pairs: mean 0.981 +- 0.006, 1.9 % low (an analytic box: 0.994 +- 0.006) --
    consistent with the estimator's documented blind spot (simulators.mc.nee), which scales with the mean free path:
    light refracted in near an edge that meets the next face unscattered and is totally reflected there (eta 1.3,
    37 deg incidence), which plain path tracing finds and a point light's connection cannot; the test uses the
    denser medium, where it is ~0.4 %."""
    env = np.zeros((_ROWS, _COLS, 1))
    env[_ROW, _COL] = 1.0
    block = Mesh(wall_on_slab_mesh())
    pt = render(block, _MEDIUM, _L_CAM, EnvironmentMap(env, max_size=_ROWS), spp=4096, seed=7)
    ne = render(block, _MEDIUM, _L_CAM, _pixel_point_lights(1.0), spp=128, seed=8,
                max_sampled_lights=16)
    m = pt.mask & ne.mask
    assert np.array_equal(pt.mask, ne.mask) and m.sum() > 400
    a, b = pt.radiance[m, 0], ne.radiance[m, 0]
    se_a, se_b = pt.stderr[m, 0], ne.stderr[m, 0]
    ratio = b.sum() / a.sum()
    ratio_se = math.sqrt(float(np.sum(se_a ** 2 + se_b ** 2))) / a.sum()
    # halves of the image (left: the wall's lit face and shadowed slab; right: lit slab) compared separately
    cols = np.nonzero(m)[1]
    half = cols < _L_CAM.width_px // 2
    halves = [(b[s].sum() / a[s].sum(), math.sqrt(float(np.sum(se_a[s] ** 2 + se_b[s] ** 2))) / a[s].sum())
              for s in (half, ~half)]
    print(f"L-block eta 1.3, map pixel: point lights / path traced = {ratio:.4f} +- {ratio_se:.4f} "
          f"(halves {halves[0][0]:.4f} +- {halves[0][1]:.4f}, {halves[1][0]:.4f} +- {halves[1][1]:.4f}); "
          f"{pt.seconds:.1f} s + {ne.seconds:.1f} s")
    assert ratio_se < 0.025
    assert abs(ratio - 1) < 4 * ratio_se
    for r, s in halves:
        assert abs(r - 1) < 4 * s


def test_l_block_shadow_at_eta_1_3_is_where_the_geometry_says():
    """Top-down orthographic view of the slab; light at (-40, 0, 100): the wall (x < 8 mm, up to z = 20 mm) shades
    the slab's top (z = 5 mm) for x < 8 + 15 x 48 / 80 = 17 mm."""
    cam = OrthographicCamera.looking_at(width_px=44, height_px=16, pixel_size_mm=0.5, direction=(0.0, 0.0, -1.0),
                                        target_mm=(19.0, 0.0, 5.0), up=(0.0, 1.0, 0.0))
    img = render(Mesh(wall_on_slab_mesh()), Medium(4.0, 0.2, 0.0, 1.3), cam,
                 PointLights(np.array([[-40.0, 0.0, 100.0]]), np.array([2e4])), spp=16, seed=5)
    o, _ = cam.pixel_rays()
    x = o[..., 0]
    rad = img.radiance[..., 0]
    assert img.mask.all()

    def band(lo: float, hi: float) -> float:
        return float(rad[(x > lo) & (x < hi)].mean())

    lit, deep, edge_in, edge_out = band(20.0, 30.0), band(9.0, 14.0), band(15.5, 16.5), band(17.5, 18.5)
    print(f"L-block eta 1.3 point light: slab top lit {lit:.4g}, deep shadow {deep:.3g} ({deep / lit:.2e}), "
          f"x 15.5-16.5 {edge_in / lit:.3f}, x 17.5-18.5 {edge_out / lit:.3f} of lit; {img.seconds:.1f} s")
    assert lit > 0 and deep < 0.01 * lit
    assert edge_in < 0.5 * lit < edge_out                    # the edge between 16 and 18 mm (l_d = 0.63 mm)


def test_many_face_planes_go_to_the_bvh_connections():
    """Beyond MAX_CONNECTION_PLANES planes no plane table is built (refused before issue 17; now the BVH
    connections, tests/simulators/test_mc_bvh_connections.py); an annulus of few sections keeps its table."""
    ring = trimesh.creation.annulus(r_min=2.0, r_max=5.0, height=2.0, sections=2 * MAX_CONNECTION_PLANES)
    fine = Mesh(ring)
    assert not fine.geometry().convex and fine.geometry().params[0] == 0
    assert fine.geometry().params[1] == BVH_CONNECTIONS
    light = PointLights([[0.0, -9.0, 3.0]], [1.0])
    coarse = Mesh(trimesh.creation.annulus(r_min=2.0, r_max=5.0, height=2.0, sections=16))
    assert coarse.geometry().params[0] == 34                 # 16 + 16 sides, top, bottom
    img = render(coarse, Medium(1.0, 0.1, 0.0, 1.3), _camera(8), light, spp=4)
    assert np.all(np.isfinite(img.radiance)) and img.radiance[img.mask].max() > 0
