"""Reference-corrected relief fit on issue 16's relief slabs (estimation.relief_correction), measured.

The relief cases of :mod:`benchmarks.gradients_cases` are slabs whose relief is known to the benchmark (a
``simulators.scene.BumpySlabObject`` of the case's period, RMS slope and seed). A *reference* renders that same
relief (same camera, LEDs, black backing, patterns, polarizations) with Monte Carlo at any (sigma_s', sigma_a) per
channel, writes it as a capture folder with the rendered normals given (``[object] shape = "relief"``,
``normals_file``), and reads it with the CLI's own entry (:func:`rig.estimate.capture_folder.estimate_capture`, the
same maps and window pipeline as the frame): :func:`reference_reader` is the ``render_and_read`` callable of
:func:`estimation.relief_correction.correct_relief_with_reference`. Renders are cached under
``benchmarks/out/relief_reference/<hash>/`` (hash: the case's geometry, the material, spp, seed, noise, the Monte
Carlo renderer's sources, ``RENDER_VERSION``).

Modes (``python benchmarks/relief_reference.py MODE --material skin1 --period 4 ...``):

- ``bias``: a quiet render at the truth (``--spp`` paths, no camera noise, seed ``--seed``) and, with
  ``--truth-seeds``, more of them: what the pipeline reads against the truth (the estimator's bias with little
  noise, mean over seeds); the first one corrected by the loop with references pooled over ``--ref-seeds``; and the
  frame's Monte Carlo standard error against the camera's (the cases' sensor: 1.5 e-/DN, read noise 2 DN) --
  issue 16's "noise as a real camera would add";
- ``loop``: the acceptance case's own frames (16-64 spp with camera noise, ``benchmarks.gradients_cases``, normals
  given) corrected by references; or with ``--frame-spp N`` a frame rendered at N spp with camera noise;
- ``acceptance``: every relief case (``--cases`` to choose), the rule lines of benchmarks/gradients_acceptance.py
  before and after the loop; ``reprint --before GA.json --after A.json...``: the same from saved JSONs.

Output: per channel truth, uncorrected and corrected l', 1 - alpha', l_d, intervals, status; ``--json OUT``.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from benchmarks import gradients_cases as gc  # noqa: E402
from estimation.relief import parameters_from_l_prime  # noqa: E402
from estimation.relief_correction import (ReliefReading, correct_relief_with_reference,  # noqa: E402
                                          reading_from_summary)

RENDER_VERSION = 1
ROOT_OUT = gc.ROOT / "benchmarks" / "out" / "relief_reference"
MAX_MARGIN_MM = 60.0
CHANNELS = "RGB"


def case_for(material: str, period_mm: float, size_px: int = 40, pixel_mm: float = 0.25, spp: int | None = None,
             seed: int = 0) -> gc.Case:
    from benchmarks.gradients_acceptance import RELIEF_SPP
    return gc.Case("relief", material, size_px=size_px, spp=spp or RELIEF_SPP[material], seed=seed,
                   period_mm=period_mm, pixel_mm=pixel_mm)


def _margin_mm(ssp: np.ndarray, sa: np.ndarray) -> float:
    ld = 1.0 / np.sqrt(3.0 * sa * (ssp + sa))
    return float(np.clip(gc.MARGIN_L_D * np.max(ld), 3.0, MAX_MARGIN_MM))


def render_relief(case: gc.Case, ssp: np.ndarray, sa: np.ndarray, spp: int, seed: int, noise: bool,
                  root: Path = ROOT_OUT) -> tuple[Path, dict[str, Any]]:
    """A capture folder of ``case``'s relief (geometry seed ``case.seed``) rendered with (``ssp``, ``sa``) per
    channel, ``spp`` paths, Monte Carlo seed ``seed``, camera noise or not; normals given. Cached."""
    from drivers.atomic import atomic_write
    from estimation.camera import OrthographicCamera
    from rig.estimate.reference.folder_reference import renderable_camera
    from rig.estimate.capture_folder.write import write_frames_and_leds
    from simulators.mc._cache import sources_hash
    from simulators.mc_capture import MCSettings
    from simulators.scene import BumpySlabObject, render_gradient_capture

    ssp = np.asarray(ssp, dtype=np.float64)
    sa = np.asarray(sa, dtype=np.float64)
    key = {"geometry": {k: getattr(case, k) for k in ("size_px", "period_mm", "pixel_mm", "seed")},
           "ssp": [float(f"{x:.6g}") for x in ssp], "sa": [float(f"{x:.6g}") for x in sa], "spp": int(spp),
           "mc_seed": int(seed), "noise": bool(noise), "version": RENDER_VERSION,
           "rms": gc.RELIEF_RMS_SLOPE, "waves": gc.RELIEF_WAVES, "backing": gc.RELIEF_BLACK_BACKING}
    h = hashlib.sha256(json.dumps(key, sort_keys=True).encode())
    h.update(sources_hash().encode())
    folder = root / h.hexdigest()[:16]
    if (folder / "meta.json").exists():
        return folder, json.loads((folder / "meta.json").read_text())
    (folder / "frames").mkdir(parents=True, exist_ok=True)
    margin = _margin_mm(ssp, sa)
    view = case.size_px * case.pixel_mm
    pos, inten, rig = gc._leds()
    patterns = {p: rig.pattern_values(p) for p in ("full", "x", "y", "z")}
    cam = renderable_camera(OrthographicCamera.looking_at(width_px=case.size_px, height_px=case.size_px,
                                                          pixel_size_mm=case.pixel_mm, direction=(0.0, 1.0, 0.0)))
    obj = BumpySlabObject((0.0, 0.0, 0.0), tuple(ssp), tuple(sa), gc.ETA, extent_mm=view + 2.0 * margin,
                          patch_mm=case.pixel_mm, rms_slope=gc.RELIEF_RMS_SLOPE,
                          wavelengths_mm=(case.period_mm, case.period_mm), n_waves=gc.RELIEF_WAVES, seed=case.seed)
    mc = MCSettings(spp=int(spp), seed=int(seed), leds="distant", relief_step_mm=case.pixel_mm,
                    slab_thickness_mm=margin)
    lit = inten * (pos[:, 1] < 0.0)[:, None] if gc.RELIEF_BLACK_BACKING else inten
    t0 = time.perf_counter()
    cap = render_gradient_capture(obj, cam, pos, lit, patterns, polarizations=("cross", "parallel"),
                                  exposure_s=gc.EXPOSURE_S, sensor=gc._sensor(), noise=bool(noise),
                                  rng=np.random.default_rng(1000 + int(seed)), render_mode="mc", mc=mc)
    seconds = time.perf_counter() - t0
    lines = ['format = "sssrig-capture"', "format_version = 1", 'name = "relief reference"', ""]
    lines += write_frames_and_leds(folder, cap.frames, gc.EXPOSURE_S, np.hstack([pos, inten]))
    np.save(folder / "true_normals.npy", np.nan_to_num(cap.normals).astype(np.float32))
    # the Monte Carlo standard error of the full cross frame, in frame units (for the frame-noise comparison)
    se = cap.diffuse_stderr or {}
    if "full" in se:
        np.save(folder / "full_cross_mc_stderr.npy", (0.5 * cap.value_per_radiance * se["full"]).astype(np.float32))
    lines += ["[camera]", 'model = "orthographic"',
              f"pixel_size_mm = {case.pixel_mm!r}", "look_direction = [0.0, 1.0, 0.0]", "", "[radiometry]",
              f"eta = {gc.ETA}", f"value_per_radiance_per_s = {gc.GAIN_DN_PER_UNIT / (gc.WHITE_DN - gc.BLACK_DN)!r}",
              "", "[object]", 'shape = "relief"', 'normals_file = "true_normals.npy"', ""]
    atomic_write(folder / "capture.toml", lambda p: p.write_text("\n".join(lines)))
    meta = {"key": key, "render_seconds": seconds, "margin_mm": margin}
    atomic_write(folder / "meta.json", lambda p: p.write_text(json.dumps(meta, indent=1)))
    return folder, meta


def read_folder(folder: Path) -> tuple[ReliefReading, dict[str, Any], float]:
    """The relief summary of a capture folder through the CLI's library entry (maps + windows + region)."""
    import tempfile

    from rig.estimate.capture_folder import estimate_capture, load_capture

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        summary = estimate_capture(load_capture(folder), Path(tmp) / "out")
    d = summary.get("diffusion", {})
    return reading_from_summary(d), d, time.perf_counter() - t0


