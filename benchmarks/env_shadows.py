"""Accuracy of the environment-map cast shadows (estimation.shadows.environment_irradiance) against a brute-force
reference, by visibility-cell rows: the table of estimation/shadows.py and docs/visibility.md.

Meshes: the L-shaped block of ``simulators.scene.wall_on_slab_mesh`` (patches of 3 mm) and a torus (its own
faces); 200 random patches each. Map: 64 x 128 (the default ``max_size``), a zenith-gradient sky with and without a
broad sun (400 x the sky, exp((cos - 1)/0.003), 40 deg from the zenith towards -x). Reference: every map pixel's
visibility is the fraction of 4 x 4 shadow rays spread over it (12 x 12 for the pixels above 4 x the mean
radiance). Errors are fractions of the mean transmitted irradiance over the patches.

Run: ``python benchmarks/env_shadows.py`` (~3 min on the shared 2-core machine). Not run in CI.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estimation.fresnel import fresnel_transmittance  # noqa: E402
from estimation.rays import RayEngine  # noqa: E402
from estimation.shadows import direction_visibility, environment_irradiance  # noqa: E402
from estimation.single_image import EnvironmentMap, patches_from_mesh  # noqa: E402
from simulators.scene import wall_on_slab_mesh  # noqa: E402

ETA = 1.3
CAMERA_MM = np.array([70.0, -40.0, 80.0])


def sky(h: int, w: int, *, sun: bool) -> np.ndarray:
    """Lat-long sky (EnvironmentMap convention): zenith gradient, a sun 40 deg from the zenith towards -x."""
    th, ph = np.meshgrid(np.pi * (np.arange(h) + 0.5) / h, 2 * np.pi * (np.arange(w) + 0.5) / w, indexing="ij")
    d = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    s = np.array([-np.sin(0.7), 0.0, np.cos(0.7)])
    m = 0.2 + 0.8 * np.clip(d[..., 2], 0, 1) + (400.0 * np.exp((d @ s - 1.0) / 0.003) if sun else 0.0)
    return m[..., None]


def dense_reference(eng: RayEngine, x: np.ndarray, n: np.ndarray, env: EnvironmentMap, sub: int,
                    sub_bright: int) -> np.ndarray:
    """Brute force: every map pixel's visibility is the fraction of sub x sub shadow rays spread over it
    (sub_bright x sub_bright for pixels above 4 x the mean radiance: the sun); below the horizon as unshadowed."""
    h, w = env.grid_shape()
    d, wt = env.directions_and_weights()
    cos = np.maximum(n @ d.T, 0.0)
    a = fresnel_transmittance(ETA, cos) * cos
    rad = np.asarray(env.radiance, float).reshape(h * w, -1).sum(axis=1)
    bright = np.flatnonzero(rad > 4.0 * np.sum(wt) / (4 * np.pi))
    v = np.zeros(a.shape)
    for s, pix in ((sub, np.arange(h * w)), (sub_bright, bright)):
        vs = np.zeros((len(x), len(pix)))
        for i in range(s):
            for j in range(s):
                th = np.pi * (pix // w + (i + 0.5) / s) / h
                ph = 2 * np.pi * (pix % w + (j + 0.5) / s) / w
                dd = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
                vs += direction_visibility(eng, x, n, dd) | (n @ dd.T <= 0)
        v[:, pix] = vs / s ** 2
    return (a * v) @ wt


def main() -> int:
    meshes = {"L-block": wall_on_slab_mesh(),
              "torus": trimesh.creation.torus(10.0, 4.0, major_sections=48, minor_sections=24)}
    for name, m in meshes.items():
        eng = RayEngine(m.vertices, m.faces)
        p = patches_from_mesh(m, CAMERA_MM, max_edge_mm=3.0 if name == "L-block" else None)
        idx = np.random.default_rng(0).choice(len(p.areas_mm2), size=200, replace=False)
        x, n = p.centers_mm[idx], p.normals[idx]
        for sun in (True, False):
            env = EnvironmentMap(sky(64, 128, sun=sun))
            d, wt = env.directions_and_weights()
            t = time.time()
            ref = dense_reference(eng, x, n, env, sub=4, sub_bright=12)
            tr = time.time() - t
            e0 = environment_irradiance(None, x, n, d, wt, env.grid_shape(), ETA)
            mean = ref.mean()
            print(f"{name} sun={sun} K={len(x)} map 64x128 (reference {tr:.0f} s); without shadows: rms "
                  f"{np.sqrt(np.mean((e0 - ref) ** 2)) / mean:.4f} max {np.abs(e0 - ref).max() / mean:.4f}", flush=True)
            for rows in (8, 16, 32):
                st: dict = {}
                t = time.time()
                e = environment_irradiance(eng, x, n, d, wt, env.grid_shape(), ETA, rows=rows, stats=st)
                te = time.time() - t
                err = np.abs(e - ref) / mean
                print(f"  rows {rows:3d} cells {st['cells']:5d} bright px {st['bright_pixels']:3d} rays/patch "
                      f"{st['rays'] / len(x):6.0f} rms {np.sqrt(np.mean(err ** 2)):.4f} max {err.max():.4f} "
                      f"({te:.2f} s)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
