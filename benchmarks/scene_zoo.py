"""Issue 15's scene zoo: does the single-image estimator hold on scenes nobody tuned for?

What. 24 scenes drawn with ``numpy.random.default_rng(15)`` (benchmarks/zoo/scenes.py), forced to cover every
failure class of issue 15 at least once; each scene's name lists its classes:

- shape ``cube`` / ``pyramid`` / ``sphere`` (icosphere mesh) / ``box`` (5 x 20 x 40 mm), 5-40 mm, random yaw and
  position; camera at a random distance, elevation and azimuth, ``graze`` when an observed face is seen more than
  60 deg from its normal;
- light ``point1`` (one point light; ``unlit``: an observed face has the light behind its plane, checked
  geometrically), ``point2``, ``sun`` (lat-long EXR map: a 3.5 deg sun lobe over a dim sky), ``sky`` (smooth, no
  sun); maps are written with drawn ``up`` / ``phi0`` / ``azimuth`` / ``rotation_deg`` keys, in a scene-file world
  that is z-up, y-up or arbitrarily tilted, and are exactly the lighting the frame was rendered with
  (benchmarks/zoo/frames.py);
- ``eta1`` / ``eta1.3`` / ``eta1.5`` (three or more eta = 1 cubes: index-matched boundary);
- material-channel from science.md sec. 2 (marble, skin1, apple, skimmilk, ketchup-R, potato-B; three RGB scenes);
- noise ``mc`` (the Monte Carlo frame at 32 spp, fireflies; float EXR), ``zeros`` (point-lit scenes only: shot +
  read noise clipped at 0 after black-level subtraction: dark pixels exactly 0), ``camera`` (Poisson-Gaussian with a
  stated gain in electrons per value and read noise; float EXR or 16-bit PNG); the camera / zeros frames are
  rendered from a 256-spp pilot (1024 under a sun) until their Monte Carlo sd is at most 1/3 of the camera's at 95 %
  of the object's pixel-channels, at most 16x the pilot under a sky, 4x under a sun, 2x under point lights (the frame
  rule, benchmarks/zoo/frames.py; off in ``--quick``); ``noise-section``: the scene file's ``[noise]`` holds the
  true gain and read noise, or — where the cap left Monte Carlo noise above the rule — a ``stderr_path`` image of
  the camera's and the renderer's noise together (else no section).
  Point-lit spheres are drawn at eta = 1 (the renderer's refracted point-light connection is face by face, ~50x
  slower on the 320-face icosphere than on a cube).

Every scene is rendered by ``simulators.mc.render`` and written as a documented scene-file folder (docs/scene-file.md)
under ``benchmarks/out/zoo/<content hash>/``, cached by the hash of the scene description, the frame spp and the
renderer's sources (a second run renders nothing). Then the user path runs: ``rig.files.scene_file.load_scene`` +
``estimate_scene`` with every model (dipole-jensen, dipole-better, mc-table, mc-table+reference), every Python
warning and every byte written to stderr (file descriptor 2) during an estimate captured and counted.

Printed per scene and model: estimates, relative errors, 95 % intervals, whether they cover the truth, the status
(benchmarks/zoo/rules.py: the result's ``status`` field when present, else ``success`` / ``converged`` /
``sigma_a_identifiable``), renders, seconds, warnings; for mc-table+reference each reference step's sigma_s' and
sigma_a error beside the cumulative seconds. Then per model the acceptance lines of issue 15 (PASS/FAIL with
counts; rules.py), a summary table and, per failure class, the pairs within 10 % and the median errors.

Non-convex family (issue 17 part 5, ``--family nonconvex`` or ``all``; benchmarks/zoo/nonconvex.py): scenes 24-27,
an L-block and a U-channel under a point light that casts the object's own shadow on an observed face and under a
smooth sky, eta 1.3-1.5, camera noise; designed, not drawn, and outside ``--quick`` (the 24 drawn scenes, their
seeds and the CI subset are unchanged). ``--shadows both`` prints every fit with shadows off beside it (non-convex
meshes only: on a convex one the fits are the same).

Run: ``python benchmarks/scene_zoo.py [--quick] [--family zoo|nonconvex|all] [--json FILE] [--reference-spp N]
[--reference-iterations K] [--scenes 0,3,7] [--models mc-table,...] [--shadows auto|on|off|both]``. Cost, measured on 2 shared cores (NUMBA_NUM_THREADS=2): the full zoo
(64 x 64 px frames; references 128 spp, at most 6 renders) ~11 min before the frame rule, of which the frames
~1.5 min (first run only) and mc-table+reference ~6 min; the frame rule's camera / zeros frames cost ~33 min of renders
on the first run (1967 s summed over the 28 frames, 1 thread each, load 6-12: z18 442 s, z05 305 s, z21 261 s;
docs/model-error.md sec. 4); ``--quick`` (6 scenes covering unlit face, eta = 1, sun, fireflies, zeros, camera
noise; 48 x 48 px, 64-spp frames, 32-spp references, at most 4 renders) ~50-75 s. Each scene also prints a *file
check*: the Monte Carlo reference rendered from the scene file at the true parameters over the frame (~1 when the
file describes what was rendered). The exit status is 0 whatever the verdicts (they are printed;
tests/rig/test_scene_zoo.py asserts them on the quick subset). Progress goes to stderr, outside the captured
estimates.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path
from statistics import median
from typing import Any, Iterator

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from rig.files.provenance import write_json  # noqa: E402
from zoo.frames import build_scene, default_root  # noqa: E402
from zoo.rules import REFERENCE_MODEL, acceptance, evaluate, worst_sigma_s  # noqa: E402
from zoo.nonconvex import draw_nonconvex  # noqa: E402
from zoo.scenes import SceneSpec, draw_zoo, quick_subset, quick_variant  # noqa: E402

MODELS = ("dipole-jensen", "dipole-better", "mc-table", REFERENCE_MODEL)
CLASS_ORDER = ("unlit", "point1", "point2", "sun", "sky", "eta1", "eta1.3", "eta1.5", "mc", "zeros", "camera",
               "noise-section", "no-noise-section", "graze", "cube", "pyramid", "sphere", "box", "lblock", "ushape",
               "rgb")


@contextlib.contextmanager
def captured() -> Iterator[dict[str, Any]]:
    """Record every Python warning and everything written to stderr (sys.stderr and file descriptor 2)."""
    rec: dict[str, Any] = {"warnings": [], "stderr": ""}
    sys.stderr.flush()
    saved_fd, saved_obj = os.dup(2), sys.stderr
    with tempfile.TemporaryFile() as tmp, warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        os.dup2(tmp.fileno(), 2)
        sys.stderr = buf = io.StringIO()
        try:
            yield rec
        finally:
            sys.stderr = saved_obj
            os.dup2(saved_fd, 2)
            os.close(saved_fd)
            tmp.seek(0)
            rec["stderr"] = buf.getvalue() + tmp.read().decode(errors="replace")
            rec["warnings"] = [f"{w.category.__name__}: {w.message} ({Path(w.filename).name}:{w.lineno})"
                               for w in caught]


def file_check(scene: Any, spec: SceneSpec, spp: int) -> list[float]:
    """The scene file against the frame: the Monte Carlo reference the estimator would render from the *file*
    (rig.estimate.reference.scene_reference: mesh, camera, lights, map and orientation keys as loaded) at the true parameters, and
    the image read back (value / radiance_scale), sampled at the same patches: the sum of the image over the sum of
    the reference on the observed patches, per channel (sums, not a median of ratios: Monte Carlo pixels are
    heavy-tailed). ~1 where the file describes the frame's lighting and geometry, up to the noise of both (under
    a sun lobe a 1024-spp render's object total varies by ~4 % between seeds)."""
    import numpy as np

    from estimation.single_image import patches_from_mesh
    from rig.estimate.pixel_map import pixel_faces, sample_at_points
    from rig.estimate.reference.scene_reference import scene_reference

    cam = scene.camera.model
    pat = patches_from_mesh(scene.mesh_data, cam)
    valid = pixel_faces(scene.mesh_data, cam) >= 0
    ref, _ = scene_reference(scene, pat, valid, spp=spp)
    q = ref(spec.sigma_s_prime_per_mm, spec.sigma_a_per_mm, spec.eta, 7)[0]
    img = scene.image_data / np.asarray(scene.image.radiance_scale)[None, None, :]
    obs, _ = sample_at_points(img, img * 0, np.broadcast_to(valid[..., None], img.shape), cam, pat.centers_mm,
                              window_px=scene.estimation.window_px)
    out = []
    for c in range(img.shape[2]):
        ok = pat.visible & np.isfinite(obs[:, c]) & np.isfinite(q[:, c]) & (q[:, c] > 0.1 * np.nanmedian(q[:, c]))
        out.append(float(np.sum(obs[ok, c]) / np.sum(q[ok, c])) if ok.any() else float("nan"))
    return out


