"""Benchmark of the single-image method (Mukaigawa, Suzuki, Yagi 2009) as published and improved.

Synthesize-and-recover on a 10 mm sphere (no inverse crime in sections 1-2: the image comes from
estimation.forward on a finer, rotated tessellation than the estimator's icosphere mesh):

1. The paper's experiment (Table 1): marble-R (sigma_s' 2.19, sigma_a 0.002 /mm, eta 1.3) under an environment
   map, quantization step 0.05-0.50 mm, for ``pinv`` (published), ``tikhonov`` and ``direct`` (the default; it
   has no bins, so one row). Per row: parameters, their relative errors, the sigma_a interval, the PSNR of the
   image re-rendered from the fitted parameters with the same forward model (over the visible patches, peak =
   max observed) and seconds. The paper used a Debevec light probe; none is bundled, so a procedural lat-long
   sky (gradient + sun) stands in. Verdict on the target: sigma_s' within 2 %, sigma_a within 25 % (or flagged
   non-identifiable with an interval containing the truth).
2. One LED (point light ~1 m away) on Jensen 2001 materials, all three channels, ``direct``.
2b. Models side by side on table-made data: the image of one LED on marble (RGB) synthesized with the Monte Carlo
   table's forward model (``synthesize_table``: exact ring integrals of its C(r), exit factor F_t/(pi c)) on the
   fine tessellation, fitted ("direct") with each profile model: parameters, errors against the truth, the
   model_bias radiance ratio against the table at the fitted parameters, seconds.
3. Cost against the patch count m (1k-100k patches of a Fibonacci sphere, same scene and E_t given to every
   solver): ``estimate_single_image`` ("direct", default options with intervals, and again without the
   profile-likelihood scan; "pinv" at 0.35 mm, which sums every pair up to EXACT_PAIR_BUDGET_BINNED) beside
   the literal dense implementation of the published method (benchmarks/_dense_reference.py: dense m_obs x m
   distance matrix, dense W, numpy.linalg.pinv, Eq. 29 fit), run only while its distance matrix fits
   ``--dense-max-gb`` (else "skipped: needs N GB" and a time extrapolated as O(m_obs m) from the largest run).
   Observations: estimation.forward on the same patches for m <= 10k, else ``predict_radiance`` with a finer
   clustering (opening 0.2) than the estimator's (0.35). At m = 10k (the largest dense m with --quick) the
   parameters are compared within each method family: our pinv (default far field, and clustered) against the
   literal dense pinv on the same bins, and our direct fit (clustered) against the same fit with
   every pair summed (far_field="exact", the dense evaluation of the direct method).
4. A PNG (``--png``; needs the optional ``plots`` extra, matplotlib): relative error against seconds for the
   rows of section 1, and seconds against m for section 3.

Timings are wall-clock minima over ``--repeats`` runs; the load average and BLAS thread settings are printed
(on a shared machine, absolute times are inflated; ratios within one run remain meaningful).

Run: ``python benchmarks/single_image.py [--quick] [--json out.json] [--png out.png]`` (a few minutes;
--quick < 30 s).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _dense_reference import distance_matrix_bytes, literal_dense_pinv  # noqa: E402
from estimation.camera import PinholeCamera  # noqa: E402
from estimation.forward import (NEAR_FIELD_SPACINGS, diffuse_exitance, radiance_from_exitance,  # noqa: E402
                                ring_radii)
from estimation.mc_table import default_table, exit_radiance_factor  # noqa: E402
from estimation.single_image import (MODELS_ALL, EnvironmentMap, Patches, PointLights,  # noqa: E402
                                     estimate_single_image,
                                     patch_irradiance, patches_from_mesh, predict_radiance)
from rig.files.provenance import write_json  # noqa: E402

CAMERA_MM = (0.0, -300.0, 0.0)
LED_MM = np.array([[300.0, -900.0, 400.0]])
TRUTH = (2.19, 0.002)  # the seed's Table 1: marble-R, eta 1.3
ETA = 1.3
TARGET_SSP, TARGET_SA = 0.02, 0.25
TARGET_SECONDS_50K, TARGET_RATIO_10K, TARGET_AGREE = 10.0, 20.0, 0.01
MATERIALS = {  # Jensen 2001 Table 2 (pbrt units), eta 1.3
    "apple": ([2.29, 2.39, 1.97], [0.0030, 0.0034, 0.046]),
    "marble": ([2.19, 2.62, 3.00], [0.0021, 0.0041, 0.0071]),
    "skin1": ([0.74, 0.88, 1.01], [0.032, 0.17, 0.48]),
    "potato": ([0.68, 0.70, 0.55], [0.0024, 0.0090, 0.12]),
    "ketchup": ([0.18, 0.07, 0.03], [0.061, 0.97, 1.45]),
    "cream": ([7.38, 5.47, 3.15], [0.0002, 0.0028, 0.0163]),
}
DEFAULT_PNG = Path(__file__).resolve().parent / "out" / "single_image_error_vs_time.png"


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


def fibonacci_sphere(m: int, radius: float = 10.0) -> Patches:
    """m equal-area patches on a sphere (Fibonacci lattice; any m, unlike icospheres)."""
    i = np.arange(m) + 0.5
    z = 1.0 - 2.0 * i / m
    phi = np.pi * (1.0 + 5.0**0.5) * i
    r = np.sqrt(1.0 - z * z)
    n = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    return Patches.from_arrays(n * radius, n, np.full(m, 4.0 * np.pi * radius**2 / m), CAMERA_MM)


def synthesize(est: Patches, fine: Patches, lights, ssp, sa, eta: float) -> np.ndarray:
    e = patch_irradiance(fine, lights, eta)
    vis = est.visible_index
    b = diffuse_exitance(est.centers_mm[vis], fine.centers_mm, fine.areas_mm2, e, ssp, sa, eta)
    return radiance_from_exitance(b, est.cos_out[vis], eta)


def psnr_db(observed: np.ndarray, rendered: np.ndarray) -> float:
    """PSNR over the visible patches, peak = max observed."""
    mse = float(np.mean((rendered - observed) ** 2))
    return float(10 * np.log10(float(np.max(observed)) ** 2 / mse)) if mse > 0 else float("inf")


def rel_err(value, truth) -> np.ndarray:
    return np.asarray(value, dtype=float) / np.asarray(truth, dtype=float) - 1.0


def row(label: str, truth_s, truth_a, r) -> dict:
    out: dict[str, Any] = {"case": label, "ok": bool(r), "message": r.message}
    if r:
        out.update(
            sigma_s_prime=r.sigma_s_prime_per_mm.tolist(), sigma_a=r.sigma_a_per_mm.tolist(),
            err_sigma_s_prime=rel_err(r.sigma_s_prime_per_mm, truth_s).tolist(),
            err_sigma_a=rel_err(r.sigma_a_per_mm, truth_a).tolist(),
            sigma_a_ci=r.sigma_a_ci_per_mm.tolist(), identifiable=list(r.sigma_a_identifiable_per_channel),
            covered=[bool(lo <= t <= hi) for (lo, hi), t in zip(r.sigma_a_ci_per_mm, np.atleast_1d(truth_a))],
            empty_bins=r.diagnostics.empty_bins, condition=r.diagnostics.condition_number,
            seconds=r.diagnostics.seconds, far_field=r.extra.get("far_field"))
    return out


def fmt(v) -> str:
    return "/".join(f"{x:.4g}" for x in np.atleast_1d(v))


def pct(v) -> str:
    return "/".join(f"{100 * x:+.2f}%" for x in np.atleast_1d(v))


def verdict(ok: bool) -> str:
    return "PASS" if ok else "FAIL"


def timed(fn, repeats: int):
    """(result of the fastest call, minimum wall-clock seconds over ``repeats`` calls)."""
    best, out = np.inf, None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        res = fn()
        sec = time.perf_counter() - t0
        if sec < best:
            best, out = sec, res
    return out, best


def table1_target(r) -> tuple[bool, str]:
    """sigma_s' within 2 % and sigma_a within 25 %, or sigma_a flagged non-identifiable with an interval
    containing the truth."""
    if not r:
        return False, f"failed: {r.message}"
    e_s = float(rel_err(r.sigma_s_prime_per_mm[0], TRUTH[0]))
    e_a = float(rel_err(r.sigma_a_per_mm[0], TRUTH[1]))
    lo, hi = r.sigma_a_ci_per_mm[0]
    ok_s = abs(e_s) <= TARGET_SSP
    if abs(e_a) <= TARGET_SA:
        ok_a, why = True, f"sigma_a {e_a:+.1%} (|.| <= {TARGET_SA:.0%})"
    elif not r.sigma_a_identifiable and lo <= TRUTH[1] <= hi:
        ok_a, why = True, f"sigma_a {e_a:+.1%} but flagged non-identifiable, interval {lo:.3g}-{hi:.3g} holds the truth"
    else:
        ok_a, why = False, f"sigma_a {e_a:+.1%} (|.| > {TARGET_SA:.0%}; identifiable={r.sigma_a_identifiable}, " \
                           f"interval {lo:.3g}-{hi:.3g})"
    return ok_s and ok_a, f"sigma_s' {e_s:+.2%} (|.| <= {TARGET_SSP:.0%}: {verdict(ok_s)}), {why}"


# ---------------------------------------------------------------------------------------------- sections
def section_table1(args, est: Patches, fine: Patches, out: dict) -> None:
    env = EnvironmentMap(sky_map())
    t0 = time.perf_counter()
    obs = synthesize(est, fine, env, [TRUTH[0]], [TRUTH[1]], ETA)
    print(f"## 1. Paper experiment (Table 1: marble-R {TRUTH[0]} / {TRUTH[1]} /mm, eta {ETA}, sky map); "
          f"synthesis {time.perf_counter() - t0:.1f} s\n")
    print("| method | bin mm | sigma_s' | err | sigma_a | err | sigma_a 95% | ident. | empty bins | PSNR dB | s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    steps = [0.1, 0.35] if args.quick else [0.05, 0.10, 0.15, 0.20, 0.25, 0.30, 0.35, 0.40, 0.45, 0.50]
    cases = [("direct", 0.35)] + [(m, b) for m in ("pinv", "tikhonov") for b in steps]
    renders: dict[tuple[float, float], float] = {}
    rows = []
    for method, b in cases:
        r, sec = timed(lambda: estimate_single_image(obs, est, env, ETA, method=method, bin_mm=b), 1)
        rw = row(f"paper/{method}/{b}", [TRUTH[0]], [TRUTH[1]], r)
        rw.update(method=method, bin_mm=b, seconds_wall=sec)
        if r:
            key = (float(r.sigma_s_prime_per_mm[0]), float(r.sigma_a_per_mm[0]))
            if key not in renders:
                renders[key] = psnr_db(obs, synthesize(est, fine, env, [key[0]], [key[1]], ETA))
            rw["psnr_db"] = renders[key]
            ok, why = table1_target(r)
            rw.update(target=ok, target_reason=why)
            print(f"| {method} | {b:.2f} | {fmt(r.sigma_s_prime_per_mm)} | {pct(rw['err_sigma_s_prime'])} | "
                  f"{fmt(r.sigma_a_per_mm)} | {pct(rw['err_sigma_a'])} | {fmt(r.sigma_a_ci_per_mm[0])} | "
                  f"{r.sigma_a_identifiable} | {r.diagnostics.empty_bins} | {rw['psnr_db']:.2f} | {sec:.2f} |")
        else:
            rw.update(target=False, target_reason=f"failed: {r.message}")
            print(f"| {method} | {b:.2f} | failed: {r.message} | | | | | | | | {sec:.2f} |")
        rows.append(rw)
    out["table1"] = rows
    print()
    d = rows[0]
    print(f"TARGET Table-1 scene, default method (direct): {verdict(d['target'])} — {d['target_reason']}")
    for method in ("tikhonov", "pinv"):
        mine = [r for r in rows if r.get("method") == method]
        n_ok = sum(bool(r["target"]) for r in mine)
        print(f"  (for comparison, {method}: {n_ok}/{len(mine)} quantization steps meet the same target)")
    out.setdefault("verdicts", {})["table1_direct"] = {"pass": bool(d["target"]), "detail": d["target_reason"]}
    print()


def section_led(args, est: Patches, fine: Patches, out: dict) -> None:
    led = PointLights(LED_MM, np.full((1, 3), 1e6))
    print("## 2. One LED at ~1 m, direct method, RGB (relative errors)\n")
    print("| material | sigma_s' err | sigma_a err | sigma_a identifiable | sigma_a CI covers truth | s |")
    print("|---|---|---|---|---|---|")
    names = ["marble", "skin1"] if args.quick else list(MATERIALS)
    rows = []
    for name in names:
        s, a = MATERIALS[name]
        obs = synthesize(est, fine, led, np.array(s), np.array(a), ETA)
        r = estimate_single_image(obs, est, led, ETA)
        rw = row(f"led/{name}", s, a, r)
        rows.append(rw)
        if r:
            print(f"| {name} | {pct(rw['err_sigma_s_prime'])} | {pct(rw['err_sigma_a'])} | "
                  f"{fmt(np.array(rw['identifiable'], dtype=int))} | {fmt(np.array(rw['covered'], dtype=int))} | "
                  f"{r.diagnostics.seconds:.2f} |")
        else:
            print(f"| {name} | failed: {r.message} | | | | |")
    out["led"] = rows
    print()


def synthesize_table(est: Patches, fine: Patches, lights, ssp, sa, eta: float, chunk: int = 256) -> np.ndarray:
    """Like :func:`synthesize` with the Monte Carlo table: near field (2 spacings) by exact equal-area ring
    integrals of its C(r), far pairs point terms, radiance with the table's exit factor F_t/(pi c)."""
    from scipy.spatial.distance import cdist

    tab = default_table()
    e = patch_irradiance(fine, lights, eta)
    vis = est.visible_index
    out = np.zeros((vis.size, e.shape[1]))
    for s0 in range(0, vis.size, chunk):
        d = cdist(est.centers_mm[vis[s0:s0 + chunk]], fine.centers_mm)
        near = d < NEAR_FIELD_SPACINGS * fine.spacing_mm
        rows, cols = np.nonzero(near)
        order, r_in, r_out = ring_radii(rows, d[rows, cols], fine.areas_mm2[cols])
        rows, cols = rows[order], cols[order]
        for c in range(e.shape[1]):
            g = tab.cumulative(r_out, ssp[c], sa[c], eta) - tab.cumulative(r_in, ssp[c], sa[c], eta)
            out[s0:s0 + chunk, c] = np.bincount(rows, weights=g * e[cols, c], minlength=d.shape[0])
            prof = np.where(near, 0.0, tab.profile(np.where(near, 1.0, d), ssp[c], sa[c], eta))
            out[s0:s0 + chunk, c] += prof @ (e[:, c] * fine.areas_mm2)
    return exit_radiance_factor(eta, est.cos_out[vis])[:, None] * out


