"""Issue 16's acceptance, printed: diffusion estimates from Monte Carlo gradient captures through the user path.

Every case (:mod:`benchmarks.gradients_cases`: frames of the project's Monte Carlo renderer with camera noise,
written as a capture folder and cached by content hash) is estimated by :func:`rig.estimate.capture_folder.estimate_capture`
on :func:`rig.estimate.capture_folder.load_capture` of that folder -- the library entry ``rig estimate gradients FOLDER``
calls -- with the CLI's defaults (``--reference`` where the case says so: ``reference_spp`` paths, at most
``reference_iterations`` renders, the CLI's reference seed 1):

- (a) relief slabs, each estimated twice: with the rendered normals given as ``[object] shape = "relief"``,
  ``normals_file`` (a relief of known geometry) and without geometry (shape "unknown": the specular normals of
  the same capture stand in for the true ones); the relief fit of ``estimation.relief`` over one window = the
  whole map: quantity l_d, from ``diffusion.l_d_mm``;
- (b) 5 mm (radius) spheres with ``--reference``: quantity D, from ``diffusion_reference_corrected.D_mm``;
- (c) 25 mm spheres, plain (the weak-information case: little curvature signal): quantity D, from
  ``diffusion.D_mm``.

Printed per case and channel: truth, estimate, relative error, 95 % interval, covered?, status (the estimator's:
ok / weak / unknown; a reference-corrected channel reports ``diffusion_reference_corrected.status``), then the
rules of the acceptance, each as one line with its count and PASS / FAIL:

1. relief slabs of marble, skin1, apple, skimmilk with their normals given (normals_file): l_d within 25 % in
   every channel and the channel order (of the truth's l_d) right; ketchup's dark channels (G, B) "unknown" (both
   geometries); the specular-normals estimates count in rules 3 and 4;
2. 5 mm spheres with --reference: D within 10 % in at least 13 of 15 channels (13/15 of the channels run), every
   other channel flagged (status not "ok") with an interval that covers the truth;
3. every case and channel with an interval: the 95 % intervals cover the truth in at least 90 %;
4. zero results more than 25 % off that are neither "weak" (or "unknown") nor covered by their interval.

An "unknown" channel (no number) counts with the interval [0, inf]: it claims nothing, so it covers the truth.

Run: ``python benchmarks/gradients_acceptance.py [--quick] [--json OUT] [--cases SUBSTRING,...] [--reprint JSON]`` (or
``python benchmarks/mc_gradients.py --acceptance ...``). ``--quick``: one relief slab (skin1, P 2.5 mm) and one
5 mm sphere (skin1) at small size. Exit status 0 whatever the rules say (the lines are the verdict).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from benchmarks.gradients_cases import Case, build_case, truth, with_noise, with_normals_file  # noqa: E402
from rig.files.provenance import write_json  # noqa: E402

CHANNELS = "RGB"
RELIEF_MATERIALS = ("marble", "skin1", "apple", "skimmilk", "ketchup")
ORDER_MATERIALS = ("marble", "skin1", "apple", "skimmilk")
SPHERE_MATERIALS = ("apple", "ketchup", "marble", "skimmilk", "skin1")
RELIEF_PERIODS_MM = (2.5, 4.0)
RELIEF_WITHIN = 0.25
SPHERE_WITHIN = 0.10
SPHERE_MIN_FRACTION = 13 / 15
COVERAGE_MIN = 0.90
CONFIDENT_WRONG = 0.25


# paths per pixel of the relief frames: short walks (skin1, ketchup: ~15 collisions) get 4x the paths of the long
# ones (marble, apple, skimmilk: 170+), about the same render seconds; at 16 spp skin1's blue frames are ~45 %
# noisy per pixel and most pixels unknown
RELIEF_SPP = {"marble": 16, "apple": 16, "skimmilk": 16, "skin1": 64, "ketchup": 64}


def full_cases() -> list[Case]:
    from rig.estimate.reference.folder_reference import REFERENCE_ITERATIONS     # the CLI's default render budget

    cases = [Case("sphere", m, size_px=32, spp=64, radius_mm=5.0, reference=True,
                  reference_iterations=REFERENCE_ITERATIONS) for m in SPHERE_MATERIALS]
    cases += [Case("sphere", m, size_px=32, spp=64, radius_mm=25.0) for m in SPHERE_MATERIALS]
    cases += [Case("relief", m, size_px=40, spp=RELIEF_SPP[m], period_mm=p, pixel_mm=0.25)
              for p in RELIEF_PERIODS_MM for m in RELIEF_MATERIALS]
    return cases


def quick_cases() -> list[Case]:
    """``--quick``: small renders of skin1 (short walks): a relief slab and a 5 mm sphere with --reference."""
    return [Case("relief", "skin1", size_px=20, spp=32, period_mm=2.5, pixel_mm=0.25),
            Case("sphere", "skin1", size_px=16, spp=32, radius_mm=5.0, reference=True, reference_spp=32,
                 reference_iterations=2)]


def ci_cases() -> list[Case]:
    """The CI subset (tests/test_gradients_acceptance.py, 28 s measured at load 7): one 16 px skin1 relief slab at 16
    spp (the smallest relief window). Every capture estimate
    builds its LED response LUT (~10 s on a shared core), and a 5 mm sphere with --reference costs about a minute
    more (tests/rig/test_capture_folder.py runs the --reference loop end to end on a 10 mm sphere)."""
    return [Case("relief", "skin1", size_px=16, spp=16, period_mm=2.5, pixel_mm=0.25)]


# --------------------------------------------------------------------------------------------------------------
def _num(x: Any) -> float:
    return float("nan") if x is None else float(x)


def estimate_case(case: Case, folder: Path, out_dir: Path) -> tuple[dict[str, Any], float]:
    """``rig estimate gradients FOLDER [--reference ...] --json``'s summary, through the CLI's library entry."""
    from rig.estimate.capture_folder import estimate_capture, load_capture

    out_dir.mkdir(parents=True, exist_ok=True)

    ref = ({"spp": case.reference_spp, "iterations": case.reference_iterations, "seed": None}
           if case.reference else None)
    if ref is not None:
        ref = {k: v for k, v in ref.items() if v is not None}
    t0 = time.perf_counter()
    summary = estimate_capture(load_capture(folder), out_dir, reference=ref)
    return summary, time.perf_counter() - t0


def case_rows(case: Case, summary: dict[str, Any], geometry: str = "") -> list[dict[str, Any]]:
    """One row per channel: the quantity of the case's rule, truth, estimate, interval, status; ``geometry``: how
    a relief case's true normals were given ("normals_file" | "specular")."""
    t = truth(case.material)
    if case.family == "relief":
        q, d = "l_d_mm", summary.get("diffusion", {})
        st = list(d.get("status", ["unknown"] * 3))
    elif case.reference:
        q, d = "D_mm", summary.get("diffusion_reference_corrected") or {}
        st = list(d.get("status", ["unknown"] * 3)) if d else ["failed: no reference-corrected summary"] * 3
    else:
        q, d = "D_mm", summary.get("diffusion", {})
        st = list(d.get("status", ["unknown"] * 3))
    block = d.get(q) or {}
    vals = block.get("value") or [None] * 3
    ivs = block.get("interval") or [[None, None]] * 3
    rows = []
    for c in range(3):
        tv = float(t[q][c])
        v = _num(vals[c])
        iv = ivs[c] if ivs[c] is not None else (None, None)
        has_iv = iv[0] is not None or iv[1] is not None      # JSON null: 0 below, infinity above
        lo = _num(iv[0]) if iv[0] is not None else 0.0
        hi = _num(iv[1]) if iv[1] is not None else math.inf
        lo_c, hi_c = (lo if np.isfinite(lo) else 0.0), (hi if not np.isnan(hi) else math.inf)
        rows.append(_unknown_is_everything({"case": case.name + (f" ({geometry})" if geometry else ""),
                     "geometry": geometry,
                     "family": case.family, "material": case.material, "channel": CHANNELS[c],
                     "quantity": q, "truth": tv, "estimate": v, "err": v / tv - 1.0 if np.isfinite(v) else math.nan,
                     "interval": [lo, hi], "has_interval": bool(has_iv),
                     "covered": bool(has_iv and lo_c <= tv <= hi_c), "status": str(st[c]),
                     "radius_mm": case.radius_mm, "period_mm": case.period_mm, "reference": case.reference}))
    return rows


