"""The scene zoo's non-convex family (issue 17 part 5, benchmarks/zoo/nonconvex.py): geometry only (no renders; the
family's fits are a benchmark run, ``python benchmarks/scene_zoo.py --family nonconvex --shadows both``).

Checks: indices after the 24 drawn scenes, which are unchanged by the family (the default ``--family zoo`` and the
``--quick`` subset draw the same specs as ``draw_zoo``); closed, non-convex meshes that the Monte Carlo renderer
connects point lights through at eta != 1 (a plane table); and under each point light a substantial part of the
object's upward floor in its own cast shadow (shadow rays of trimesh against the mesh), the rest lit."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from zoo.nonconvex import FIRST_INDEX, NONCONVEX_SHAPES, draw_nonconvex  # noqa: E402
from zoo.scenes import draw_zoo  # noqa: E402

from simulators.mc import Mesh  # noqa: E402
from simulators.mc.shapes import PLANE_TABLE  # noqa: E402


def test_family_follows_the_drawn_zoo_without_touching_it() -> None:
    zoo = draw_zoo()
    fam = draw_nonconvex()
    assert [s.index for s in zoo] == list(range(24)) and FIRST_INDEX == 24
    assert [s.index for s in fam] == [24, 25, 26, 27]
    assert all(s.shape not in NONCONVEX_SHAPES for s in zoo)
    assert {s.shape for s in fam} == set(NONCONVEX_SHAPES) and {s.light for s in fam} == {"point1", "sky"}
    assert all(s.eta != 1.0 for s in fam)
    assert [s.to_json() for s in draw_zoo()] == [s.to_json() for s in zoo]     # deterministic


def test_family_meshes_are_closed_non_convex_and_connectable() -> None:
    for s in draw_nonconvex():
        m = s.mesh()
        assert m.is_watertight and not m.is_convex and m.volume > 0
        geo = Mesh(m).geometry()
        assert not geo.convex and geo.params[1] == PLANE_TABLE and geo.params[0] <= 10


def test_point_lit_scenes_cast_the_objects_own_shadow_on_its_floor() -> None:
    rng = np.random.default_rng(0)
    for s in draw_nonconvex():
        if s.light != "point1":
            continue
        m = s.mesh()
        up = m.face_normals[:, 2] > 0.99
        floor_z = m.triangles_center[up, 2].min()
        tri = m.triangles[up & (np.abs(m.triangles_center[:, 2] - floor_z) < 1e-9)]
        a, b = rng.random((2, 2000, 1))
        flip = a + b > 1
        a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
        k = rng.integers(len(tri), size=2000)
        p = tri[k, 0] + a * (tri[k, 1] - tri[k, 0]) + b * (tri[k, 2] - tri[k, 0]) + np.array([0, 0, 1e-6])
        light = np.array(s.point_lights[0][:3])
        d = light - p
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        shaded = trimesh.ray.ray_triangle.RayMeshIntersector(m).intersects_any(p, d)
        print(f"{s.name}: floor in the object's own shadow {shaded.mean():.2f}")
        assert 0.3 < shaded.mean() < 0.8
