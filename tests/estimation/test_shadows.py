"""Cast shadows of the single-image method (estimation/shadows.py, patch_irradiance): a non-convex L-shaped block
(a wall on a slab) under a point light and under a sky with a sun, against geometry and against a dense
brute-force reference; convex meshes give exactly the unshadowed irradiance."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from estimation.rays import RayEngine
from estimation.shadows import environment_irradiance, is_convex_mesh
from estimation.single_image import (DirectionalLights, EnvironmentMap, PointLights, patch_irradiance,
                                     patches_from_mesh)
from simulators.scene import wall_on_slab_mesh

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from env_shadows import dense_reference, sky  # noqa: E402  (the benchmark's brute force, one copy)

ETA = 1.3
CAMERA_MM = np.array([70.0, -40.0, 80.0])
LIGHT_MM = np.array([[-40.0, 0.0, 100.0]])   # beyond the wall: its shadow on the slab ends at x = 8 + 15 * 48/80 = 17


def _slab_top(p) -> np.ndarray:
    return (p.normals[:, 2] > 0.999) & (np.abs(p.centers_mm[:, 2] - 5.0) < 1e-9)


def test_is_convex_mesh() -> None:
    assert is_convex_mesh(trimesh.creation.box().vertices, trimesh.creation.box().faces)
    ico = trimesh.creation.icosphere(subdivisions=3)
    assert is_convex_mesh(ico.vertices, ico.faces)
    wall = wall_on_slab_mesh()
    assert wall.is_watertight and not is_convex_mesh(wall.vertices, wall.faces)
    torus = trimesh.creation.torus(10.0, 4.0)
    assert not is_convex_mesh(torus.vertices, torus.faces)
    box = trimesh.creation.box()
    v = box.vertices[box.faces].reshape(-1, 3)                               # every face its own vertices
    assert is_convex_mesh(v, np.arange(len(v)).reshape(-1, 3))
    open_box = trimesh.creation.box()
    assert not is_convex_mesh(open_box.vertices, open_box.faces[:-2])        # a missing side: not closed


def test_point_light_shadow_is_zero_in_the_shadow_and_max_n_l_elsewhere() -> None:
    p = patches_from_mesh(wall_on_slab_mesh(), CAMERA_MM, max_edge_mm=2.0)
    assert p.shadows                                                         # auto: the mesh is not convex
    lights = PointLights(LIGHT_MM, [[1e4, 2e4]])
    e = patch_irradiance(p, lights, ETA)
    e0 = patch_irradiance(p, lights, ETA, shadows=False)                     # max(0, n.l) only
    top = _slab_top(p)
    x = p.centers_mm[top, 0]
    shadowed = e[top, 0] == 0.0
    # the wall's shadow on the slab's top: x < 17 mm (patch centres within one patch of the edge either way)
    assert np.all(x[shadowed] < 17.0 + 0.1) and np.all(x[~shadowed] > 17.0 - 0.1)
    assert np.all(shadowed == (x < 17.0))
    assert 50 < shadowed.sum() and 50 < (~shadowed).sum()
    assert np.all(e0[top][shadowed] > 0)                                     # lit without shadows
    assert np.all(e[top][shadowed] == 0.0)
    # everywhere else exactly the unshadowed irradiance (nothing else stands between a face and the light)
    lit = ~(top & (p.centers_mm[:, 0] < 17.0))
    np.testing.assert_array_equal(e[lit], e0[lit])
    # distant lights: a sun at the same direction casts the parallel-ray shadow (ends at x = 8 + 15 / tan(elev))
    d = np.array([-1.0, 0.0, 1.5])
    es = patch_irradiance(p, DirectionalLights(d[None], [[1.0, 1.0]]), ETA)
    x_edge = 8.0 + 15.0 / 1.5
    assert np.all((es[top, 0] == 0.0) == (x < x_edge))


def test_convex_meshes_give_exactly_the_unshadowed_irradiance() -> None:
    ico = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    box = trimesh.creation.box(extents=(20.0, 10.0, 6.0))
    env = EnvironmentMap(sky(16, 32, sun=True))
    for mesh in (ico, box):
        auto = patches_from_mesh(mesh, CAMERA_MM)
        assert not auto.shadows and auto.occluder is None                    # proven convex: nothing is cast
        forced = patches_from_mesh(mesh, CAMERA_MM, shadows=True)
        assert forced.shadows
        for lights in (PointLights(LIGHT_MM, [[1e4]]), DirectionalLights([[0.3, -0.2, 1.0]], [[2.0]]), env):
            e_auto = patch_irradiance(auto, lights, ETA)
            np.testing.assert_array_equal(e_auto, patch_irradiance(auto, lights, ETA, shadows=False))
            # shadow rays on a convex mesh find nothing
            np.testing.assert_allclose(patch_irradiance(forced, lights, ETA), e_auto, rtol=1e-12, atol=0)


@pytest.mark.parametrize("sun", [True, False])
def test_environment_map_shadows_match_a_dense_brute_force_reference(sun: bool) -> None:
    mesh = wall_on_slab_mesh()
    p = patches_from_mesh(mesh, CAMERA_MM, max_edge_mm=3.0)
    rng = np.random.default_rng(1)
    idx = rng.choice(len(p.areas_mm2), size=100, replace=False)
    x, n = p.centers_mm[idx], p.normals[idx]
    env = EnvironmentMap(sky(32, 64, sun=sun))
    eng = RayEngine(mesh.vertices, mesh.faces)
    ref = dense_reference(eng, x, n, env, sub=3, sub_bright=12)             # 32 x 64 x 9 directions + the sun
    d, w = env.directions_and_weights()
    stats: dict = {}
    e = environment_irradiance(eng, x, n, d, w, env.grid_shape(), ETA, stats=stats)      # default 16 rows
    e0 = environment_irradiance(None, x, n, d, w, env.grid_shape(), ETA)
    scale = ref.mean()
    err = np.abs(e - ref)[:, 0] / scale
    print(f"sun={sun}: rms {np.sqrt(np.mean(err ** 2)):.4f}, max {err.max():.4f} of the mean E_t; {stats}")
    assert stats["cells"] == 16 * 32 and (stats["bright_pixels"] > 0) == sun
    # stated accuracy (docs/visibility.md): rms ~1 % of the mean irradiance (< 1.25 %), no patch off by more than 6 %
    assert np.sqrt(np.mean(err ** 2)) < 0.0125 and err.max() < 0.06
    # ... while ignoring the shadows is off by far more: the test can see them
    assert np.sqrt(np.mean(((e0 - ref)[:, 0] / scale) ** 2)) > 0.08
    # the same through patch_irradiance, and through DirectionalLights on the map's grid (the scene files' path)
    sub = p.with_shadows(eng)
    e_p = patch_irradiance(sub, env, ETA)[idx]
    np.testing.assert_allclose(e_p, e, rtol=1e-12, atol=1e-12 * scale)
    e_d = patch_irradiance(sub, DirectionalLights(d, w, grid_shape=env.grid_shape()), ETA)[idx]
    np.testing.assert_allclose(e_d, e, rtol=1e-12, atol=1e-12 * scale)


def test_shadow_switch_and_bad_input() -> None:
    mesh = wall_on_slab_mesh()
    p = patches_from_mesh(mesh, CAMERA_MM, max_edge_mm=3.0)
    off = patches_from_mesh(mesh, CAMERA_MM, max_edge_mm=3.0, shadows=False)
    assert p.shadows and not off.shadows and not p.with_shadows(None).shadows
    lights = PointLights(LIGHT_MM, [[1e4]])
    np.testing.assert_array_equal(patch_irradiance(off, lights, ETA), patch_irradiance(p, lights, ETA, shadows=False))
    assert np.sum(patch_irradiance(p, lights, ETA)) < 0.95 * np.sum(patch_irradiance(off, lights, ETA))
    with pytest.raises(ValueError, match="shadows"):
        patches_from_mesh(mesh, CAMERA_MM, shadows="yes")
    with pytest.raises(ValueError, match="grid"):
        environment_irradiance(None, p.centers_mm, p.normals, np.ones((10, 3)), np.ones((10, 1)), (3, 4), ETA)