def run_model(scene: Any, model: str, spec: SceneSpec, ref_spp: int, ref_iterations: int,
              shadows: str | None = None, reference_mode: str | None = None) -> dict[str, Any]:
    from rig.estimate.scenes import estimate_scene

    t0 = time.perf_counter()
    with captured() as rec:
        try:
            res = estimate_scene(scene, model=model, reference_spp=ref_spp, reference_iterations=ref_iterations,
                                 shadows=shadows, reference_mode=reference_mode)
            exc = None
        except Exception as e:  # noqa: BLE001 - a crash is a result of the zoo, counted like a warning
            res, exc = {"success": False, "message": f"exception {type(e).__name__}: {e}",
                        "channels": list(spec.channels)}, f"{type(e).__name__}: {e}"
    seconds = time.perf_counter() - t0
    lines = [ln for ln in rec["stderr"].splitlines() if ln.strip()]
    ref = res.get("reference") or {}
    out = {"model": model, "seconds": seconds, "success": bool(res.get("success")), "message": res.get("message"),
           "warnings": rec["warnings"], "stderr_lines": lines, "exception": exc,
           "n_warnings": len(rec["warnings"]) + len(lines) + (exc is not None), "converged": res.get("converged"),
           "renders": len(ref.get("renders") or []), "scan_renders": len(ref.get("scan_renders") or []),
           "ridge_scan": ref.get("ridge_scan"), "ridge_line_search": ref.get("ridge_line_search"),
           "status": res.get("status"), "render_spp": [r.get("spp") for r in ref.get("renders") or []],
           "sample_count_levels": ref.get("sample_count_levels"), "hybrid_fallback": ref.get("hybrid_fallback"),
           "rows": evaluate(res, model, list(spec.sigma_s_prime_per_mm), list(spec.sigma_a_per_mm))}
    if ref:
        steps, cum = [], 0.0
        for st in ref.get("steps") or []:
            cum += float(st.get("render_seconds") or 0.0) + float(st.get("fit_seconds") or 0.0)
            steps.append({"iteration": st.get("iteration"), "seconds_cumulative": cum,
                          "err_s": [s / t - 1 for s, t in zip(st["sigma_s_prime_per_mm"], spec.sigma_s_prime_per_mm)],
                          "err_a": [a / t - 1 for a, t in zip(st["sigma_a_per_mm"], spec.sigma_a_per_mm)],
                          "kappa_p05": st.get("kappa_p05"), "change": st.get("change")})
        out["steps"] = steps
    return out