def mean_reading(readings: list[ReliefReading]) -> ReliefReading:
    """Several readings of renders that differ only in their Monte Carlo seed, pooled: geometric means of l' and
    1 - alpha' over the usable ones, interval half-widths (log) divided by sqrt(n) (independent seeds); status "ok"
    where any read ok, "unknown" where none is usable."""
    if len(readings) == 1:
        return readings[0]
    use = np.stack([r.usable() for r in readings])
    n = use.sum(0)
    with np.errstate(divide="ignore", invalid="ignore"):
        lg = np.stack([np.where(u, np.log(r.l_prime_mm), 0.0) for r, u in zip(readings, use)])
        om = np.stack([np.where(u, np.log(1 - r.alpha_prime), 0.0) for r, u in zip(readings, use)])
        hl = np.stack([np.where(u, 0.5 * np.log(r.l_prime_interval_mm[:, 1] / r.l_prime_interval_mm[:, 0]), 0.0)
                       for r, u in zip(readings, use)])
        ha = np.stack([np.where(u, 0.5 * np.log((1 - r.alpha_prime_interval[:, 0]) / (1 - r.alpha_prime_interval[:, 1])),
                                0.0) for r, u in zip(readings, use)])
        l_m = np.where(n > 0, np.exp(lg.sum(0) / n), np.nan)
        om_m = np.where(n > 0, np.exp(om.sum(0) / n), np.nan)
        b = np.log1p(readings[0].model_bias_rel)
        h_l = np.maximum(hl.sum(0) / n - b, 0.0) / np.sqrt(n) + b
        h_a = ha.sum(0) / n / np.sqrt(n)
    st = tuple("unknown" if n[c] == 0 else ("ok" if any(r.status[c] == "ok" for r in readings) else "weak")
               for c in range(3))
    return ReliefReading(1 - om_m, l_m, np.stack([l_m * np.exp(-h_l), l_m * np.exp(h_l)], -1),
                         np.stack([1 - om_m * np.exp(h_a), 1 - om_m * np.exp(-h_a)], -1), st,  # type: ignore[arg-type]
                         readings[0].model_bias_rel)


