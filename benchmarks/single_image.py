"""Benchmark of the single-image method (Mukaigawa, Suzuki, Yagi 2009) as published and improved.

Synthesize-and-recover on a sphere (no inverse crime: the image comes from estimation.forward on a finer,
rotated tessellation than the estimator's icosphere mesh):

1. The paper's experiment (Table 1): marble-R (sigma_s' 2.19, sigma_a 0.002 /mm, eta 1.3) under an
   environment map, quantization step 0.05-0.50 mm, for ``pinv`` (published), ``tikhonov`` and ``direct``.
   The paper used a Debevec light probe; none is bundled, so a procedural lat-long sky (gradient + sun) stands in.
2. One LED (point light ~1 m away) on Jensen 2001 materials, all three channels, ``direct``.

Run: ``python benchmarks/single_image.py [--quick] [--json out.json]`` (a few minutes; --quick ~20 s).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estimation.camera import PinholeCamera  # noqa: E402
from estimation.forward import diffuse_exitance, radiance_from_exitance  # noqa: E402
from estimation.single_image import (EnvironmentMap, PointLights, estimate_single_image, patch_irradiance,  # noqa: E402
                                     patches_from_mesh, Patches)

CAMERA_MM = (0.0, -300.0, 0.0)
LED_MM = np.array([[300.0, -900.0, 400.0]])
MATERIALS = {  # Jensen 2001 Table 2 (pbrt units), eta 1.3
    "apple": ([2.29, 2.39, 1.97], [0.0030, 0.0034, 0.046]),
    "marble": ([2.19, 2.62, 3.00], [0.0021, 0.0041, 0.0071]),
    "skin1": ([0.74, 0.88, 1.01], [0.032, 0.17, 0.48]),
    "potato": ([0.68, 0.70, 0.55], [0.0024, 0.0090, 0.12]),
    "ketchup": ([0.18, 0.07, 0.03], [0.061, 0.97, 1.45]),
    "cream": ([7.38, 5.47, 3.15], [0.0002, 0.0028, 0.0163]),
}


def sky_map(h: int = 32, w: int = 64) -> np.ndarray:
    """Procedural lat-long sky (EnvironmentMap convention): bright zenith gradient plus a sun at 40 deg."""
    theta = np.pi * (np.arange(h) + 0.5) / h
    phi = 2 * np.pi * (np.arange(w) + 0.5) / w
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    sun = np.array([np.sin(0.7) * np.cos(4.2), np.sin(0.7) * np.sin(4.2), np.cos(0.7)])
    sky = 0.2 + 0.8 * np.clip(d[..., 2], 0, 1) + 400.0 * np.exp((d @ sun - 1.0) / 0.003)
    return sky[..., None]


def fine_sources(sub: int, radius: float) -> Patches:
    m = trimesh.creation.icosphere(subdivisions=sub, radius=1.0)
    n = m.triangles_center / np.linalg.norm(m.triangles_center, axis=1, keepdims=True)
    n = n @ Rotation.from_euler("xyz", [0.3, 0.7, 0.2]).as_matrix().T
    a = m.area_faces * (4 * np.pi / m.area_faces.sum()) * radius**2
    return Patches.from_arrays(n * radius, n, a, CAMERA_MM)


def synthesize(est: Patches, fine: Patches, lights, ssp, sa, eta: float) -> np.ndarray:
    e = patch_irradiance(fine, lights, eta)
    vis = est.visible_index
    b = diffuse_exitance(est.centers_mm[vis], fine.centers_mm, fine.areas_mm2, e, ssp, sa, eta)
    return radiance_from_exitance(b, est.cos_out[vis], eta)


def row(label: str, truth_s, truth_a, r) -> dict:
    out = {"case": label, "ok": bool(r), "message": r.message}
    if r:
        out.update(
            sigma_s_prime=r.sigma_s_prime_per_mm.tolist(), sigma_a=r.sigma_a_per_mm.tolist(),
            err_sigma_s_prime=(r.sigma_s_prime_per_mm / np.asarray(truth_s) - 1).tolist(),
            err_sigma_a=(r.sigma_a_per_mm / np.asarray(truth_a) - 1).tolist(),
            sigma_a_ci=r.sigma_a_ci_per_mm.tolist(), identifiable=list(r.sigma_a_identifiable_per_channel),
            covered=[bool(lo <= t <= hi) for (lo, hi), t in zip(r.sigma_a_ci_per_mm, np.atleast_1d(truth_a))],
            empty_bins=r.diagnostics.empty_bins, condition=r.diagnostics.condition_number,
            seconds=r.diagnostics.seconds)
    return out


def fmt(v) -> str:
    return "/".join(f"{x:.4g}" for x in np.atleast_1d(v))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="coarser meshes, fewer cases")
    ap.add_argument("--json", type=Path, help="write the rows as JSON")
    args = ap.parse_args(argv)
    sub_est, sub_fine = (3, 4) if args.quick else (4, 5)
    radius, eta = 10.0, 1.3
    cam = PinholeCamera.looking_at(width_px=640, height_px=480, fx_px=1500, position_mm=CAMERA_MM,
                                   target_mm=(0, 0, 0))
    est = patches_from_mesh(trimesh.creation.icosphere(subdivisions=sub_est, radius=radius), cam)
    fine = fine_sources(sub_fine, radius)
    rows: list[dict] = []
    print(f"# single-image benchmark: {len(est.areas_mm2)} estimator patches ({est.visible.sum()} visible, spacing "
          f"{est.spacing_mm:.2f} mm), {len(fine.areas_mm2)} source patches for synthesis\n")

    # 1. the paper's table: marble-R under an environment map
    truth = ([2.19], [0.002])
    env = EnvironmentMap(sky_map())
    t0 = time.perf_counter()
    obs = synthesize(est, fine, env, *truth, eta)
    print(f"## Paper experiment (marble-R 2.19 / 0.002, eta 1.3, sky map); synthesis {time.perf_counter() - t0:.1f} s\n")
    print("| method | bin mm | sigma_s' | sigma_a | sigma_a 95% | ident. | empty bins | cond | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    steps = [0.1, 0.35] if args.quick else [0.05, 0.10, 0.15, 0.20, 0.25, 0.30, 0.35, 0.40, 0.45, 0.50]
    cases = [("direct", 0.35)] + [(m, b) for m in ("pinv", "tikhonov") for b in steps]
    for method, b in cases:
        r = estimate_single_image(obs, est, env, eta, method=method, bin_mm=b)
        rows.append(row(f"paper/{method}/{b}", *truth, r))
        if r:
            print(f"| {method} | {b:.2f} | {fmt(r.sigma_s_prime_per_mm)} | {fmt(r.sigma_a_per_mm)} | "
                  f"{fmt(r.sigma_a_ci_per_mm[0])} | {r.sigma_a_identifiable} | {r.diagnostics.empty_bins} | "
                  f"{r.diagnostics.condition_number:.3g} | {r.diagnostics.seconds:.2f} |")
        else:
            print(f"| {method} | {b:.2f} | failed: {r.message} | | | | | | |")

    # 2. one LED, Jensen materials, direct
    led = PointLights(LED_MM, np.full((1, 3), 1e6))
    print("\n## One LED at ~1 m, direct method, RGB (relative errors)\n")
    print("| material | sigma_s' err | sigma_a err | sigma_a identifiable | sigma_a CI covers truth | s |")
    print("|---|---|---|---|---|---|")
    names = ["marble", "skin1"] if args.quick else list(MATERIALS)
    for name in names:
        s, a = MATERIALS[name]
        obs = synthesize(est, fine, led, np.array(s), np.array(a), eta)
        r = estimate_single_image(obs, est, led, eta)
        rw = row(f"led/{name}", s, a, r)
        rows.append(rw)
        if r:
            print(f"| {name} | {fmt(np.round(rw['err_sigma_s_prime'], 4))} | {fmt(np.round(rw['err_sigma_a'], 4))} | "
                  f"{fmt(np.array(rw['identifiable'], dtype=int))} | {fmt(np.array(rw['covered'], dtype=int))} | "
                  f"{r.diagnostics.seconds:.2f} |")
        else:
            print(f"| {name} | failed: {r.message} | | | | |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
