"""Issue 8: the gradient (diffusion) estimators on Monte Carlo frames of a sphere, across the measured materials.

Scene (the setup of ``tests/simulators/test_mc_frames_gradients.py``): a sphere of ``--radius-mm`` (default
10 mm) of each material of science.md sec. 2 (Jensen et al. 2001 Table 2: reduced sigma_s', sigma_a per RGB in
1/mm, eta 1.3; ``rig.config.MATERIALS`` plus spectralon, sigma_a = 0), seen by a pinhole camera 400 mm away that
the sphere fills (``--size`` px square, default 32), lit by the default rig (362 LEDs at 1 m, ideal full / x / y /
z drive, cross-polarized, 14-bit sensor without noise: expected values). The subsurface light of every pattern is
rendered by Monte Carlo (``render_gradient_capture(render_mode="mc")``, ``--spp`` paths per pixel, ``--seed``):
the only noise is the Monte Carlo error. Maps: ``compute_maps`` in LED mode (response LUT of the distant LEDs,
albedo scale from the rig's radiometry), region: the sphere's pixels eroded by 2 px, true normals known.

Models (per material and RGB channel):

- ``dipole-jensen``: :func:`estimation.diffusion.estimate_sphere`, ``method="sphere"`` (the exact inversion of
  the pooled (median albedo, median shortening) with the truncated half-space Jensen dipole on the sphere);
- ``dipole-better``, ``mc-table``: ``estimate_sphere(method="small_blur", model=...)`` (alpha' from the model's
  half-space R_d, l' from the first-order shortening; the exact sphere integrals exist for the Jensen dipole
  only, so these two use the small-blur approximation);
- ``dipole-jensen+reference``: :func:`estimation.gradient_correction.estimate_sphere_with_reference` with a
  :class:`rig.estimate.reference.mc_reference.GradientsMonteCarloReference` of the same capture (same camera, LEDs, patterns, spp,
  maps and region; reference seed = ``--seed`` + 100 for every render: common random numbers, independent of the
  frame's realisation), at most ``--reference-iterations`` renders, ``rel_tol`` 0.02.

Printed per material and channel: truth D = 1 / (3 (sigma_s' + sigma_a)) and, per model, D, sigma_s', sigma_a,
their relative errors (sigma_a's is n/a where the truth is 0: spectralon), status (``ok``; ``censored``: a model
bound was hit — sigma_a clipped at 0, the interval one-sided; ``failed``: the estimator raised or returned no
finite value, with the reason) and the estimation seconds. Seconds of the observation render, of the maps, of
each estimate and of the reference renders are listed separately; the renderer's paths per second (paths =
object pixels x spp x 3 channels per pattern render, over the renderer's own seconds), collisions per path and
truncated fraction are printed per material. Nothing here is a verdict: the summary counts channels within
10 % in D per model, as measured in this run.

Issue 16's acceptance printer (relief slabs, 5 mm spheres with --reference, 25 mm spheres through the capture-folder
user path, with the rule lines) is ``benchmarks/gradients_acceptance.py``; ``python benchmarks/mc_gradients.py
--acceptance [its options]`` runs it.

Run: ``python benchmarks/mc_gradients.py [--quick] [--json out.json] [--materials marble,skin1]`` (full: 12
materials, 32 x 32 px at 128 spp, 4 reference iterations: 336 s measured on 2 shared cores, ~40 % of it spectralon
(380 collisions per path); ``--quick``: marble and skin1, 16 x 16 px at 16 spp,
2 reference iterations, ~5 s plus numba's cache load).
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estimation.camera import PinholeCamera  # noqa: E402
from estimation.diffusion import estimate_sphere  # noqa: E402
from estimation.gradient_correction import estimate_sphere_with_reference  # noqa: E402
from estimation.gradients import LedRig, albedo_scale_from_radiometry, build_response_lut, compute_maps  # noqa: E402
from rig.config import MATERIALS as RIG_MATERIALS  # noqa: E402
from rig.acquire.geometry import led_layout  # noqa: E402
from rig.estimate.reference.mc_reference import GradientsMonteCarloReference  # noqa: E402
from simulators.camera import SensorModel  # noqa: E402
from simulators.mc_capture import MCSettings  # noqa: E402
from simulators.scene import SphereObject, render_gradient_capture  # noqa: E402
from rig.files.provenance import write_json  # noqa: E402

ETA = 1.3
# science.md sec. 2 (pbrt's units: reduced sigma_s', sigma_a in 1/mm); rig.config holds all but spectralon
MATERIALS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = dict(
    RIG_MATERIALS, spectralon=((11.6, 20.4, 14.9), (0.0, 0.0, 0.0)))
SENSOR = SensorModel(gain_dn_per_unit=4.5e7, black_level_dn=512, white_level_dn=16383, read_noise_dn=2.0,
                     electrons_per_dn=1.5)
EXPOSURE_S = 0.02
CAMERA_DISTANCE_MM = 400.0
REF_SEED_OFFSET = 100
REL_TOL = 0.02
QUICK_MATERIALS = ("marble", "skin1")
CHANNELS = "RGB"
# model label -> estimate_sphere keywords (None: the reference-corrected estimate)
MODELS: dict[str, dict[str, str] | None] = {
    "dipole-jensen": {"method": "sphere", "model": "dipole-jensen"},
    "dipole-better": {"method": "small_blur", "model": "dipole-better"},
    "mc-table": {"method": "small_blur", "model": "mc-table"},
    "dipole-jensen+reference": None,
}
WITHIN = 0.10   # the summary counts |D / D_true - 1| <= this


# --------------------------------------------------------------------------------------------------------------
def camera(size_px: int, radius_mm: float) -> PinholeCamera:
    """Pinhole camera on -y looking at the origin; the sphere's image just fills the frame."""
    return PinholeCamera.looking_at(width_px=size_px, height_px=size_px,
                                    fx_px=size_px * CAMERA_DISTANCE_MM / (2.0 * radius_mm),
                                    position_mm=(0.0, -CAMERA_DISTANCE_MM, 0.0), target_mm=(0.0, 0.0, 0.0))