def reference_reader(case: gc.Case, spp: int, seeds: tuple[int, ...], noise: bool = False,
                     log: list[dict[str, Any]] | None = None):
    """``render_and_read(alpha', l')`` for the loop: renders of the case's relief at those parameters, one per
    Monte Carlo seed of ``seeds`` (the same seeds at every step: common random numbers), each read by the CLI's
    pipeline, pooled by :func:`mean_reading`."""
    def render_and_read(alpha: np.ndarray, l_mm: np.ndarray) -> ReliefReading:
        ssp, sa = alpha / l_mm, (1.0 - alpha) / l_mm
        reads = []
        for sd in seeds:
            folder, meta = render_relief(case, ssp, sa, spp, sd, noise)
            r, _, est_s = read_folder(folder)
            reads.append(r)
            if log is not None:
                log.append({"folder": folder.name, "seed": sd, "render_seconds": meta["render_seconds"],
                            "estimate_seconds": est_s, "rendered_l_prime_mm": l_mm.tolist(),
                            "rendered_alpha_prime": alpha.tolist(), "read_l_prime_mm": r.l_prime_mm.tolist(),
                            "read_alpha_prime": r.alpha_prime.tolist()})
            print(f"  reference spp {spp} seed {sd}: alpha' {np.round(alpha, 5).tolist()} l' "
                  f"{np.round(l_mm, 4).tolist()} -> read alpha' {np.round(r.alpha_prime, 5).tolist()} l' "
                  f"{np.round(r.l_prime_mm, 4).tolist()} ({meta['render_seconds']:.0f} s render, {est_s:.0f} s "
                  f"estimate)", flush=True)
        return mean_reading(reads)
    return render_and_read


def truth_alpha_l(material: str) -> tuple[np.ndarray, np.ndarray]:
    ssp, sa = (np.asarray(x, dtype=np.float64) for x in gc.materials()[material])
    return ssp / (ssp + sa), 1.0 / (ssp + sa)