def _pct(x: float) -> str:
    return "fail" if x != x else f"{x:+.1%}"


def _ci(ci: list[float]) -> str:
    return f"{ci[0]:.3g}-{ci[1]:.3g}"


def print_scene(spec: SceneSpec, meta: dict[str, Any], folder: Path, results: list[dict[str, Any]]) -> None:
    ch = "".join(spec.channels)
    noise = (f"camera noise: gain {meta['gain_e_per_value']:.0f} e-/value, read noise {meta['read_noise_value']:.3g} "
             f"(value units), {spec.image_format}, black level subtracted and clipped at 0" if spec.noise == "zeros"
             else f"camera noise: gain {meta['gain_e_per_value']:.0f} e-/value, read noise "
             f"{meta['read_noise_value']:.3g} (value units), {spec.image_format}" if spec.noise == "camera"
             else "Monte Carlo noise only (float EXR)")
    print(f"\n## {spec.name}  [{folder.name}]\n")
    spp = meta.get("frame_spp_rendered", meta["frame_spp"])
    rule = meta.get("mc_over_camera_sd")
    rule_txt = (f"; MC sd / camera sd median {rule['median']:.2f}, p95 {rule['p95']:.2f}, within 1/3 at "
                f"{rule['fraction_within_rule']:.0%}" if rule else "")
    stated = meta.get("noise_stated") or "given (true gain/read noise)"
    print(f"frame {spec.size_px}x{spec.size_px} px, {spp} spp (pilot {meta['frame_spp']}; MC rel. stderr median "
          f"{meta['mc_rel_stderr_median']:.1%}, max/p99 {meta['max_over_p99']:.1f}{rule_txt}), {noise}; [noise] "
          f"{stated if spec.noise_section else 'absent'}; exact zeros "
          f"{meta['zero_fraction']:.1%} of object pixels; {meta['object_pixels']} object px; patches <= "
          f"{meta['max_edge_mm']} mm; render {meta['render_seconds']:.1f} s"
          f"{' (cached)' if meta.get('cached') else ''}")
    print(f"truth {spec.material}-{ch}: sigma_s' {spec.sigma_s_prime_per_mm.tolist()}, sigma_a "
          f"{spec.sigma_a_per_mm.tolist()} /mm; eta {spec.eta}; unlit observed faces {meta['unlit_faces']}; max "
          f"observed view angle {meta['max_observed_view_deg']:.0f} deg; world {spec.world}"
          + ("" if spec.point_lights else f"; map {spec.env_rows} rows, keys {dict(spec.env_keys)}"))
    print(f"file check: image / Monte Carlo reference rendered from the scene file at the truth (sums over the "
          f"observed patches): {', '.join(f'{x:.3f}' for x in meta['file_check'])}")
    print("\n| model | ch | sigma_s' | err | 95 % | covers | status | sigma_a | err | 95 % | covers | status | renders "
          "(+ the start's ridge scan, at spp / 4) | s | warn |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        for row in r["rows"]:
            print(f"| {r['model']} | {spec.channels[row['channel']]} | {row['value_s']:.4g} | {_pct(row['err_s'])} | "
                  f"{_ci(row['ci_s'])} | {row['covers_s']} | {row['status_s']} | {row['value_a']:.4g} | "
                  f"{_pct(row['err_a'])} | {_ci(row['ci_a'])} | {row['covers_a']} | {row['status_a']} | "
                  f"{r['renders']}{f' + {n} scan' if (n := r.get('scan_renders')) else ''} | {r['seconds']:.1f} | "
                  f"{r['n_warnings']} |")
    for r in results:
        if not r["success"]:
            print(f"- {r['model']} failed: {r['message']}")
        for w in (r["warnings"] + r["stderr_lines"])[:3]:
            print(f"- {r['model']} warning: {w[:200]}")
        if r.get("steps"):
            path = ", ".join(f"{st['iteration']}: {'/'.join(_pct(e) for e in st['err_s'])} | "
                             f"{'/'.join(_pct(e) for e in st['err_a'])} @ {st['seconds_cumulative']:.1f} s"
                             for st in r["steps"])
            print(f"- {r['model']} (converged {r['converged']}) step: sigma_s' err | sigma_a err @ cumulative s: "
                  f"{path}")
        if line := r.get("ridge_line_search"):  # not converged: the line search along the ridge (renders not counted above)
            grid = "; ".join(", ".join(f"{_pct(g['sigma_s_prime_per_mm'] / spec.sigma_s_prime_per_mm[c] - 1)}: "
                                       f"{g['objective']:.1f}" for g in line["grid"][c])
                             for c in range(len(line["grid"])) if line["grid"][c])
            print(f"- {r['model']} ridge line search ({line['renders']} renders at {line['spp']} spp, "
                  f"{sum(line['render_seconds']):.1f} s): sigma_s' err: objective {grid} -> "
                  + "/".join(_pct(v / t - 1) for v, t in zip(line["sigma_s_prime_per_mm"],
                                                             spec.sigma_s_prime_per_mm))
                  + "".join(f"; gate: gain {g:.1f}"
                            + (f", check seeds' mean {gc:.1f}" if gc is not None else "")
                            + f" vs {z:.2f} x sd {sd:.1f}: {'moved' if mv else 'kept'}"
                            for g, gc, sd, z, mv in zip(line.get("gain", []),
                                                        line.get("gain_check", [None] * len(line.get("gain", []))),
                                                        line.get("gain_sd", []), line.get("gain_threshold_sd", []),
                                                        line.get("moved", []))
                            if g is not None and sd is not None))
    sys.stdout.flush()


def class_table(scenes: list[dict[str, Any]], models: tuple[str, ...]) -> None:
    print("\n## Per failure class: sigma_s' within 10 % / pairs, median sigma_s' error, median sigma_a error\n")
    print("| class | " + " | ".join(models) + " |")
    print("|---|" + "---|" * len(models))
    for cls in CLASS_ORDER:
        sc = [s for s in scenes if cls in s["classes"]]
        if not sc:
            continue
        cells = []
        for m in models:
            rows = [row for s in sc for r in s["results"] if r["model"] == m for row in r["rows"]]
            es = [row["err_s"] for row in rows if row["err_s"] == row["err_s"]]
            ea = [row["err_a"] for row in rows if row["err_a"] == row["err_a"]]
            cells.append(f"{sum(row['within_s'] for row in rows)}/{len(rows)}, "
                         f"{_pct(median(es)) if es else '-'}, {_pct(median(ea)) if ea else '-'}")
        print(f"| {cls} ({len(sc)}) | " + " | ".join(cells) + " |")


def summarize(scenes: list[dict[str, Any]], models: tuple[str, ...]) -> dict[str, Any]:
    verdict: dict[str, Any] = {}
    print("\n## Summary per model\n")
    print("| model | sigma_s' within 10 % | worst sigma_s' | sigma_a rule | coverage | ok but >25 % off | warnings | "
          "failed | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for m in models:
        res = [r for s in scenes for r in s["results"] if r["model"] == m]
        rows = [row for r in res for row in r["rows"]]
        warn = sum(r["n_warnings"] for r in res)
        acc = acceptance(rows, warn)
        verdict[m] = acc
        n = len(rows)
        cover = sum(row["covers_s"] + row["covers_a"] for row in rows)
        print(f"| {m} | {sum(row['within_s'] for row in rows)}/{n} | {_pct(worst_sigma_s(rows))} | "
              f"{sum(row['pass_a'] for row in rows)}/{n} | {cover}/{2 * n} | "
              f"{sum(row['confident_wrong'] for row in rows)} | {warn} | {sum(not r['success'] for r in res)} | "
              f"{sum(r['seconds'] for r in res):.0f} |")
    class_table(scenes, models)
    print("\n## Acceptance (issue 15)\n")
    for m in models:
        for key, v in verdict[m].items():
            print(f"ACCEPTANCE {m} {key}: {'PASS' if v['pass'] else 'FAIL'} - {v['text']}")
    return verdict


def merge(paths: list[Path], out: Path | None) -> int:
    """The verdicts of several runs' JSON files taken together (``--merge``): the runs must share models and
    reference settings, and no scene may appear twice."""
    import json

    docs = [json.loads(p.read_text()) for p in paths]
    keys = {(tuple(d["models"]), d["reference_spp"], d["reference_iterations"], d["quick"]) for d in docs}
    if len(keys) != 1:
        raise SystemExit(f"--merge: the runs differ in models / reference spp / iterations / --quick: {sorted(keys)}")
    scenes = sorted((s for d in docs for s in d["scenes"]), key=lambda s: s["name"])
    names = [s["name"] for s in scenes]
    if len(set(names)) != len(names):
        raise SystemExit(f"--merge: a scene appears twice: {sorted(n for n in set(names) if names.count(n) > 1)}")
    models = tuple(docs[0]["models"])
    print(f"# Scene zoo (issue 15), merged: {len(scenes)} scenes from {len(paths)} runs "
          f"({', '.join(str(p) for p in paths)}); run seconds {' + '.join(str(round(d['seconds'])) for d in docs)}")
    verdict = summarize(scenes, models)
    if out is not None:
        write_json(out, {**{k: docs[0][k] for k in ("quick", "reference_spp", "reference_iterations", "models")},
                         "scenes": scenes, "acceptance": verdict, "seconds": sum(d["seconds"] for d in docs),
                         "merged_from": [str(p) for p in paths]}, indent=1)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the CI subset: 6 scenes, 48 x 48 px, 64-spp frames")
    ap.add_argument("--json", type=Path, help="write every scene, result row and verdict as JSON")
    ap.add_argument("--reference-spp", type=int, help="mc-table+reference render spp (default 128, --quick 32)")
    ap.add_argument("--reference-iterations", type=int, help="at most this many reference renders (default 6, "
                    "--quick 4)")
    ap.add_argument("--reference-mode", choices=["adaptive", "hybrid", "legacy"],
                    help="mc-table+reference sample counts (rig estimate single-image --reference-mode; default: its "
                         "default)")
    ap.add_argument("--scenes", help="comma-separated scene indices (default: all of the zoo or the subset)")
    ap.add_argument("--family", choices=["zoo", "nonconvex", "all"], default="zoo",
                    help="zoo: the 24 drawn convex scenes (default; --quick takes its subset of them); nonconvex: "
                         "issue 17's self-shadowing L-blocks and U-channels under a point light and a sky "
                         "(indices 24-27, benchmarks/zoo/nonconvex.py); all: both")
    ap.add_argument("--models", help="comma-separated models (default: all four)")
    ap.add_argument("--root", type=Path, help="scene folders (default benchmarks/out/zoo or $SSSRIG_ZOO_DIR)")
    ap.add_argument("--shadows", choices=["auto", "on", "off", "both"], default="auto",
                    help="cast shadows in the estimates (default auto: on for non-convex meshes); 'both' also prints "
                         "every fit with shadows off beside it (the acceptance rules use the first)")
    ap.add_argument("--merge", type=Path, nargs="+", metavar="JSON",
                    help="print the summary, class table and acceptance of the scenes of several --json files "
                         "(runs over disjoint --scenes, same models and reference settings) and exit")
    args = ap.parse_args(argv)
    if args.merge:
        return merge(args.merge, args.json)
    ref_spp = args.reference_spp or (32 if args.quick else 128)
    ref_it = args.reference_iterations or (4 if args.quick else 6)
    models = tuple(args.models.split(",")) if args.models else MODELS
    specs = draw_zoo() if args.family != "nonconvex" else []
    if args.quick:
        specs = [quick_variant(s) for s in quick_subset(specs)] if specs else []
    if args.family != "zoo":
        specs += draw_nonconvex()
    if args.scenes:
        keep = {int(x) for x in args.scenes.split(",")}
        specs = [s for s in specs if s.index in keep]
    root = args.root or default_root()
    import numba

    t_all = time.perf_counter()
    print(f"# Scene zoo (issue 15): {len(specs)} scenes{' (--quick subset)' if args.quick else ''}, models "
          f"{', '.join(models)}; references {ref_spp} spp, at most {ref_it} renders; numba threads "
          f"{numba.get_num_threads()}, load {os.getloadavg()[0]:.2f}; scene folders under {root}")
    scenes = []
    for i, spec in enumerate(specs):
        print(f"[{i + 1}/{len(specs)}] {spec.name}: frame", file=sys.stderr, flush=True)
        folder, meta = build_scene(spec, root)
        from estimation.shadows import is_convex_mesh
        from rig.files.scene_file import load_scene

        scene = load_scene(folder / "scene.toml")
        check = file_check(scene, spec, ref_spp)
        results, results_off = [], []
        first = "auto" if args.shadows == "both" else args.shadows
        # on a convex mesh nothing casts a shadow on the object: the fits with shadows off are the same ones
        both = args.shadows == "both" and not is_convex_mesh(scene.mesh_data.vertices, scene.mesh_data.faces)
        for m in models:
            print(f"[{i + 1}/{len(specs)}] {spec.name}: {m}", file=sys.stderr, flush=True)
            results.append(run_model(scene, m, spec, ref_spp, ref_it, shadows=first,
                                     reference_mode=args.reference_mode))
            if both:
                results_off.append(run_model(scene, m, spec, ref_spp, ref_it, shadows="off",
                                             reference_mode=args.reference_mode))
        meta["file_check"] = check
        print_scene(spec, meta, folder, results)
        if results_off:
            print("  the same fits with shadows off:")
            print_scene(spec, meta, folder, results_off)
        scenes.append({"name": spec.name, "folder": str(folder), "classes": sorted(
            spec.classes | {"noise-section" if spec.noise_section else "no-noise-section"}), "meta": meta,
                       "results": results, **({"results_shadows_off": results_off} if results_off else {})})
        if args.json:  # after every scene (atomically): a run stopped part-way keeps the scenes it finished
            _write_doc(args.json, args.quick, ref_spp, ref_it, models, scenes, None, time.perf_counter() - t_all)
    verdict = summarize(scenes, models)
    total = time.perf_counter() - t_all
    print(f"\ntotal {total:.0f} s ({len(specs)} scenes; frames rendered this run "
          f"{sum(not s['meta'].get('cached') for s in scenes)}, frame render seconds "
          f"{sum(s['meta']['render_seconds'] for s in scenes if not s['meta'].get('cached')):.0f})")
    if args.json:
        _write_doc(args.json, args.quick, ref_spp, ref_it, models, scenes, verdict, total)
    return 0


def _write_doc(path: Path, quick: bool, ref_spp: int, ref_it: int, models: tuple[str, ...],
               scenes: list[dict[str, Any]], verdict: dict[str, Any] | None, seconds: float) -> None:
    """The run's JSON: every scene so far; ``acceptance`` None until the run's end (``--merge`` recomputes it)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, {"quick": quick, "reference_spp": ref_spp, "reference_iterations": ref_it, "models": models,
                      "scenes": scenes, "acceptance": verdict, "seconds": seconds, "complete": verdict is not None},
               indent=1)


if __name__ == "__main__":
    raise SystemExit(main())