def section_models(args, est: Patches, fine: Patches, out: dict) -> None:
    led = PointLights(LED_MM, np.full((1, 3), 1e6))
    s, a = (np.array(v) for v in MATERIALS["marble"])
    print("## 2b. Models side by side: one LED on marble (RGB), image made with the Monte Carlo table, direct fit\n")
    print("radiance ratio: the model's predicted radiance over the table's at the fitted parameters (model_bias; "
          "exit normalization included)\n")
    print("| model | sigma_s' | err | sigma_a | err | radiance ratio | s |")
    print("|---|---|---|---|---|---|---|")
    obs = synthesize_table(est, fine, led, s, a, ETA)
    rows = []
    for model in MODELS_ALL:
        r, sec = timed(lambda model=model: estimate_single_image(obs, est, led, ETA, model=model), args.repeats)
        rw = row(f"models/{model}", s, a, r)
        rw["model"] = model
        if r:
            rw["model_bias"] = r.extra["model_bias"]
            rw["seconds"] = sec
            print(f"| {model} | {fmt(r.sigma_s_prime_per_mm)} | {pct(rw['err_sigma_s_prime'])} | "
                  f"{fmt(r.sigma_a_per_mm)} | {pct(rw['err_sigma_a'])} | "
                  f"{fmt(r.extra['model_bias']['radiance_ratio'])} | {sec:.2f} |")
        else:
            print(f"| {model} | failed: {r.message} | | | | | {sec:.2f} |")
        rows.append(rw)
    out["models"] = rows
    print()