def rows(material: str, before: ReliefReading, corrected: Any) -> list[dict[str, Any]]:
    a_t, l_t = truth_alpha_l(material)
    t = parameters_from_l_prime(a_t, l_t)
    b = parameters_from_l_prime(before.alpha_prime, before.l_prime_mm)
    out = []
    for c in range(3):
        r = {"channel": CHANNELS[c], "l_prime_true": float(l_t[c]), "one_minus_alpha_true": float(1 - a_t[c]),
             "l_d_true": float(t["l_d_mm"][c]),
             "before": {"l_prime_err": float(b["l_prime_mm"][c] / l_t[c] - 1),
                        "one_minus_alpha_err": float((1 - b["alpha_prime"][c]) / (1 - a_t[c]) - 1),
                        "l_d_err": float(b["l_d_mm"][c] / t["l_d_mm"][c] - 1), "status": before.status[c]}}
        if corrected is not None:
            iv = corrected.intervals["l_d_mm"][c]
            r["after"] = {"l_prime_err": float(corrected.values["l_prime_mm"][c] / l_t[c] - 1),
                          "one_minus_alpha_err": float((1 - corrected.values["alpha_prime"][c]) / (1 - a_t[c]) - 1),
                          "l_d_err": float(corrected.values["l_d_mm"][c] / t["l_d_mm"][c] - 1),
                          "l_d_interval": iv.tolist(), "covered": bool(iv[0] <= t["l_d_mm"][c] <= iv[1]),
                          "status": corrected.status[c]}
        out.append(r)
    return out


def print_rows(rs: list[dict[str, Any]]) -> None:
    for r in rs:
        b = r["before"]
        line = (f"  {r['channel']}: l' {b['l_prime_err']:+.1%}  1-a' {b['one_minus_alpha_err']:+.1%}  l_d "
                f"{b['l_d_err']:+.1%} ({b['status']})")
        if "after" in r:
            a = r["after"]
            line += (f"  ->  l' {a['l_prime_err']:+.1%}  1-a' {a['one_minus_alpha_err']:+.1%}  l_d {a['l_d_err']:+.1%}"
                     f" [{a['l_d_interval'][0]:.3g}, {a['l_d_interval'][1]:.3g}] mm (truth {r['l_d_true']:.3g}) "
                     f"{'covered' if a['covered'] else 'NOT covered'} ({a['status']})")
        print(line, flush=True)


def frame_noise(folder: Path) -> dict[str, Any]:
    """Monte Carlo standard error of the full cross frame against the cases' camera noise (per channel, median
    over pixels): the camera's sd of a frame value I is sqrt(I / e + r^2) (e = 1.5 e-/DN x (white - black)
    electrons per value, r = 2 DN / (white - black); green averages two photosites: / sqrt 2)."""
    from rig.files.imageio import read_image

    se_p = folder / "full_cross_mc_stderr.npy"
    if not se_p.exists():
        return {}
    se = np.load(se_p).astype(np.float64)
    img = np.asarray(read_image(folder / "frames/full_cross.exr")[0], dtype=np.float64)
    span = float(gc.WHITE_DN - gc.BLACK_DN)
    e_per_value, r = 1.5 * span, 2.0 / span
    cam = np.sqrt(np.maximum(img, 0) / e_per_value + r * r) * np.array([1.0, 2 ** -0.5, 1.0])
    ratio = np.median((se / cam).reshape(-1, 3), axis=0)
    return {"mc_over_camera_sd": ratio.tolist(), "frame_value_median": np.median(img.reshape(-1, 3), 0).tolist()}


