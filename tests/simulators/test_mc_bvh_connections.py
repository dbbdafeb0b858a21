"""Point lights through a refracting NON-CONVEX mesh of any size (issue 17 part 3): simulators.mc.nee
``bvh_mesh_connections`` -- candidate triangles within the connection radius found by the mesh's BVH instead of
every face plane -- against the paths it generalizes.

Checks:
1. deterministic, against the all-planes path: on the L-block, the U-channel and a dented subdivided box (plane
   tables of 8-60 planes) the BVH connections equal ``nonconvex_mesh_connections`` at random interior points and
   lights (to rounding: same planes, same solutions, same shadow rays), with the radius set to hold the whole mesh
   and with the default radius (which drops connections lighter than CUTOFF = 1e-6 of their unattenuated weight);
2. deterministic, against the convex path: on a subdivided box and a rotated pyramid (face tables) the same;
3. a non-convex mesh of more than MAX_CONNECTION_PLANES planes (an annulus of 1,024 sections) at eta 1.3 under a
   point light is rendered (it was refused before: ValueError).
Render-level measurements (image means, per-pixel agreement, energy conservation on a displaced mesh) are in
benchmarks/mc_bvh_connections.py.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from estimation.camera import PinholeCamera
from estimation.single_image import PointLights
from simulators.mc import Medium, Mesh, render
from simulators.mc.nee import bvh_mesh_connections, connection_radius, light_contribution
from simulators.mc.shapes import (BVH_CONNECTIONS, MAX_CONNECTION_PLANES, PLANE_TABLE, STACK_SIZE, plane_table,
                                  refracted_point_lights_supported)
from simulators.scene import wall_on_slab_mesh
from test_mc_frames_single_image import pyramid_mesh

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from zoo.nonconvex import u_channel_mesh  # noqa: E402


def _contribution(geo, x, d, light, sigma_t, g, eta):
    stack = np.empty(STACK_SIZE, np.int64)
    return light_contribution(geo.kind, geo.params, geo.nodes_box, geo.nodes_idx, geo.triangles, geo.eps_t, stack,
                              *x, *d, *light, sigma_t, g, eta, 32)


def _bvh(geo, x, d, light, sigma_t, g, eta, radius):
    stack = np.empty(STACK_SIZE, np.int64)
    return bvh_mesh_connections(geo.params, geo.nodes_box, geo.nodes_idx, geo.triangles, geo.eps_t, stack, *x,
                                *light, eta, sigma_t, g, *d, radius)


def _forced_bvh(geo):
    return geo._replace(params=np.array([0.0, BVH_CONNECTIONS] + [0.0] * 6))


def _dented_box() -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=(10.0, 8.0, 6.0)).subdivide().subdivide()
    v = np.array(box.vertices)
    top = v[:, 2] > 2.9
    v[top, 2] -= 2.0 * np.exp(-(v[top, 0] ** 2 + v[top, 1] ** 2) / 8.0)      # a dent in the top: non-convex
    return trimesh.Trimesh(v, box.faces, process=False)


def _compare(mesh: trimesh.Trimesh, n: int, seed: int) -> int:
    shape = Mesh(mesh)
    geo = shape.geometry()
    if geo.convex:
        assert geo.params[1] == 0.0                       # the convex face table
    else:
        assert geo.params[1] == PLANE_TABLE
    forced = _forced_bvh(geo)
    lo, hi = mesh.bounds
    size = float(np.linalg.norm(hi - lo))
    rng = np.random.default_rng(seed)
    n_lit = 0
    for _ in range(n):
        while True:
            x = rng.uniform(lo, hi)
            if shape.contains(x)[0]:
                break
        while True:
            light = (lo + hi) / 2 + rng.normal(size=3) * size
            if not shape.contains(light)[0] and np.linalg.norm(light - (lo + hi) / 2) > 0.6 * size:
                break
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        sigma_t, g, eta = rng.uniform(0.05, 3.0), rng.uniform(-0.5, 0.8), float(rng.choice([0.7, 1.3, 1.5]))
        ref = _contribution(geo, x, d, light, sigma_t, g, eta)
        n_lit += ref > 0
        whole = _bvh(geo, x, d, light, sigma_t, g, eta, math.inf)
        assert whole == pytest.approx(ref, rel=1e-9, abs=1e-300)
        # the default radius drops connections beyond R = ln(1/CUTOFF)/sigma_t (each < CUTOFF of its unattenuated
        # weight): identical when the ball holds the whole mesh, else lower by a negligible amount
        got = _contribution(forced, x, d, light, sigma_t, g, eta)
        if connection_radius(sigma_t) > size:
            assert got == pytest.approx(ref, rel=1e-9, abs=1e-300)
        else:
            assert whole * (1 - 1e-6) - 1e-9 <= got <= whole * (1 + 1e-12) + 1e-300
    return n_lit


@pytest.mark.parametrize("which", ["l-block", "u-channel", "dented-box"])
def test_bvh_connections_equal_the_all_planes_path(which: str) -> None:
    mesh = {"l-block": wall_on_slab_mesh, "u-channel": u_channel_mesh, "dented-box": _dented_box}[which]()
    n_lit = _compare(mesh, 300, seed=len(which))
    assert n_lit > 60                                     # the comparison is not vacuous: many are lit


def test_bvh_connections_equal_the_convex_face_table() -> None:
    rot, _ = np.linalg.qr(np.random.default_rng(5).normal(size=(3, 3)))
    rot *= np.sign(np.linalg.det(rot))
    pyr = pyramid_mesh(6.0, 4.5)
    pyr.apply_transform(np.block([[rot, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]))
    for mesh in (trimesh.creation.box(extents=(4.0, 6.0, 5.0)).subdivide().subdivide(), pyr):
        assert _compare(mesh, 300, seed=3) > 100


def test_many_plane_non_convex_mesh_renders_point_lights_at_eta() -> None:
    """Before: ValueError ("at most 512 distinct face planes"). Now the BVH connections render it; the pixels
    agree with the all-planes path by the deterministic checks above, and at image level in
    benchmarks/mc_bvh_connections.py (the all-planes render of its 2,050 planes is too slow for CI)."""
    ring = trimesh.creation.annulus(r_min=2.0, r_max=5.0, height=2.0, sections=2 * MAX_CONNECTION_PLANES)
    shape = Mesh(ring)
    geo = shape.geometry()
    assert not geo.convex and geo.params[1] == BVH_CONNECTIONS and refracted_point_lights_supported(geo)
    assert plane_table(np.asarray(ring.vertices, float), np.asarray(ring.faces)) is None   # > 512 planes
    cam = PinholeCamera.looking_at(width_px=6, height_px=6, fx_px=9.0, position_mm=(0.0, -9.0, 7.0),
                                   target_mm=(0.0, 0.0, 0.0))
    light = PointLights([[3.0, -8.0, 6.0]], [100.0])
    img = render(shape, Medium(1.0, 0.05, 0.0, 1.3), cam, light, spp=8, seed=1)
    m = img.mask
    assert m.sum() > 10 and np.all(np.isfinite(img.radiance)) and img.radiance[m].min() > 0