def section_cost(args, out: dict) -> None:
    sizes = [1000, 3000] if args.quick else [1000, 3000, 10_000, 30_000, 50_000, 100_000]
    if args.sizes:
        sizes = args.sizes
    fits = [m for m in sizes if distance_matrix_bytes(int(0.32 * m), m) <= args.dense_max_gb * 1e9]
    compare_m = 10_000 if 10_000 in fits else max(fits, default=None)
    env = EnvironmentMap(sky_map())
    print(f"## 3. Cost against the patch count m (Fibonacci sphere r = 10 mm, marble-R, sky map; wall-clock "
          f"minimum of {args.repeats} run(s); dense limited to {args.dense_max_gb:g} GB)\n")
    print("m = patches (all are light sources), m_obs = visible ones (observed). direct / pinv: "
          "estimate_single_image(method=..., default options; direct: far field clustered above "
          "EXACT_PAIR_BUDGET pairs, pinv: every pair summed up to EXACT_PAIR_BUDGET_BINNED pairs). 'direct s' "
          "includes the default intervals (Wald + profile-likelihood scan of sigma_a); 'no scan' is the same fit "
          "with profile_likelihood=False (Wald intervals only). The literal dense method computes no intervals "
          "at all. dense: the literal published method (dense distance matrix, pinv).\n")
    print("| m | m_obs | far field | direct s (system + fit) | direct s, no scan | pinv 0.35 s (far field) | "
          "dense pinv s | dense / direct | dense / direct no scan | dense / pinv | direct sigma_s' err | "
          "direct sigma_a err |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    rows = []
    last_dense: tuple[int, int, float] | None = None
    for m in sizes:
        p = fibonacci_sphere(m)
        vis = p.visible_index
        e_t = patch_irradiance(p, env, ETA)  # the same E_t (and c_k) for every solver
        t0 = time.perf_counter()
        if m <= 10_000:
            obs = radiance_from_exitance(diffuse_exitance(p.centers_mm[vis], p.centers_mm, p.areas_mm2, e_t,
                                                          TRUTH[0], TRUTH[1], ETA), p.cos_out[vis], ETA)
            source = "forward"
        else:
            obs = predict_radiance(p, e_t, ETA, TRUTH[0], TRUTH[1], far_field="clustered", far_field_theta=0.2)
            source = "predict_radiance(theta=0.2)"
        t_syn = time.perf_counter() - t0
        rd, s_direct = timed(lambda: estimate_single_image(obs, p, e_t, ETA), args.repeats)
        _, s_noscan = timed(lambda: estimate_single_image(obs, p, e_t, ETA, profile_likelihood=False), args.repeats)
        rp, s_pinv = timed(lambda: estimate_single_image(obs, p, e_t, ETA, method="pinv", bin_mm=0.35), args.repeats)
        need = distance_matrix_bytes(vis.size, m)
        rw: dict[str, Any] = {"m": m, "m_obs": int(vis.size), "observations": source, "synthesis_s": t_syn,
                              "direct_s": s_direct, "direct_noscan_s": s_noscan,
                              "direct_system_s": rd.extra.get("seconds_system"),
                              "direct_fit_s": rd.extra.get("seconds_fit"),
                              "direct_far_field": rd.extra.get("far_field"),
                              "direct_far_terms": rd.extra.get("far_terms"), "pinv_s": s_pinv,
                              "pinv_far_field": rp.extra.get("far_field"), "direct_far_field_theta":
                              rd.extra.get("far_field_theta"),
                              "direct_sigma_s_prime": float(rd.sigma_s_prime_per_mm[0]) if rd else None,
                              "direct_sigma_a": float(rd.sigma_a_per_mm[0]) if rd else None,
                              "pinv_sigma_s_prime": float(rp.sigma_s_prime_per_mm[0]) if rp else None,
                              "pinv_sigma_a": float(rp.sigma_a_per_mm[0]) if rp else None,
                              "dense_bytes": need}
        if need <= args.dense_max_gb * 1e9:
            bins = rp.profile_bins_mm if rp else np.arange(0.0, 21.0, 0.35)
            dres, s_dense = timed(lambda: literal_dense_pinv(obs[:, 0], p.centers_mm, p.areas_mm2, p.cos_out,
                                                             p.visible, e_t[:, 0], ETA, bins), args.repeats)
            rw.update(dense_s=s_dense, dense_sigma_s_prime=dres.sigma_s_prime_per_mm, dense_sigma_a=dres.sigma_a_per_mm,
                      dense_note="measured")
            last_dense = (m, int(vis.size), s_dense)
            dense_txt = f"{s_dense:.3f}"
        else:
            est_s = last_dense[2] * (vis.size * m) / (last_dense[1] * last_dense[0]) if last_dense else np.nan
            rw.update(dense_s=None, dense_extrapolated_s=est_s,
                      dense_note=f"skipped: needs {need / 1e9:.1f} GB (> {args.dense_max_gb:g} GB)")
            dense_txt = f"skipped: needs {need / 1e9:.1f} GB (~{est_s:.0f} s extrapolated)"
        dense_s = rw.get("dense_s") or rw.get("dense_extrapolated_s")
        rw["ratio_dense_direct"] = dense_s / s_direct if dense_s else None
        rw["ratio_dense_pinv"] = dense_s / s_pinv if dense_s else None
        rw["ratio_dense_noscan"] = dense_s / s_noscan if dense_s else None
        ext = "" if rw.get("dense_s") else " (extrap.)"
        e_s = rel_err(rd.sigma_s_prime_per_mm[0], TRUTH[0]) if rd else np.nan
        e_a = rel_err(rd.sigma_a_per_mm[0], TRUTH[1]) if rd else np.nan
        print(f"| {m} | {vis.size} | {rd.extra.get('far_field')} | {s_direct:.3f} "
              f"({rd.extra.get('seconds_system', np.nan):.3f} + "
              f"{rd.extra.get('seconds_fit', np.nan):.3f}) | {s_noscan:.3f} | {s_pinv:.3f} "
              f"({rp.extra.get('far_field')}) | {dense_txt} | "
              f"{rw['ratio_dense_direct'] or np.nan:.1f}{ext} | {rw['ratio_dense_noscan'] or np.nan:.1f}{ext} | "
              f"{rw['ratio_dense_pinv'] or np.nan:.1f}{ext} | "
              f"{pct(e_s)} | {pct(e_a)} |")
        if m == compare_m and rw.get("dense_s"):
            rw["agreement"] = agreement(obs, p, e_t, rd, rp, rw)
        rows.append(rw)
    out["cost"] = rows
    print()
    verdicts = out.setdefault("verdicts", {})
    r50 = next((r for r in rows if r["m"] == 50_000), None)
    if r50:
        ok = r50["direct_s"] < TARGET_SECONDS_50K
        print(f"TARGET m = 50k patches in < {TARGET_SECONDS_50K:g} s: {verdict(ok)} — direct {r50['direct_s']:.2f} s "
              f"(m_obs {r50['m_obs']}; pinv {r50['pinv_s']:.2f} s)")
        verdicts["m50k_seconds"] = {"pass": bool(ok), "seconds": r50["direct_s"]}
    else:
        print("TARGET m = 50k in < 10 s: not run (--quick or --sizes)")
    rc = next((r for r in rows if r["m"] == compare_m and r.get("dense_s")), None)
    if rc:
        ag = rc["agreement"]
        ok_ratio = rc["ratio_dense_direct"] >= TARGET_RATIO_10K
        ok_noscan = rc["ratio_dense_noscan"] >= TARGET_RATIO_10K
        ok_pinv_speed = rc["ratio_dense_pinv"] >= TARGET_RATIO_10K
        print(f"TARGET m = {compare_m} at least {TARGET_RATIO_10K:g}x faster than the literal dense method "
              f"(comparison: our default, direct, against the literal dense pinv; one run): {verdict(ok_ratio)} — "
              f"dense {rc['dense_s']:.3f} s / direct {rc['direct_s']:.3f} s (with its default intervals) = "
              f"{rc['ratio_dense_direct']:.1f}x; without the profile-likelihood scan (the dense method computes no "
              f"intervals): {rc['direct_noscan_s']:.3f} s = {rc['ratio_dense_noscan']:.1f}x "
              f"({verdict(ok_noscan)})")
        print(f"  same method (our pinv, {rc['pinv_far_field']} far field, against the literal dense pinv): "
              f"{rc['pinv_s']:.3f} s = {rc['ratio_dense_pinv']:.1f}x ({verdict(ok_pinv_speed)})")
        ok_d = max(abs(ag["direct_vs_exact"][0]), abs(ag["direct_vs_exact"][1])) <= TARGET_AGREE
        ok_p = max(abs(ag["pinv_vs_dense"][0]), abs(ag["pinv_vs_dense"][1])) <= TARGET_AGREE
        print(f"TARGET parameters (sigma_s', sigma_a) within {TARGET_AGREE:.0%} of the dense computation of the "
              f"same method: pinv (ours, {rc['pinv_far_field']} far field, vs the literal dense pinv, same bins) "
              f"{verdict(ok_p)} — {pct(ag['pinv_vs_dense'])}; direct (our default, far field "
              f"{rc['direct_far_field']}, vs the same fit with every pair summed) {verdict(ok_d)} — "
              f"{pct(ag['direct_vs_exact'])}")
        print(f"  (our pinv with the far field clustered at opening {ag['pinv_clustered_theta']:g} instead: "
              f"{pct(ag['pinv_clustered_vs_dense'])}; cond(W) {ag['pinv_condition']:.3g} amplifies the ~1e-4 "
              f"clustering error; our pinv leaves {ag['pinv_empty_bins']} empty bins out of the Eq. 29 fit. Across "
              f"methods — our direct vs the literal dense pinv: {pct(ag['direct_vs_dense'])}; they fit different "
              f"things: the dense pinv is {pct(ag['dense_vs_truth'])} from the truth, our direct "
              f"{pct(ag['direct_vs_truth'])})")
        ok_all = ok_ratio and ok_p and ok_d
        print(f"VERDICT m = {compare_m}: {'PASS' if ok_all else 'FAIL'} — speed (direct vs dense) "
              f"{verdict(ok_ratio)}, agreement pinv vs dense {verdict(ok_p)}, agreement direct clustered vs exact "
              f"{verdict(ok_d)}")
        verdicts[f"m{compare_m}_ratio"] = {"pass": bool(ok_ratio), "ratio_direct": rc["ratio_dense_direct"],
                                           "ratio_direct_no_scan": rc["ratio_dense_noscan"],
                                           "ratio_pinv": rc["ratio_dense_pinv"]}
        verdicts[f"m{compare_m}_agreement"] = {"direct_pass": bool(ok_d), "pinv_pass": bool(ok_p), **ag}
    print()


def agreement(obs, p: Patches, e_t, rd, rp, rw: dict) -> dict:
    """Relative differences (sigma_s', sigma_a) within each method family at one m."""
    rde = estimate_single_image(obs, p, e_t, ETA, far_field="exact")
    rpe = estimate_single_image(obs, p, e_t, ETA, method="pinv", bin_mm=0.35, far_field="exact")
    rpc = estimate_single_image(obs, p, e_t, ETA, method="pinv", bin_mm=0.35, far_field="clustered")
    dense = np.array([rw["dense_sigma_s_prime"], rw["dense_sigma_a"]])
    truth = np.array(TRUTH)

    def pair(r) -> np.ndarray:
        return np.array([r.sigma_s_prime_per_mm[0], r.sigma_a_per_mm[0]]) if r else np.full(2, np.nan)

    return {"direct_vs_exact": (pair(rd) / pair(rde) - 1).tolist(), "direct_exact_s": rde.diagnostics.seconds,
            "pinv_vs_dense": (pair(rp) / dense - 1).tolist(), "pinv_exact_vs_dense": (pair(rpe) / dense - 1).tolist(),
            "pinv_clustered_vs_dense": (pair(rpc) / dense - 1).tolist(),
            "pinv_clustered_theta": rpc.extra.get("far_field_theta") if rpc else np.nan,
            "direct_vs_dense": (pair(rd) / dense - 1).tolist(), "dense_vs_truth": (dense / truth - 1).tolist(),
            "direct_vs_truth": (pair(rd) / truth - 1).tolist(),
            "pinv_condition": rp.diagnostics.condition_number if rp else np.nan,
            "pinv_empty_bins": int(rp.diagnostics.empty_bins) if rp else 0}


def write_png(path: Path, out: dict) -> None:
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print(f"note: matplotlib is not installed (optional extra 'plots'): {path} not written")
        return
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    styles = {"direct": ("o", "C0"), "tikhonov": ("s", "C1"), "pinv": ("^", "C3")}
    for ax, key, title in ((axes[0], "err_sigma_s_prime", "sigma_s'"), (axes[1], "err_sigma_a", "sigma_a")):
        for method, (marker, color) in styles.items():
            pts = [(r["seconds"], abs(r[key][0]), r["bin_mm"]) for r in out.get("table1", [])
                   if r.get("method") == method and r["ok"]]
            if pts:
                s, e, b = zip(*pts)
                ax.scatter(s, np.maximum(e, 1e-5), marker=marker, color=color, label=method)
                if method != "direct":
                    for si, ei, bi in zip(s, e, b):
                        ax.annotate(f"{bi:.2f}", (si, max(ei, 1e-5)), fontsize=6, alpha=0.6)
        ax.axhline(TARGET_SSP if key == "err_sigma_s_prime" else TARGET_SA, ls="--", color="gray", lw=0.8,
                   label="target")
        ax.set(xscale="log", yscale="log", xlabel="seconds", ylabel=f"|relative error| of {title}",
               title=f"Table-1 scene: {title} error vs time (labels: bin mm)")
        ax.legend(fontsize=8)
    cost = out.get("cost", [])
    if cost:
        m = [r["m"] for r in cost]
        axes[2].plot(m, [r["direct_s"] for r in cost], "o-", label="ours: direct")
        axes[2].plot(m, [r["pinv_s"] for r in cost], "^-", label="ours: pinv 0.35 mm")
        dm = [(r["m"], r["dense_s"]) for r in cost if r.get("dense_s")]
        if dm:
            axes[2].plot(*zip(*dm), "k*-", label="literal dense pinv")
        de = [(r["m"], r["dense_extrapolated_s"]) for r in cost if r.get("dense_extrapolated_s")]
        if de:
            axes[2].plot(*zip(*de), "k*:", alpha=0.5, label="dense, extrapolated (memory)")
        axes[2].set(xscale="log", yscale="log", xlabel="patches m", ylabel="seconds", title="cost vs patch count")
        axes[2].legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    print(f"wrote {path}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="coarser meshes, fewer cases, m = 1k and 3k only")
    ap.add_argument("--json", type=Path, help="write the rows and verdicts as JSON")
    ap.add_argument("--png", type=Path, default=DEFAULT_PNG, help=f"error-vs-time figure (default {DEFAULT_PNG})")
    ap.add_argument("--no-png", action="store_true", help="do not write the figure")
    ap.add_argument("--dense-max-gb", type=float, default=2.0,
                    help="run the literal dense method only while its distance matrix fits (GB)")
    ap.add_argument("--repeats", type=int, default=None, help="timing repeats (default 2, --quick 1)")
    ap.add_argument("--sizes", type=int, nargs="+", help="patch counts of section 3")
    ap.add_argument("--skip", nargs="+", default=[], choices=["table1", "led", "models", "cost"],
                    help="sections to skip")
    args = ap.parse_args(argv)
    if args.repeats is None:
        args.repeats = 1 if args.quick else 2
    sub_est, sub_fine = (3, 4) if args.quick else (4, 5)
    radius = 10.0
    cam = PinholeCamera.looking_at(width_px=640, height_px=480, fx_px=1500, position_mm=CAMERA_MM,
                                   target_mm=(0, 0, 0))
    est = patches_from_mesh(trimesh.creation.icosphere(subdivisions=sub_est, radius=radius), cam)
    fine = fine_sources(sub_fine, radius)
    load = os.getloadavg() if hasattr(os, "getloadavg") else (np.nan,) * 3
    threads = {k: os.environ[k] for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
               if k in os.environ}
    out: dict[str, Any] = {"environment": {"cpu_count": os.cpu_count(), "loadavg_start": list(load),
                                           "blas_threads_env": threads, "quick": args.quick}}
    print(f"# single-image benchmark: {len(est.areas_mm2)} estimator patches ({est.visible.sum()} visible, spacing "
          f"{est.spacing_mm:.2f} mm), {len(fine.areas_mm2)} source patches for synthesis")
    print(f"# {os.cpu_count()} cores, load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}, "
          f"BLAS threads env {threads or 'unset'}\n")
    t_all = time.perf_counter()
    if "table1" not in args.skip:
        section_table1(args, est, fine, out)
    if "led" not in args.skip:
        section_led(args, est, fine, out)
    if "models" not in args.skip:
        section_models(args, est, fine, out)
    if "cost" not in args.skip:
        section_cost(args, out)
    out["environment"]["loadavg_end"] = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    out["environment"]["seconds_total"] = time.perf_counter() - t_all
    if not args.no_png and str(args.png) not in ("", "."):
        write_png(args.png, out)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        write_json(args.json, out, indent=1)
    print(f"total {out['environment']['seconds_total']:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