def acceptance(a: argparse.Namespace) -> int:
    """Issue 16's relief rule lines (benchmarks/gradients_acceptance.py's rules, normals given) before and after
    the reference loop, on the acceptance cases' own frames; references at ``--spp`` paths, seeds ``--ref-seeds``."""
    from benchmarks.gradients_acceptance import (RELIEF_MATERIALS, RELIEF_PERIODS_MM, case_rows, print_rules,
                                                 rules)

    seeds = tuple(int(x) for x in a.ref_seeds.split(",") if x.strip())
    want = [w.strip() for w in a.cases.split(",") if w.strip()]
    before_rows: list[dict[str, Any]] = []
    after_rows: list[dict[str, Any]] = []
    per_case: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    for p in RELIEF_PERIODS_MM:
        for m in RELIEF_MATERIALS:
            case = case_for(m, p)
            if want and not any(w in case.name for w in want):
                continue
            src, _ = gc.build_case(case)
            frame = gc.with_normals_file(src, ROOT_OUT / f"case-{src.name}")
            observed, d, est_s = read_folder(frame)
            print(f"# {case.name}: frame read in {est_s:.0f} s: alpha' {np.round(observed.alpha_prime, 5).tolist()} "
                  f"l' {np.round(observed.l_prime_mm, 4).tolist()} {observed.status}", flush=True)
            log: list[dict[str, Any]] = []
            tc = time.perf_counter()
            res = correct_relief_with_reference(observed, reference_reader(case, a.spp, seeds, log=log),
                                                max_renders=a.renders, min_one_minus_alpha=a.min_one_minus_alpha,
                                                l_prime_bounds_mm=(case.pixel_mm / 4, 2 * case.size_px * case.pixel_mm))
            rs = rows(m, observed, res)
            print_rows(rs)
            before_rows += case_rows(case, {"diffusion": d}, "normals_file")
            after_rows += case_rows(case, {"diffusion": res.as_dict()}, "normals_file")
            per_case.append({"case": case.name, "rows": rs, "correction": res.as_dict(), "references": log,
                             "loop_seconds": time.perf_counter() - tc})
            if a.json:
                a.json.write_text(json.dumps({"cases": per_case}, indent=1, default=float))
    print("## before (the frame's relief fit)")
    rb = rules(before_rows)
    print_rules(rb)
    print(f"## after the reference loop (references {a.spp} spp, seeds {list(seeds)}, at most {a.renders} renders)")
    ra = rules(after_rows)
    print_rules(ra)
    print(f"total {time.perf_counter() - t0:.0f} s, load {os.getloadavg()[0]:.2f}")
    if a.json:
        a.json.write_text(json.dumps({"cases": per_case, "rules_before": rb, "rules_after": ra,
                                      "rows_before": before_rows, "rows_after": after_rows,
                                      "seconds": time.perf_counter() - t0}, indent=1, default=float))
    return 0


