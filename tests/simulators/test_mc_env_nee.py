"""Environment next-event estimation of the Monte Carlo renderer (simulators/mc/walk.py, lights.env_nee_table).

A map with a small bright sun (3.5 deg Gaussian lobe, ~400x the sky) over a dim sky: escaping walks rarely find the
sun, so the plain path tracer is ~55 % noisy per pixel at 256 spp; connecting every collision to a sun pixel (drawn
by power) through the refracting boundary brings that to ~4-5 %. Both estimate the same image: the sums over the
object agree within 4 combined standard errors (measured at 16384 / 1024 spp: box eta 1.3 0.996 +- 0.015, box eta 1
0.991 +- 0.012, 320-triangle icosphere mesh eta 1.5 0.988 +- 0.017; a mesh of more than
ENV_NEE_MAX_FLAT_FACES flat faces now path-traces, the icosahedron stands in for it). Before the renderer split escaping paths into straight
exits (whose sun pixels the connection covers) and exits after an internal reflection (which still look the sun up),
the box at eta 1.3 came out 3.4 % dark (2.8 standard errors): the test would catch that.
"""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from estimation.camera import PinholeCamera
from estimation.single_image import EnvironmentMap
from simulators.mc import Box, Medium, Mesh, render
from simulators.mc.lights import env_nee_table


def sun_map(rows: int = 32, sigma_deg: float = 3.5, gain: float = 400.0) -> np.ndarray:
    h, w = rows, 2 * rows
    th = np.pi * (np.arange(h) + 0.5) / h
    ph = 2 * np.pi * (np.arange(w) + 0.5) / w
    t, p = np.meshgrid(th, ph, indexing="ij")
    d = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)
    s = np.array([0.5, -0.6, 0.62]) / np.linalg.norm([0.5, -0.6, 0.62])
    ang = np.arccos(np.clip(d @ s, -1, 1))
    return np.where(d[..., 2] > 0, 0.2, 0.05) + gain * np.exp(-0.5 * (ang / np.radians(sigma_deg)) ** 2)


CAMERA = PinholeCamera.looking_at(width_px=10, height_px=10, fx_px=10 * 450 / (1.9 * 20), position_mm=(250, -300, 220),
                                  target_mm=(0, 0, 0))
CASES = {"box-eta1.3": (lambda: Box((-10,) * 3, (10,) * 3), 1.3), "box-eta1.0": (lambda: Box((-10,) * 3, (10,) * 3), 1.0),
         "icosahedron-eta1.5": (lambda: Mesh(trimesh.creation.icosphere(0, radius=10.0)), 1.5)}


def test_table_holds_the_sun_and_the_rest_the_sky():
    m = sun_map()
    table, rest = env_nee_table(m)
    assert 0 < len(table) < 0.05 * m.size and np.all(np.diff(table[:, 0]) >= 0) and table[-1, 0] == 1.0
    rows, cols = table[:, 1].astype(int), table[:, 2].astype(int)
    assert np.all(rest[rows, cols] == 0) and np.all(m[rows, cols] > 4 * 0.2)
    np.testing.assert_array_equal(np.delete(rest.ravel(), rows * m.shape[1] + cols),
                                  np.delete(m.ravel(), rows * m.shape[1] + cols))
    flat_table, flat_rest = env_nee_table(np.ones((8, 16)))  # nothing bright: no connections
    assert len(flat_table) == 0 and np.all(flat_rest == 1)


@pytest.mark.parametrize("name", sorted(CASES))
def test_sun_connections_agree_with_path_tracing_and_cut_the_noise(name):
    """A 10 deg sun (gain 60): broad enough for 4096-spp path tracing to be a sharp oracle (a 3.5 deg sun leaves its
    sum heavy-tailed: rare sun hits are missed and its standard error understates that)."""
    make, eta = CASES[name]
    light = EnvironmentMap(sun_map(sigma_deg=10.0, gain=60.0), max_size=32)
    med = [Medium.from_reduced(0.74, 0.032, eta=eta)]  # skin1-R
    pt = render(make(), med, CAMERA, light, spp=4096, seed=11, env_nee=False)
    nee = render(make(), med, CAMERA, light, spp=256, seed=12)
    m = pt.mask
    s_pt, s_nee = pt.radiance[m, 0].sum(), nee.radiance[m, 0].sum()
    se = np.hypot(np.sqrt((pt.stderr[m, 0] ** 2).sum()) / s_pt, np.sqrt((nee.stderr[m, 0] ** 2).sum()) / s_nee)
    print(f"{name}: connections / path tracing {s_nee / s_pt:.4f} +- {se:.4f}")
    assert abs(s_nee / s_pt - 1) <= 4 * se
    pt256 = render(make(), med, CAMERA, light, spp=256, seed=13, env_nee=False)
    rel = lambda im: np.median(im.stderr[m, 0] / im.radiance[m, 0])  # noqa: E731
    assert rel(nee) < 0.2 * rel(pt256)


def test_many_faced_refracting_mesh_path_traces():
    """Above ENV_NEE_MAX_FLAT_FACES flat faces a refracting mesh's connections (a scan of every face) cost more than
    they save (measured 5x the path tracer's time on the 320-triangle icosphere): env_nee is then not used."""
    from simulators.mc.render import ENV_NEE_MAX_FLAT_FACES

    mesh = trimesh.creation.icosphere(2, radius=10.0)
    assert len(mesh.faces) > ENV_NEE_MAX_FLAT_FACES
    light = EnvironmentMap(sun_map(), max_size=32)
    med = [Medium.from_reduced(0.74, 0.032, eta=1.5)]
    a = render(Mesh(mesh), med, CAMERA, light, spp=8, seed=3, env_nee=True)
    b = render(Mesh(mesh), med, CAMERA, light, spp=8, seed=3, env_nee=False)
    np.testing.assert_array_equal(a.radiance, b.radiance)