def make_rig() -> dict[str, Any]:
    pos, _ = led_layout(6, 1000.0, -60.0)
    inten = np.full((len(pos), 3), 1000.0)
    leds = LedRig.from_positions(pos, inten)
    patterns = {name: leds.pattern_values(name)[:, 0] for name in ("full", "x", "y", "z")}  # ideal drive values
    # the Monte Carlo frames see the LEDs as distant (no near field): the LUT of a surface at the origin
    lut = build_response_lut(leds, eta=ETA, size=33)
    return {"pos": pos, "inten": inten, "patterns": patterns, "leds": leds, "lut": lut}


def maps_of(cap: Any, rig: dict[str, Any]) -> Any:
    scale = albedo_scale_from_radiometry([cap.value_per_radiance] * 3, rig["leds"], eta=ETA)
    return compute_maps(cap.frames, albedo_scale=scale, lut=rig["lut"], eta=ETA,
                        view_dirs=np.nan_to_num(cap.view_dirs), geometry_normals=np.nan_to_num(cap.normals),
                        object_mask=cap.hit)


@contextmanager
def record_mc_renders(log: list[dict[str, Any]]) -> Iterator[None]:
    """Record every Monte Carlo image the capture simulator renders (its own seconds, paths, collisions)."""
    import simulators.mc_capture as mcc

    orig = mcc.render_mc

    def wrapped(obj: Any, cam: Any, lights: Any, settings: Any = None) -> Any:
        img = orig(obj, cam, lights, settings)
        log.append({"seconds": float(img.seconds), "paths": int(img.mask.sum()) * int(img.spp) * img.radiance.shape[-1],
                    "mean_collisions": float(img.mean_collisions), "truncated_fraction": float(img.truncated_fraction)})
        return img

    mcc.render_mc = wrapped
    try:
        yield
    finally:
        mcc.render_mc = orig


def render_stats(log: list[dict[str, Any]]) -> dict[str, float]:
    if not log:
        return {"seconds": 0.0, "paths": 0, "paths_per_s": float("nan"), "mean_collisions": float("nan"),
                "truncated_fraction": float("nan")}
    sec = sum(r["seconds"] for r in log)
    paths = sum(r["paths"] for r in log)
    w = np.array([r["paths"] for r in log], float)
    return {"seconds": sec, "paths": paths, "paths_per_s": paths / max(sec, 1e-9),
            "mean_collisions": float(np.average([r["mean_collisions"] for r in log], weights=w)),
            "truncated_fraction": float(np.average([r["truncated_fraction"] for r in log], weights=w))}


