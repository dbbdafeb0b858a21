"""Sun lobes in the Monte Carlo reference: efficiency before / after issue 15's sun-lit fix, in one run.

The zoo's sun-lit scenes (benchmarks/scene_zoo.py; docs/model-error.md sec. 4) need references at the truth that
resolve a 3.5 deg sun. For each scene the scene-file reference (rig.estimate.reference.scene_reference, what the
reference loop renders) is rendered at the true parameters twice with the same seed:

- *before*: the renderer's estimator before the fix: straight sun connections only (``env_chain_reflections=0``;
  internally reflected light found by escaping walks), and none at all through a convex mesh of more than 24 flat
  faces (``env_nee=False``: the z03 icosphere), as ``simulators.mc.render`` did then;
- *after*: the default (simulators/mc/env_chains.py: closed-form distant-light face connections for convex meshes
  of up to 4096 flat faces, chains of up to 6 internal reflections for up to 24 faces).

Printed per scene over the observed object pixels: seconds, the image mean with its standard error, the relative
standard error of the image mean, the median / 90th percentile / maximum per-pixel relative standard error,
efficiency = 1 / (relative variance of the image mean x seconds) and the ratio after / before, and the two means'
difference in combined standard errors (both estimate the same image). The per-pixel medians of a heavy-tailed
estimator understate its error (a pixel that drew no sun hit looks quiet), which is why the image mean's error is
the efficiency's measure.

Run: ``NUMBA_NUM_THREADS=2 python benchmarks/mc_sun_lobes.py [--scenes 3,6,13,21] [--spp 128] [--json out.json]``
(frames from the zoo's cache, rendered on first use; minutes, the z03 icosphere most of it).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from zoo.frames import build_scene, default_root  # noqa: E402
from zoo.information import frame_data  # noqa: E402
from zoo.scenes import draw_zoo  # noqa: E402


def measure(index: int, spp: int, seed: int) -> dict[str, Any]:
    from rig.estimate.reference.scene_reference import scene_reference
    from rig.files.scene_file import load_scene
    from simulators.mc import Medium, render
    from simulators.mc.render import ENV_CHAIN_MAX_FLAT_FACES

    spec = draw_zoo()[index]
    folder, _ = build_scene(spec, default_root())
    scene = load_scene(folder / "scene.toml")
    fd = frame_data(scene)
    ref, info = scene_reference(scene, fd["patches"], fd["valid_px"], spp=spp)
    media = [Medium.from_reduced(float(s), float(a), g=ref.g, eta=float(spec.eta))
             for s, a in zip(spec.sigma_s_prime_per_mm, spec.sigma_a_per_mm)]
    px = fd["seen_px"]
    geo = ref.shape.geometry()
    many = bool(geo.convex) and int(geo.params[0]) > ENV_CHAIN_MAX_FLAT_FACES
    before_kw: dict[str, Any] = {"env_nee": False} if many else {"env_chain_reflections": 0}
    out: dict[str, Any] = {"scene": spec.name, "index": index, "spp": spp, "seed": seed, "faces": info["mesh_faces"],
                           "pixels": int(px.sum()), "before": before_kw}
    for label, kw in (("before", before_kw), ("after", {})):
        img = render(ref.shape, media, ref.camera, ref.lights, spp=spp, seed=seed, **kw)
        q, se = img.radiance[px], img.stderr[px]
        mean = float(q.mean())
        se_mean = float(np.sqrt(np.sum(se ** 2)) / q.size)
        rel = se / np.maximum(q, 1e-300)
        out[label] = {"seconds": img.seconds, "mean": mean, "se_mean": se_mean, "rel_se_mean": se_mean / mean,
                      "rel_se_px_median": float(np.median(rel)), "rel_se_px_p90": float(np.percentile(rel, 90)),
                      "rel_se_px_max": float(rel.max()),
                      "efficiency": 1.0 / ((se_mean / mean) ** 2 * img.seconds)}
    b, a = out["before"], out["after"]
    out["efficiency_ratio"] = a["efficiency"] / b["efficiency"]
    out["z_means"] = (a["mean"] - b["mean"]) / float(np.hypot(a["se_mean"], b["se_mean"]))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="3,6,13,21", help="zoo scene indices (default the sun-lit 3,6,13,21)")
    ap.add_argument("--spp", type=int, default=128)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    rows = []
    print("| scene | px | s before / after | mean before | mean after | z | rel se of mean before / after | "
          "px rel se median, p90, max before | after | eff before / after [1/s] | **ratio** |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for i in [int(s) for s in args.scenes.split(",")]:
        r = measure(i, args.spp, args.seed)
        rows.append(r)
        b, a = r["before"], r["after"]
        print(f"| z{i:02d} {r['scene'].split(' ', 1)[1]} ({r['faces']} faces) | {r['pixels']} | "
              f"{b['seconds']:.1f} / {a['seconds']:.1f} | {b['mean']:.4g} +- {b['se_mean']:.2g} | "
              f"{a['mean']:.4g} +- {a['se_mean']:.2g} | {r['z_means']:+.2f} | "
              f"{b['rel_se_mean']:.4f} / {a['rel_se_mean']:.4f} | {b['rel_se_px_median']:.3f}, "
              f"{b['rel_se_px_p90']:.3f}, {b['rel_se_px_max']:.2f} | {a['rel_se_px_median']:.3f}, "
              f"{a['rel_se_px_p90']:.3f}, {a['rel_se_px_max']:.2f} | {b['efficiency']:.3g} / {a['efficiency']:.3g} | "
              f"**{r['efficiency_ratio']:.1f}** |", flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
