"""Issue 19, acceptance line 2: the reference-corrected estimates now against the start of issue 19, in one run.

What. Two items, each estimated by two source trees in subprocesses, one after the other, on the same cached frames:

- ``anchor``: the code at the start of issue 19 (:data:`ANCHOR_COMMIT`, the parent of 9b1ed69, the first commit of
  the issue: ``benchmarks/mc_vs_mitsuba.py``'s first version), checked out once as a ``git worktree`` under
  ``~/.cache/sssrig/reference-speed/anchor-<commit>`` (outside the checkout; its numba cache stays there);
- ``current``: this checkout.

Items: (a) the zoo's median single-image scene, z10 (an 18 mm skin1-G cube under one point light, eta 1.5, 64 x 64
px; ``model = mc-table+reference``, 128 spp, at most 6 renders, seed 1; the current tree in its default
``reference_mode = "hybrid"``): the median of the per-scene reference times
measured at the issue's start in docs/model-error.md ("The loop's start, measured": 69, 86, 98, 105, **164**, 177,
250, 341, 428 s; no full-zoo run records per-scene times, and timing the anchor on all 24 scenes takes hours here);
(b) a 5 mm sphere capture, ``sphere_skin1_r5mm`` of ``benchmarks/gradients_acceptance.py`` (32 px, 64-spp frames;
``rig estimate gradients --reference`` at 64 spp, at most 8 renders, seed 1: the CLI's defaults at both commits).
Both trees get the same options and the same frames (benchmarks/out/zoo, benchmarks/out/gradients_acceptance, found
by their description whatever renderer hash their folder carries; rendered by the current code only when absent).

Each subprocess (benchmarks/_reference_speed_driver.py, NUMBA_NUM_THREADS=1, OPENBLAS_NUM_THREADS=1) first runs the
same estimate at 2 spp and one render (kernels compiled or loaded), then times the real one: wall and CPU seconds
of the whole estimate (the plain fit, the reference loop, the summary: what a user waits for). Printed per item and
tree: CPU and wall seconds, the reference loop's own wall seconds and renders, the error against the truth
(sigma_s' per channel for the scene, D per channel for the sphere) with its 95 % interval and status, judged by the
current zoo rules / gradients_acceptance rows for both; then the ratio anchor / current (CPU: the acceptance's
number, wall beside it) and "same accuracy" (both within 10 % of the truth, or the current error no larger than the
anchor's plus the current interval's half-width, channel by channel; every status the same or better).

The sphere's current tree runs twice (branch lut19): ``cold`` (``SSSRIG_LUT_CACHE=off`` and the LED response LUT of
the warm-up forgotten, so the timed estimate builds its LUT and solve tables: the first capture on a new LED layout)
and ``current`` (the LUT of the warm-up reused: a later capture of the same layout); ratio and "same accuracy" are
printed for both (JSON keys ``*_cold`` and the plain ones).

Run: ``NUMBA_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 nice python benchmarks/reference_speed.py [--skip-scene]
[--skip-sphere] [--trees anchor,current] [--json OUT]``. The machine is shared: the trees run back to back, and CPU
seconds (one numba thread) are the load-independent number.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))

#: the start of issue 19: the parent of 9b1ed69 ("benchmarks/mc_vs_mitsuba.py: first version"), the issue's first commit
ANCHOR_COMMIT = "654c245"
TOL = 0.10
SCENE_INDEX = 10
#: the current tree runs the single-image reference in its default mode, "hybrid" (rig.estimate.scenes
#: DEFAULT_REFERENCE_MODE; z10 stays in its adaptive pass: its sigma_s' is ok; the anchor has one mode)
SCENE_OPTS = {"model": "mc-table+reference", "spp": 128, "iterations": 6, "reference_seed": 1,
              "reference_mode": "hybrid"}
SPHERE_OPTS = {"spp": 64, "iterations": 8, "reference": {"seed": 1}}


def anchor_tree(commit: str = ANCHOR_COMMIT) -> Path:
    """A git worktree of ``commit`` (made once; detached, never edited) outside this checkout, so that nothing scanning
    the tree (tests/test_architecture.py, lint-imports) sees the anchor's modules: ``$SSSRIG_ANCHOR_TREE``, else
    ``$XDG_CACHE_HOME/sssrig/reference-speed/anchor-<commit>`` (default ``~/.cache``)."""
    full = subprocess.run(["git", "-C", str(ROOT), "rev-parse", commit], check=True, capture_output=True,
                          text=True).stdout.strip()
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "sssrig" / "reference-speed"
    tree = Path(os.environ.get("SSSRIG_ANCHOR_TREE") or cache / f"anchor-{full[:12]}")
    if not (tree / "rig").is_dir():
        tree.parent.mkdir(parents=True, exist_ok=True)
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), full], check=True,
                       capture_output=True)
    return tree


def _cached(root: Path, match: Any) -> Path | None:
    """The newest cached folder under ``root`` whose meta.json satisfies ``match`` (any renderer hash)."""
    found = [f for f in root.iterdir() if (f / "meta.json").exists()
             and match(json.loads((f / "meta.json").read_text()))] if root.exists() else []
    return max(found, key=lambda f: (f / "meta.json").stat().st_mtime) if found else None


def scene_item() -> tuple[Path, Any]:
    from zoo.frames import build_scene, default_root
    from zoo.scenes import draw_zoo

    spec = {s.index: s for s in draw_zoo()}[SCENE_INDEX]
    want = json.loads(json.dumps(spec.to_json()))
    folder = _cached(default_root(), lambda m: m.get("spec") == want) or build_scene(spec, default_root())[0]
    return folder, spec


def sphere_item(material: str = "skin1") -> tuple[Path, Any]:
    from benchmarks.gradients_acceptance import full_cases
    from benchmarks.gradients_cases import build_case, default_root

    case = next(c for c in full_cases() if c.family == "sphere" and c.material == material and c.radius_mm == 5.0)
    want = json.loads(json.dumps(case.render_key()))
    folder = _cached(default_root(), lambda m: {k: v for k, v in (m.get("case") or {}).items() if k not in (
        "reference", "reference_spp", "reference_iterations")} == want) or build_case(case)[0]
    return folder, case


def run_tree(tree: Path, kind: str, folder: Path, opts: dict[str, Any]) -> dict[str, Any]:
    """One timed estimate in a fresh subprocess; ``opts["lut"] == "cold"``: no LUT from disk or from the warm-up."""
    env = {**os.environ, "PYTHONPATH": f"{tree}{os.pathsep}{tree / 'benchmarks'}", "NUMBA_NUM_THREADS": "1",
           "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    if opts.get("lut") == "cold":
        env["SSSRIG_LUT_CACHE"] = "off"
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, str(HERE / "_reference_speed_driver.py"), kind, str(folder),
                        json.dumps(opts)], env=env, capture_output=True, text=True, cwd=str(tree))
    if p.returncode != 0:
        raise RuntimeError(f"{tree.name} {kind}: exit {p.returncode}\n{p.stderr[-4000:]}")
    out = json.loads(p.stdout.strip().splitlines()[-1])
    out["process_seconds"] = time.perf_counter() - t0
    return out


def scene_row(run: dict[str, Any], spec: Any) -> dict[str, Any]:
    from zoo.rules import REFERENCE_MODEL, evaluate

    res = run["result"]
    ref = res.get("reference") or {}
    rows = evaluate(res, REFERENCE_MODEL, list(spec.sigma_s_prime_per_mm), list(spec.sigma_a_per_mm))
    renders = list(ref.get("renders") or [])
    return {"quantity": "sigma_s'", "truth": list(spec.sigma_s_prime_per_mm), "err": [r["err_s"] for r in rows],
            "interval": [r["ci_s"] for r in rows], "status": [r["status_s"] for r in rows],
            "converged": res.get("converged"), "reference_seconds": float(ref.get("seconds_total") or math.nan),
            "renders": [f"{r.get('spp', '?')}spp" for r in renders], "render_seconds":
            float(sum(float(r.get("seconds") or 0.0) for r in renders))}


def sphere_row(run: dict[str, Any], case: Any) -> dict[str, Any]:
    from benchmarks.gradients_acceptance import case_rows

    summary = run["result"]
    rows = case_rows(case, summary)
    d = summary.get("diffusion_reference_corrected") or {}
    ref = d.get("reference") or {}
    spp = ref.get("render_spp") or [ref.get("spp")] * len(ref.get("render_seconds") or [])
    return {"quantity": "D", "truth": [r["truth"] for r in rows], "err": [r["err"] for r in rows],
            "interval": [r["interval"] for r in rows], "status": [r["status"] for r in rows],
            "converged": d.get("converged"), "reference_seconds": float(d.get("seconds") or math.nan),
            "renders": [f"{s}spp" for s in spp],
            "render_seconds": float(sum(ref.get("render_seconds") or []))}


def same_accuracy(old: dict[str, Any], new: dict[str, Any]) -> list[bool]:
    """Channel by channel: both within TOL of the truth, or the new error no larger than the old one plus the new
    interval's relative half-width; and the new status "ok" wherever the old one was."""
    same = []
    for c, (eo, en) in enumerate(zip(old["err"], new["err"])):
        if not (eo == eo and en == en):
            same.append(bool(eo != eo and en != en))
            continue
        lo, hi = new["interval"][c]
        t = new["truth"][c]
        ok_lohi = lo is not None and hi is not None and math.isfinite(lo) and math.isfinite(hi)
        half = 0.5 * (hi - lo) / t if ok_lohi else math.inf
        acc = (abs(eo) <= TOL and abs(en) <= TOL) or abs(en) <= abs(eo) + half
        status_ok = not (old["status"][c] == "ok" and new["status"][c] != "ok")
        same.append(bool(acc and status_ok))
    return same