def capture(name: str, rig: dict[str, Any], cam: PinholeCamera, radius_mm: float, spp: int, seed: int) -> Any:
    ssp, sa = MATERIALS[name]
    obj = SphereObject((0.0, 0.0, 0.0), radius_mm, tuple(ssp), tuple(sa), ETA, tessellation=3)
    return render_gradient_capture(obj, cam, rig["pos"], rig["inten"], rig["patterns"], polarizations=("cross",),
                                   exposure_s=EXPOSURE_S, sensor=SENSOR, noise=False, render_mode="mc",
                                   mc=MCSettings(spp=spp, seed=seed))


# --------------------------------------------------------------------------------------------------------------
def _rel(est: float, true: float) -> float:
    return est / true - 1.0 if true > 0 and np.isfinite(est) else float("nan")


def channel_rows(model: str, name: str, D: Any, ssp: Any, sa: Any, status: list[str], seconds: float,
                 extra: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    t_ssp, t_sa = (np.asarray(x, float) for x in MATERIALS[name])
    t_D = 1.0 / (3.0 * (t_ssp + t_sa))
    rows = []
    for c in range(3):
        d, s, a = float(D[c]), float(ssp[c]), float(sa[c])
        st = status[c]
        if st in ("ok", "censored") and not (np.isfinite(d) and np.isfinite(s) and np.isfinite(a)):
            st = f"failed: non-finite result (D {d:.4g}, sigma_s' {s:.4g}, sigma_a {a:.4g}; estimator said {st})"
        rows.append({"material": name, "channel": CHANNELS[c], "model": model, "D_true_mm": float(t_D[c]),
                     "sigma_s_prime_true_per_mm": float(t_ssp[c]), "sigma_a_true_per_mm": float(t_sa[c]),
                     "D_mm": d, "err_D": _rel(d, t_D[c]), "sigma_s_prime_per_mm": s,
                     "err_sigma_s_prime": _rel(s, t_ssp[c]), "sigma_a_per_mm": a, "err_sigma_a": _rel(a, t_sa[c]),
                     "status": st, "seconds": seconds, **(extra or {})})
    return rows


def failed_rows(model: str, name: str, reason: str, seconds: float) -> list[dict[str, Any]]:
    nan = np.full(3, np.nan)
    return channel_rows(model, name, nan, nan, nan, [f"failed: {reason}"] * 3, seconds)


def estimate_uncorrected(model: str, maps: Any, cap: Any, radius_mm: float, name: str) -> list[dict[str, Any]]:
    kw = MODELS[model]
    assert kw is not None
    t0 = time.perf_counter()
    try:
        est = estimate_sphere(maps, radius_mm=radius_mm, true_normals=cap.normals, erode_px=2, **kw)
    except Exception as exc:  # a failure is a row that says why
        return failed_rows(model, name, f"{type(exc).__name__}: {exc}", time.perf_counter() - t0)
    sec = time.perf_counter() - t0
    s = est.summary
    status = ["failed: no usable pixels (unknown)" if x == "unknown" else x for x in s.status]
    return channel_rows(model, name, s.value("D_mm"), s.value("sigma_s_prime_per_mm"), s.value("sigma_a_per_mm"),
                        status, sec, {"method": kw["method"], "n_pixels": s.n_pixels.tolist()})


def estimate_corrected(observed: Any, ref: GradientsMonteCarloReference, radius_mm: float, name: str, seed: int,
                       iterations: int) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    model = "dipole-jensen+reference"
    n0 = len(ref.renders)
    t0 = time.perf_counter()
    try:
        res = estimate_sphere_with_reference(observed, ref, radius_mm, ETA, seed=seed + REF_SEED_OFFSET,
                                             max_iterations=iterations, rel_tol=REL_TOL)
    except Exception as exc:
        sec = time.perf_counter() - t0
        rs = sum(r["render_seconds"] + r["maps_seconds"] for r in ref.renders[n0:])
        rows = failed_rows(model, name, f"{type(exc).__name__}: {exc}", sec)
        for r in rows:
            r.update(reference_seconds=rs, estimation_seconds=sec - rs, renders=len(ref.renders) - n0)
        return rows, {"message": f"{type(exc).__name__}: {exc}"}
    sec = time.perf_counter() - t0
    rs = sum(r["render_seconds"] + r["maps_seconds"] for r in ref.renders[n0:])
    status = []
    for c in range(3):
        if not np.isfinite(res.D_mm[c]):
            A, S = float(observed.albedo[c]), float(observed.shortening[c])
            why = ("no usable pixels" if not np.isfinite(A) else
                   f"no measurable blur (observed median shortening {S:.4f} >= 1)" if S >= 1 else
                   f"the sphere inversion of the observation (albedo {A:.4g}, shortening {S:.4f}) is not finite")
            status.append(f"failed: {why}")
            continue
        st = "censored" if bool(res.censored[c]) else "ok"
        if not np.isfinite(res.kappa_albedo[c]):
            st += " (uncorrected: the reference render of this channel had no measurable blur or light)"
        status.append(st)
    info = {"message": res.message, "converged": res.converged, "iterations": res.iterations,
            "kappa_albedo": res.kappa_albedo.tolist(), "kappa_blur": res.kappa_blur.tolist(),
            "D_interval_mm": res.intervals["D_mm"].tolist(), "steps": [st.as_dict() for st in res.steps]}
    rows = channel_rows(model, name, res.D_mm, res.sigma_s_prime_per_mm, res.sigma_a_per_mm, status, sec,
                        {"method": "sphere+reference", "reference_seconds": rs, "estimation_seconds": sec - rs,
                         "renders": res.iterations, "converged": res.converged})
    for c, r in enumerate(rows):
        lo, hi = res.intervals["D_mm"][c]
        r["D_interval_mm"] = [float(lo), float(hi)]
        r["D_interval_covers"] = bool(lo <= r["D_true_mm"] <= hi)
    return rows, info


# --------------------------------------------------------------------------------------------------------------
def fmt_err(x: float) -> str:
    return "n/a" if not np.isfinite(x) else f"{x:+.1%}"


def fmt(x: float) -> str:
    return "nan" if not np.isfinite(x) else f"{x:.4g}"


def print_material(name: str, rows: list[dict[str, Any]], info: dict[str, Any]) -> None:
    ssp, sa = MATERIALS[name]
    m = info["render"]
    print(f"\n### {name} (sigma_s' {ssp}, sigma_a {sa} /mm)\n")
    print(f"observation render {info['capture_seconds']:.2f} s wall ({m['seconds']:.2f} s in the renderer, "
          f"{m['paths']} paths, {m['paths_per_s']:.3g} paths/s, {m['mean_collisions']:.0f} collisions/path, "
          f"truncated {m['truncated_fraction']:.2g}); frames: max {info['frame_max']:.3f} of full scale, "
          f"saturated pixels {info['saturated_px']}; maps {info['maps_seconds']:.3f} s; region pixels per channel "
          f"{info['n_pixels']}")
    rr = info.get("reference_render")
    if rr:
        print(f"reference: {info['reference'].get('message', '')}; renders {rr['seconds']:.2f} s in the renderer "
              f"({rr['paths_per_s']:.3g} paths/s); kappa_albedo "
              f"{np.round(info['reference'].get('kappa_albedo', []), 3).tolist()}, kappa_blur "
              f"{np.round(info['reference'].get('kappa_blur', []), 2).tolist()}")
    print()
    print("| model | ch | D_true mm | D mm | err D | sigma_s' /mm | err | sigma_a /mm | err | status | est s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        sec = r["seconds"]
        if "reference_seconds" in r:
            sec_s = f"{r['estimation_seconds']:.2f} + renders {r['reference_seconds']:.1f}"
        else:
            sec_s = f"{sec:.2f}"
        print(f"| {r['model']} | {r['channel']} | {r['D_true_mm']:.4g} | {fmt(r['D_mm'])} | {fmt_err(r['err_D'])} | "
              f"{fmt(r['sigma_s_prime_per_mm'])} | {fmt_err(r['err_sigma_s_prime'])} | {fmt(r['sigma_a_per_mm'])} | "
              f"{fmt_err(r['err_sigma_a']) if r['sigma_a_true_per_mm'] > 0 else 'n/a (truth 0)'} | {r['status']} | "
              f"{sec_s} |")


def print_summary(rows: list[dict[str, Any]], infos: dict[str, dict[str, Any]]) -> None:
    models = list(MODELS)
    print("\n## D / D_true - 1 per material and channel (c = censored, F = failed, u = the reference could not correct this channel)\n")
    print("| material | ch | D_true mm | " + " | ".join(models) + " |")
    print("|---|---|---|" + "---|" * len(models))
    by = {(r["material"], r["channel"], r["model"]): r for r in rows}
    for name in infos:
        for ch in CHANNELS:
            cells = []
            for m in models:
                r = by[(name, ch, m)]
                st = r["status"]
                tag = (" F" if st.startswith("failed") else (" c" if st.startswith("censored") else "")
                       + (" u" if "uncorrected" in st else ""))
                cells.append(fmt_err(r["err_D"]) + tag)
            print(f"| {name} | {ch} | {by[(name, ch, models[0])]['D_true_mm']:.4g} | " + " | ".join(cells) + " |")
    print("\n## Seconds per material (render: the observation capture, wall; paths/s: the renderer's own seconds)\n")
    print("| material | render s | paths/s | collisions/path | maps s | " + " | ".join(f"{m} s" for m in models[:-1])
          + " | reference renders | reference s (renders + estimation) |")
    print("|---|---|---|---|---|" + "---|" * (len(models) - 1) + "---|---|")
    for name, info in infos.items():
        secs = [by[(name, "R", m)]["seconds"] for m in models[:-1]]
        rc = by[(name, "R", models[-1])]
        print(f"| {name} | {info['capture_seconds']:.2f} | {info['render']['paths_per_s']:.3g} | "
              f"{info['render']['mean_collisions']:.0f} | {info['maps_seconds']:.2f} | "
              + " | ".join(f"{s:.2f}" for s in secs)
              + f" | {rc.get('renders', 0)} | {rc.get('reference_seconds', float('nan')):.1f} + "
                f"{rc.get('estimation_seconds', float('nan')):.2f} |")
    print(f"\n## Channels within {WITHIN:.0%} in D (of {3 * len(infos)}; counted in this run)\n")
    print("| model | within | censored | failed | median abs err D |")
    print("|---|---|---|---|---|")
    for m in models:
        rs = [r for r in rows if r["model"] == m]
        e = np.array([abs(r["err_D"]) for r in rs])
        fin = np.isfinite(e)
        print(f"| {m} | {int(np.sum(e[fin] <= WITHIN))} | {sum(r['status'].startswith('censored') for r in rs)} | "
              f"{sum(r['status'].startswith('failed') for r in rs)} | "
              f"{(np.median(e[fin]) if fin.any() else float('nan')):.1%} |")


def main(argv: list[str] | None = None) -> int:
    args_in = list(sys.argv[1:] if argv is None else argv)
    if "--acceptance" in args_in:   # issue 16's acceptance printer, with the remaining options
        args_in.remove("--acceptance")
        from benchmarks.gradients_acceptance import main as acceptance_main
        return acceptance_main(args_in)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="marble and skin1, 16 x 16 px, 16 spp, 2 reference "
                    "iterations")
    ap.add_argument("--json", type=Path, metavar="OUT", help="write every row and the per-material details as JSON")
    ap.add_argument("--materials", help=f"comma-separated subset of: {', '.join(MATERIALS)} (default: all; "
                    f"--quick: {', '.join(QUICK_MATERIALS)})")
    ap.add_argument("--size", type=int, help="image width = height in px (default 32, --quick 16)")
    ap.add_argument("--spp", type=int, help="paths per pixel of the frames and the reference renders (default 128, "
                    "--quick 16)")
    ap.add_argument("--seed", type=int, default=0, help="the frames' seed (the reference renders use seed + 100)")
    ap.add_argument("--radius-mm", type=float, default=10.0)
    ap.add_argument("--reference-iterations", type=int, help="at most this many reference renders per material "
                    "(default 4, --quick 2)")
    args = ap.parse_args(argv)
    if args.materials:
        names = [s.strip() for s in args.materials.split(",") if s.strip()]
    else:
        names = list(QUICK_MATERIALS if args.quick else MATERIALS)
    unknown = [n for n in names if n not in MATERIALS]
    if unknown:
        ap.error(f"unknown material(s) {unknown}; valid: {', '.join(MATERIALS)}")
    size = args.size or (16 if args.quick else 32)
    spp = args.spp or (16 if args.quick else 128)
    ref_it = args.reference_iterations or (2 if args.quick else 4)
    radius = float(args.radius_mm)
    t_all = time.perf_counter()
    import numba

    print(f"# Gradient estimators on Monte Carlo frames of a {radius:g} mm sphere ({'quick' if args.quick else 'full'})"
          f": {size}x{size} px, {spp} spp, seed {args.seed} (reference seed {args.seed + REF_SEED_OFFSET}), "
          f"<= {ref_it} reference renders; eta {ETA}; machine {platform.machine()} {platform.system()}, "
          f"{os.cpu_count()} CPUs, numba threads {numba.get_num_threads()}, OpenBLAS threads "
          f"{os.environ.get('OPENBLAS_NUM_THREADS')}, load {os.getloadavg()[0]:.2f}")

    t0 = time.perf_counter()
    rig = make_rig()
    lut_s = time.perf_counter() - t0
    cam = camera(size, radius)
    # warm-up: numba compile / cache load and the models' tables, on a tiny capture (not in the figures)
    t0 = time.perf_counter()
    small = camera(8, radius)
    wcap = capture("marble", rig, small, radius, 2, 0)
    wmaps = maps_of(wcap, rig)
    for kw in MODELS.values():
        if kw is not None:
            estimate_sphere(wmaps, radius_mm=radius, true_normals=wcap.normals, erode_px=1, **kw)
    warm_s = time.perf_counter() - t0
    print(f"LUT {lut_s:.1f} s; warm-up (numba compile or cache load, model tables) {warm_s:.1f} s\n")
    print("Models: dipole-jensen = estimate_sphere(method='sphere'); dipole-better, mc-table = "
          "estimate_sphere(method='small_blur', model=...); dipole-jensen+reference = "
          "estimate_sphere_with_reference (dipole-jensen corrected by Monte Carlo renders of the known sphere).")

    rows: list[dict[str, Any]] = []
    infos: dict[str, dict[str, Any]] = {}
    for name in names:
        info: dict[str, Any] = {}
        log: list[dict[str, Any]] = []
        t0 = time.perf_counter()
        with record_mc_renders(log):
            cap = capture(name, rig, cam, radius, spp, args.seed)
        info["capture_seconds"] = time.perf_counter() - t0
        info["render"] = render_stats(log)
        fr = np.stack([np.asarray(f) for f in cap.frames.values()])
        info["frame_max"] = float(np.nanmax(fr))
        info["saturated_px"] = int(np.sum(np.any(fr >= 1.0, axis=(0, -1)) & cap.hit))
        t0 = time.perf_counter()
        maps = maps_of(cap, rig)
        info["maps_seconds"] = time.perf_counter() - t0
        mrows: list[dict[str, Any]] = []
        for m in MODELS:
            if MODELS[m] is not None:
                mrows += estimate_uncorrected(m, maps, cap, radius, name)
        info["n_pixels"] = mrows[0].get("n_pixels")
        ref = GradientsMonteCarloReference(cam, rig["pos"], rig["inten"], rig["patterns"],
                                           lambda c: maps_of(c, rig), radius, spp=spp, exposure_s=EXPOSURE_S,
                                           sensor=SENSOR, erode_px=2)
        rlog: list[dict[str, Any]] = []
        try:
            observed = ref.observables(cap)
        except Exception as exc:
            crow = failed_rows("dipole-jensen+reference", name, f"observables: {type(exc).__name__}: {exc}", 0.0)
            info["reference"] = {"message": str(exc)}
        else:
            with record_mc_renders(rlog):
                crow, info["reference"] = estimate_corrected(observed, ref, radius, name, args.seed, ref_it)
        info["reference_render"] = render_stats(rlog) if rlog else None
        info["reference_renders"] = list(ref.renders)
        mrows += crow
        rows += mrows
        infos[name] = info
        print_material(name, mrows, info)
        sys.stdout.flush()

    print_summary(rows, infos)
    total = time.perf_counter() - t_all
    print(f"\ntotal {total:.1f} s (load {os.getloadavg()[0]:.2f})")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        out = {"size_px": size, "spp": spp, "seed": args.seed, "reference_seed": args.seed + REF_SEED_OFFSET,
               "reference_iterations": ref_it, "radius_mm": radius, "eta": ETA, "threads": numba.get_num_threads(),
               "cpu_count": os.cpu_count(), "warmup_seconds": warm_s, "lut_seconds": lut_s, "seconds_total": total,
               "materials": {k: {"sigma_s_prime_per_mm": MATERIALS[k][0], "sigma_a_per_mm": MATERIALS[k][1], **v}
                             for k, v in infos.items()},
               "rows": rows}
        write_json(args.json, out, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