def reprint(before_json: Path | None, after_jsons: list[Path]) -> int:
    """The rule lines before and after the loop over the cases that the acceptance-mode JSONs hold (partial or
    several runs), the before rows taken from a gradients_acceptance.py JSON of the same frames."""
    from benchmarks.gradients_acceptance import case_rows, print_rules, rules

    if before_json is None or not after_jsons:
        raise SystemExit("reprint needs --before GRADIENTS_ACCEPTANCE_JSON and --after ACCEPTANCE_JSON...")
    after: list[dict[str, Any]] = []
    done: list[str] = []
    for f in after_jsons:
        if not Path(f).is_file():
            raise SystemExit(f"--after: no such file {f}")
        for c in json.loads(Path(f).read_text()).get("cases", []):
            _, per, mat = c["case"].split()
            case = case_for(mat, float(per[1:-2]))
            after += case_rows(case, {"diffusion": c["correction"]}, "normals_file")
            done.append(case.name + " (normals_file)")
    before = [r for r in json.loads(Path(before_json).read_text())["rows"] if r["case"] in done]
    for label, rs in (("before (the frame's relief fit)", before), ("after the reference loop", after)):
        print(f"## {label}: {len(done)} cases")
        for r in rs:
            print(f"  {r['case']} {r['channel']}: l_d {r['err']:+.1%} [{r['interval'][0]:.3g}, {r['interval'][1]:.3g}] "
                  f"{'covered' if r['covered'] else 'NOT covered'} {r['status']}")
        print_rules(rules(rs))
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mode", choices=("bias", "loop", "acceptance", "reprint"))
    ap.add_argument("--before", type=Path, help="reprint: benchmarks/gradients_acceptance.py --json output of the same "
                                                 "frames (the before rows)")
    ap.add_argument("--after", type=Path, nargs="*", default=[], help="reprint: acceptance-mode JSONs (partial runs)")
    ap.add_argument("--cases", default="", help="acceptance: substrings of the relief case names to run (default all)")
    ap.add_argument("--min-one-minus-alpha", type=float, default=5e-4,
                    help="lower bound of 1 - alpha' of the rendered references (render cost; the truths are >= 1e-3)")
    ap.add_argument("--material", default="skin1")
    ap.add_argument("--period", type=float, default=4.0)
    ap.add_argument("--spp", type=int, default=256, help="paths per pixel of the quiet renders (references)")
    ap.add_argument("--seed", type=int, default=0, help="Monte Carlo seed of the quiet frame (bias mode)")
    ap.add_argument("--ref-seeds", default="1", help="Monte Carlo seeds of every reference (comma-separated: "
                                                     "their readings are pooled)")
    ap.add_argument("--truth-seeds", default="", help="bias mode: also read quiet renders at the truth with these "
                                                      "seeds (the pipeline's bias, averaged over seeds)")
    ap.add_argument("--renders", type=int, default=3, help="at most this many references")
    ap.add_argument("--frame-spp", type=int, default=0, help="loop: render the frame at this spp with camera noise "
                                                             "(0: the acceptance case's frames)")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    if a.mode == "acceptance":
        return acceptance(a)
    if a.mode == "reprint":
        return reprint(a.before, a.after)
    case = case_for(a.material, a.period)
    a_t, l_t = truth_alpha_l(a.material)
    ssp_t, sa_t = a_t / l_t, (1 - a_t) / l_t
    out: dict[str, Any] = {"mode": a.mode, "material": a.material, "period_mm": a.period, "spp": a.spp,
                           "load": os.getloadavg()[0]}
    t0 = time.perf_counter()
    if a.mode == "bias":
        frame, meta = render_relief(case, ssp_t, sa_t, a.spp, a.seed, noise=False)
        print(f"# quiet frame at the truth: {a.material} P {a.period:g} mm, {a.spp} spp, seed {a.seed}: "
              f"{meta['render_seconds']:.0f} s", flush=True)
    else:
        if a.frame_spp:
            frame, meta = render_relief(case, ssp_t, sa_t, a.frame_spp, 0, noise=True)
        else:
            src, meta = gc.build_case(case)
            frame = gc.with_normals_file(src, ROOT_OUT / f"case-{src.name}")
        print(f"# frame: {frame}", flush=True)
    out["frame_noise"] = frame_noise(frame)
    observed, _, est_s = read_folder(frame)
    print(f"# frame read in {est_s:.0f} s: alpha' {observed.alpha_prime.tolist()} l' {observed.l_prime_mm.tolist()}",
          flush=True)
    log: list[dict[str, Any]] = []
    seeds = tuple(int(x) for x in a.ref_seeds.split(",") if x.strip())
    if a.mode == "bias" and a.truth_seeds:
        reads = [observed]
        for sd in (int(x) for x in a.truth_seeds.split(",") if x.strip()):
            f2, m2 = render_relief(case, ssp_t, sa_t, a.spp, sd, noise=False)
            r2, _, _ = read_folder(f2)
            reads.append(r2)
            print(f"  truth seed {sd}: read alpha' {np.round(r2.alpha_prime, 5).tolist()} l' "
                  f"{np.round(r2.l_prime_mm, 4).tolist()} ({m2['render_seconds']:.0f} s)", flush=True)
        lr = np.log(np.stack([r.l_prime_mm for r in reads]) / l_t)
        om = np.log(np.stack([1 - r.alpha_prime for r in reads]) / (1 - a_t))
        out["truth_reads"] = {"seeds": [a.seed] + [int(x) for x in a.truth_seeds.split(",")],
                              "log_l_prime_over_truth": lr.tolist(), "log_one_minus_alpha_over_truth": om.tolist()}
        k = len(reads)
        print(f"# pipeline bias at the truth over {k} seeds (mean +- sd of the mean): l' "
              + " / ".join(f"{np.expm1(m):+.1%} +- {s / np.sqrt(k):.1%}" for m, s in zip(lr.mean(0), lr.std(0, ddof=1)))
              + "; 1 - alpha' " + " / ".join(f"{np.expm1(m):+.1%} +- {s / np.sqrt(k):.1%}"
                                              for m, s in zip(om.mean(0), om.std(0, ddof=1)))
              + f"; sd of one read's log l' {np.round(lr.std(0, ddof=1), 3).tolist()}", flush=True)
    res = correct_relief_with_reference(observed, reference_reader(case, a.spp, seeds, log=log),
                                        max_renders=a.renders)
    rs = rows(a.material, observed, res)
    print(f"# {a.material} P {a.period:g} mm: before -> after the reference loop ({len(res.steps)} renders)")
    print_rows(rs)
    if out["frame_noise"]:
        print(f"# frame's Monte Carlo sd / camera sd (median): {np.round(out['frame_noise']['mc_over_camera_sd'], 2)}")
    out.update(rows=rs, correction=res.as_dict(), references=log, seconds=time.perf_counter() - t0)
    if a.json:
        a.json.write_text(json.dumps(out, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