def _line(tree: str, run: dict[str, Any], row: dict[str, Any]) -> str:
    errs = ", ".join(f"{e:+.1%}" if e == e else "nan" for e in row["err"])
    ivs = ", ".join("[-]" if lo is None else f"[{lo:.4g}, {hi:.4g}]" for lo, hi in row["interval"])
    return (f"  {tree:8s} CPU {run['cpu_seconds']:7.1f} s, wall {run['seconds']:7.1f} s; reference loop CPU "
            f"{run['loop_cpu_seconds']:6.1f} s ({run['loop_calls']} call), wall {row['reference_seconds']:6.1f} s, renders {len(row['renders'])} ({' '.join(row['renders'])}) wall "
            f"{row['render_seconds']:6.1f} s; {row['quantity']} err {errs}; 95 % {ivs}; status {row['status']}; "
            f"converged {row['converged']}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--skip-scene", action="store_true")
    ap.add_argument("--skip-sphere", action="store_true")
    ap.add_argument("--trees", default="anchor,current", help="which trees to time (default both)")
    ap.add_argument("--anchor", default=ANCHOR_COMMIT, help=f"anchor commit (default {ANCHOR_COMMIT})")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--reference-mode", choices=("adaptive", "hybrid", "legacy"), default=SCENE_OPTS["reference_mode"],
                    help="the current tree's single-image reference mode (default %(default)s; hybrid: adaptive, "
                         "legacy where sigma_s' is not ok)")
    args = ap.parse_args(argv)
    trees = {"anchor": None, "current": ROOT}
    names = [t for t in args.trees.split(",") if t]
    if "anchor" in names:
        trees["anchor"] = anchor_tree(args.anchor)
    t_all = time.perf_counter()
    print(f"# reference_speed (issue 19 acceptance line 2): anchor {args.anchor} ({trees['anchor']}), current "
          f"{ROOT}; load {os.getloadavg()[0]:.2f}", flush=True)
    items = []
    if not args.skip_scene:
        folder, spec = scene_item()
        items.append(("scene", folder, spec, {**SCENE_OPTS, "reference_mode": args.reference_mode}, scene_row,
                      f"z{SCENE_INDEX:02d} {spec.name}"))
    if not args.skip_sphere:
        folder, case = sphere_item()
        items.append(("sphere", folder, case, SPHERE_OPTS, sphere_row, case.name))
    doc: list[dict[str, Any]] = []
    for kind, folder, truth, opts, row_fn, label in items:
        print(f"\n## {label} ({folder.name})", flush=True)
        runs, rows = {}, {}
        # the sphere's current tree twice: LUT cold (built in the timed run: the first capture on a rig) and warm
        variants = [(n, n, opts) for n in names if n != "current" or kind != "sphere"]
        if kind == "sphere" and "current" in names:
            variants += [("cold", "current", {**opts, "lut": "cold"}), ("current", "current", opts)]
        for name, tree, o in variants:
            print(f"# {name} ... (load {os.getloadavg()[0]:.2f})", file=sys.stderr, flush=True)
            runs[name] = run_tree(trees[tree], kind, folder, o)  # type: ignore[arg-type]
            rows[name] = row_fn(runs[name], truth)
            print(_line(name, runs[name], rows[name]), flush=True)
        entry: dict[str, Any] = {"item": label, "kind": kind, "folder": str(folder), "options": opts,
                                 "runs": {n: {k: v for k, v in r.items() if k != "result"} | {"row": rows[n]}
                                          for n, r in runs.items()}}
        for cur in [n for n in ("cold", "current") if n in runs and "anchor" in runs]:
            a, c = runs["anchor"], runs[cur]
            ratio, ratio_wall = a["cpu_seconds"] / c["cpu_seconds"], a["seconds"] / c["seconds"]
            ratio_loop = a["loop_cpu_seconds"] / c["loop_cpu_seconds"]
            same = same_accuracy(rows["anchor"], rows[cur])
            sfx = "_cold" if cur == "cold" else ""
            entry.update({f"ratio_cpu{sfx}": ratio, f"ratio_wall{sfx}": ratio_wall,
                          f"ratio_loop_cpu{sfx}": ratio_loop, f"same_accuracy{sfx}": same})
            what = {"cold": "current, LUT cold",
                    "current": "current, LUT warm" if kind == "sphere" else "current"}[cur]
            print(f"  RATIO anchor / {what}: whole estimate CPU {a['cpu_seconds']:.1f} / {c['cpu_seconds']:.1f} s = "
                  f"{ratio:.2f}x (target >= 3: {'PASS' if ratio >= 3 else 'FAIL'}), wall {ratio_wall:.2f}x; reference "
                  f"loop CPU {a['loop_cpu_seconds']:.1f} / {c['loop_cpu_seconds']:.1f} s = {ratio_loop:.2f}x (target "
                  f">= 3: {'PASS' if ratio_loop >= 3 else 'FAIL'}); same accuracy per channel {same}: "
                  f"{'PASS' if all(same) else 'FAIL'}", flush=True)
        doc.append(entry)
    print(f"\ntotal {time.perf_counter() - t_all:.0f} s, load {os.getloadavg()[0]:.2f}")
    if args.json:
        args.json.write_text(json.dumps(doc, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
