"""Benchmark of the Monte Carlo reference renderer (simulators/mc, issue 8).

Figures:
1. photon throughput of the pencil-beam profile (half-space, marble-like optical medium: albedo' 0.999, eta 1.3,
   isotropic): photons/s and collisions/s;
2. the target image: a 30 mm marble-R sphere (Jensen et al. 2001 Table 2: sigma_s' 2.19, sigma_a 0.0021 /mm,
   eta 1.3, isotropic) filling a 128 x 128 pinhole frame at 64 samples per pixel, lit by one LED-like point light
   (refracted next-event estimation) -- target < 60 s on 2 cores -- and the same frame under the "x" gradient
   pattern (exit look-ups only);
3. per-pixel standard error: median and 90th percentile of stderr / radiance over lit pixels.

Compilation (or loading numba's cache) is timed separately by a tiny warm-up render.

Run: ``python benchmarks/monte_carlo.py [--quick] [--json [out.json]]`` (full ~1 min on 2 idle cores;
``--quick``: 32 x 32 at 16 spp, < 30 s including a cold compile). ``--json`` alone prints JSON instead of the
table. Threads: numba's default (NUMBA_NUM_THREADS).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numba  # noqa: E402

from estimation.camera import PinholeCamera  # noqa: E402
from estimation.single_image import PointLights  # noqa: E402
from simulators.mc import GradientPattern, Medium, Sphere, pencil_beam_profile, render  # noqa: E402
from rig.files.provenance import write_json  # noqa: E402

MARBLE_R = Medium.from_reduced(2.19, 0.0021, g=0.0, eta=1.3)
SPHERE = Sphere((0.0, 0.0, 0.0), 30.0)
LED = PointLights(np.array([[300.0, -900.0, 400.0]]), np.array([1.0e6]))


def camera(size: int) -> PinholeCamera:
    return PinholeCamera.looking_at(width_px=size, height_px=size, fx_px=600.0 * size / 128, position_mm=(0, -300, 0),
                                    target_mm=(0, 0, 0))


def stderr_stats(img) -> dict:
    v = img.radiance[..., 0]
    lit = img.mask & (v > 0.01 * v.max())
    rel = img.stderr[lit, 0] / v[lit]
    return {"lit_pixels": int(lit.sum()), "rel_stderr_median": float(np.median(rel)),
            "rel_stderr_p90": float(np.percentile(rel, 90)), "abs_stderr_median": float(np.median(img.stderr[lit, 0])),
            "radiance_median": float(np.median(v[lit]))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="32 x 32 at 16 spp, 50k photons")
    ap.add_argument("--json", nargs="?", const="-", metavar="PATH",
                    help="write JSON to PATH (alone: print JSON instead of the table)")
    args = ap.parse_args(argv)
    size, spp, photons = (32, 16, 50_000) if args.quick else (128, 64, 1_000_000)
    out: dict = {"threads": numba.get_num_threads(), "cpu_count": os.cpu_count(),
                 "load_average": list(os.getloadavg()), "quick": bool(args.quick)}

    t = time.perf_counter()
    render(SPHERE, MARBLE_R, camera(4), [LED, GradientPattern("x")], spp=2, seed=0)
    pencil_beam_profile(Medium(0.999, 0.001, 0.0, 1.3), [0, 1], 100, seed=0)
    out["warmup_compile_s"] = time.perf_counter() - t

    prof = pencil_beam_profile(Medium(0.999, 0.001, 0.0, 1.3), np.linspace(0, 10, 11), photons, seed=1)
    out["profile"] = {"photons": photons, "seconds": prof.seconds, "photons_per_s": photons / prof.seconds,
                      "collisions_per_photon": prof.mean_collisions,
                      "collisions_per_s": photons * prof.mean_collisions / prof.seconds,
                      "R_d": prof.total_diffuse_reflectance, "R_d_stderr": prof.total_diffuse_reflectance_stderr}

    cam = camera(size)
    for name, lights in (("point_light", LED), ("gradient_x", GradientPattern("x"))):
        img = render(SPHERE, MARBLE_R, cam, lights, spp=spp, seed=1)
        paths = int(img.mask.sum()) * spp
        out[name] = {"size_px": size, "spp": spp, "seconds": img.seconds, "object_pixels": int(img.mask.sum()),
                     "paths_per_s": paths / img.seconds, "collisions_per_path": img.mean_collisions,
                     "truncated_fraction": img.truncated_fraction, **stderr_stats(img)}
    out["load_average_after"] = list(os.getloadavg())

    if args.json == "-":
        print(json.dumps(out, indent=1))
        return 0
    p = out["profile"]
    print(f"# Monte Carlo renderer benchmark ({'quick' if args.quick else 'full'}; {out['threads']} numba threads, "
          f"load average {out['load_average'][0]:.2f} -> {out['load_average_after'][0]:.2f})")
    print(f"warm-up (compile or cache load): {out['warmup_compile_s']:.1f} s")
    print(f"pencil beam, albedo' 0.999, eta 1.3: {p['photons']} photons in {p['seconds']:.2f} s = "
          f"{p['photons_per_s']:.3g} photons/s, {p['collisions_per_s']:.3g} collisions/s "
          f"({p['collisions_per_photon']:.0f} per photon); R_d = {p['R_d']:.4f} +- {p['R_d_stderr']:.4f}")
    print()
    print("| lights | image | seconds | paths/s | collisions/path | median rel. stderr | p90 rel. stderr |")
    print("|---|---|---|---|---|---|---|")
    for name in ("point_light", "gradient_x"):
        r = out[name]
        print(f"| {name} | {r['size_px']}x{r['size_px']} @ {r['spp']} spp | {r['seconds']:.2f} | "
              f"{r['paths_per_s']:.3g} | {r['collisions_per_path']:.0f} | {r['rel_stderr_median']:.3f} | "
              f"{r['rel_stderr_p90']:.3f} |")
    if args.json:
        write_json(args.json, out, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