def _unknown_is_everything(row: dict[str, Any]) -> dict[str, Any]:
    """An "unknown" channel states no number: its interval is the whole range [0, inf] (as the relief fit reports
    it; the sphere summaries write none), which covers any truth."""
    if row["status"] == "unknown" and not row["has_interval"]:
        row.update(interval=[0.0, math.inf], has_interval=True, covered=True)
    return row


# --------------------------------------------------------------------------------------------------------------
def _flagged(status: str) -> bool:
    return status != "ok"


def rules(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The acceptance rules over whichever cases ran: [{rule, count, needed, pass, detail}]."""
    out: list[dict[str, Any]] = []
    rel = [r for r in rows if r["family"] == "relief" and r["material"] in ORDER_MATERIALS
           and r["geometry"] == "normals_file"]
    if rel:
        within = sum(abs(r["err"]) <= RELIEF_WITHIN for r in rel if np.isfinite(r["err"]))
        by_case: dict[str, list[dict[str, Any]]] = {}
        for r in rel:
            by_case.setdefault(r["case"], []).append(r)
        order_ok = 0
        for rs in by_case.values():
            e = np.array([r["estimate"] for r in rs])
            tv = np.array([r["truth"] for r in rs])
            order_ok += bool(np.all(np.isfinite(e)) and np.array_equal(np.argsort(-e), np.argsort(-tv)))
        n = len(rel)
        out.append({"rule": f"relief (normals_file) l_d within {RELIEF_WITHIN:.0%} ({', '.join(ORDER_MATERIALS)})",
                    "count": within,
                    "needed": n, "of": n, "pass": within == n})
        out.append({"rule": "relief (normals_file) channel order right", "count": order_ok, "needed": len(by_case),
                    "of": len(by_case), "pass": order_ok == len(by_case)})
    dark = [r for r in rows if r["family"] == "relief" and r["material"] == "ketchup" and r["channel"] in "GB"]
    if dark:
        unk = sum(r["status"] == "unknown" for r in dark)
        out.append({"rule": "relief ketchup G, B unknown (both geometries)", "count": unk, "needed": len(dark), "of": len(dark),
                    "pass": unk == len(dark)})
    sph = [r for r in rows if r["family"] == "sphere" and r["reference"] and r["radius_mm"] == 5.0]
    if sph:
        within = [np.isfinite(r["err"]) and abs(r["err"]) <= SPHERE_WITHIN for r in sph]
        need = math.ceil(SPHERE_MIN_FRACTION * len(sph) - 1e-9)
        others = [r for r, w in zip(sph, within) if not w]
        flagged = sum(_flagged(r["status"]) and r["covered"] for r in others)
        out.append({"rule": f"5 mm spheres --reference: D within {SPHERE_WITHIN:.0%}", "count": int(sum(within)),
                    "needed": need, "of": len(sph), "pass": sum(within) >= need})
        out.append({"rule": "5 mm spheres --reference: every other channel flagged with a covering interval",
                    "count": flagged, "needed": len(others), "of": len(others), "pass": flagged == len(others)})
    with_iv = [r for r in rows if r["has_interval"]]
    cov = sum(r["covered"] for r in with_iv)
    need = math.ceil(COVERAGE_MIN * len(with_iv) - 1e-9)
    out.append({"rule": f"95 % intervals cover the truth (>= {COVERAGE_MIN:.0%})", "count": cov, "needed": need,
                "of": len(with_iv), "pass": cov >= need and len(with_iv) > 0})
    bad = [r for r in rows if np.isfinite(r["err"]) and abs(r["err"]) > CONFIDENT_WRONG
           and r["status"] == "ok" and not r["covered"]]
    out.append({"rule": f"confidently wrong (> {CONFIDENT_WRONG:.0%} off, status ok, not covered)",
                "count": len(bad), "needed": 0, "of": len(rows), "pass": not bad,
                "detail": [f"{r['case']} {r['channel']}" for r in bad]})
    return out


# --------------------------------------------------------------------------------------------------------------
def _f(x: float) -> str:
    return "nan" if not np.isfinite(x) else f"{x:.4g}"


def _e(x: float) -> str:
    return "n/a" if not np.isfinite(x) else f"{x:+.1%}"


def print_rows(rows: list[dict[str, Any]], metas: dict[str, dict[str, Any]]) -> None:
    print("| case | ch | quantity | truth | estimate | error | 95 % interval | covered | status |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        lo, hi = r["interval"]
        iv = f"[{_f(lo)}, {_f(hi) if not np.isinf(hi) else 'inf'}]" if r["has_interval"] else "none"
        print(f"| {r['case']} | {r['channel']} | {r['quantity']} | {r['truth']:.4g} | {_f(r['estimate'])} | "
              f"{_e(r['err'])} | {iv} | {'yes' if r['covered'] else 'no'} | {r['status']} |")
    print("\n| case | render s | cached | estimate s | frame max | saturated px | object px | slab (extent x thickness "
          "mm) |")
    print("|---|---|---|---|---|---|---|---|")
    for name, m in metas.items():
        slab = (f"{m['slab_extent_mm']:.0f} x {m['slab_thickness_mm']:.0f}" if "slab_extent_mm" in m else "")
        print(f"| {name} | {m['render_seconds']:.1f} | {m['cached']} | {m['estimate_seconds']:.1f} | "
              f"{m['frame_max']:.3f} | {m['saturated_px']} | {m['object_pixels']} | {slab} |")


def print_rules(rs: list[dict[str, Any]]) -> None:
    print("\n## Acceptance rules (on the cases that ran)\n")
    for r in rs:
        det = f"  [{'; '.join(r['detail'])}]" if r.get("detail") else ""
        print(f"- {r['rule']}: {r['count']} of {r['of']} (needed {r['needed']}{' = max' if r['rule'].startswith('confidently') else ''}) "
              f"{'PASS' if r['pass'] else 'FAIL'}{det}")


def run(cases: list[Case], root: Path | None = None, out_dir: Path | None = None, verbose: bool = True,
        relief_geometries: tuple[str, ...] = ("normals_file", "specular"), noise: bool = False) -> dict[str, Any]:
    """Render (or load) and estimate every case (relief cases once per entry of ``relief_geometries``); ``noise``:
    state the cases' camera noise in ``[noise]`` (a copy of each folder) so the intervals propagate it. Returns
    {rows, metas, rules}."""
    rows: list[dict[str, Any]] = []
    metas: dict[str, dict[str, Any]] = {}
    tmp = tempfile.TemporaryDirectory(prefix="gradients-acceptance-") if out_dir is None else None
    base = Path(tmp.name) if tmp is not None else Path(out_dir)  # type: ignore[arg-type]
    try:
        for i, case in enumerate(cases):
            folder, meta = build_case(case, root)
            if verbose:
                print(f"# {case.name}: {'cached' if meta['cached'] else 'rendered'} "
                      f"({meta['render_seconds']:.1f} s to render) {folder}", file=sys.stderr, flush=True)
            variants = [(g, with_normals_file(folder, base / f"case{i}") if g == "normals_file" else folder)
                        for g in relief_geometries] if case.family == "relief" else [("", folder)]
            if noise:
                variants = [(g, with_noise(f, f if f != folder else base / f"case{i}{g}noise")) for g, f in variants]
            sec_all = 0.0
            for geo, f in variants:
                try:
                    summary, sec = estimate_case(case, f, base / f"maps{i}{geo}")
                    crow = case_rows(case, summary, geo)
                except Exception as exc:   # a failure is rows that say why
                    sec = float("nan")
                    crow = case_rows(case, {}, geo)
                    for r in crow:
                        r["status"] = f"failed: {type(exc).__name__}: {exc}"
                sec_all += sec
                rows += crow
                if verbose:
                    for r in crow:
                        print(f"  {r['case']} {r['channel']}: {r['quantity']} {_f(r['estimate'])} (truth "
                              f"{r['truth']:.4g}, {_e(r['err'])}) [{_f(r['interval'][0])}, {_f(r['interval'][1])}]"
                              f" {r['status']}", file=sys.stderr, flush=True)
            meta["estimate_seconds"] = sec_all
            metas[case.name] = meta
    finally:
        if tmp is not None:
            tmp.cleanup()
    return {"rows": rows, "metas": metas, "rules": rules(rows)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the CI subset: one small relief slab, one 5 mm sphere")
    ap.add_argument("--json", type=Path, metavar="OUT", help="write rows, render facts and rules as JSON")
    ap.add_argument("--cases", help="comma-separated substrings: run the cases whose name contains any")
    ap.add_argument("--noise", action="store_true", help="state the cases' camera noise in [noise] (1.5 e-/DN, "
                    "2 DN read noise): the estimates propagate it into their intervals (docs/gradients.md sec. 9)")
    ap.add_argument("--reprint", type=Path, metavar="JSON", help="print the table and rules of a --json file "
                    "again (rules re-derived from its rows; nothing rendered or estimated)")
    args = ap.parse_args(argv)
    if args.reprint:
        old = json.loads(args.reprint.read_text())
        rows = [_unknown_is_everything(r) for r in old["rows"]]
        print(f"# Issue 16 acceptance, reprinted from {args.reprint} ({len(old['metas'])} cases, run "
              f"{old.get('seconds_total', float('nan')):.0f} s)\n")
        print_rows(rows, old["metas"])
        print_rules(rules(rows))
        return 0
    cases = quick_cases() if args.quick else full_cases()
    if args.cases:
        keys = [s.strip() for s in args.cases.split(",") if s.strip()]
        cases = [c for c in cases if any(k in c.name for k in keys)]
    import numba

    t0 = time.perf_counter()
    print(f"# Issue 16 acceptance ({'quick' if args.quick else 'full'}; {len(cases)} cases"
          f"{'; [noise] stated' if args.noise else ''}): machine "
          f"{platform.machine()}, {os.cpu_count()} CPUs, numba threads {numba.get_num_threads()}, load "
          f"{os.getloadavg()[0]:.2f}\n")
    res = run(cases, noise=args.noise)
    print_rows(res["rows"], res["metas"])
    print_rules(res["rules"])
    total = time.perf_counter() - t0
    print(f"\ntotal {total:.1f} s (render {sum(m['render_seconds'] for m in res['metas'].values() if not m['cached']):.1f}"
          f" s of it new; load {os.getloadavg()[0]:.2f})")
    if args.json:
        write_json(args.json, {"cases": [asdict(c) for c in cases], **res, "seconds_total": total}, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
