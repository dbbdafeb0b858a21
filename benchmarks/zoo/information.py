"""Is the information there? The likelihood profile of a zoo frame along sigma_s' (docs/model-error.md sec. 4).

For each scene: Monte Carlo references rendered from the *scene file* (rig.estimate.reference.scene_reference: the mesh, camera,
lights and map the estimator is given) at f x (sigma_s', sigma_a) of the truth, f in ``--factors`` (default 0.8,
0.9, 1, 1.1, 1.25): sigma_a is scaled with sigma_s', so the albedo -- which sets the brightness of a uniformly lit
body -- is held and only the optical size of the object changes, and sigma_a is then re-optimised at every f to
first order (the renderer's score-function derivative d Q / d log sigma_a from the same paths: chi^2 minimised
over delta log sigma_a within +-0.7 (:func:`estimation.ridge_scan.profile_chi2`, the function the reference loop's
start scans the ridge with), which is printed; |delta| << 1 says the albedo-held ridge was the right one, a
clipped +-0.7 that sigma_a hardly shows in the frame). Every render
uses the same seeds (common random numbers); two seeds (``--seeds``) give an unbiased *expected* delta-chi^2.

chi^2 of the frame against each render, per channel, two ways:

- ``px``: over the object pixels of the faces the estimator observes (view angle below its limit, valid pixels),
  with the scene's noise model exactly as the estimator builds it (``rig.estimate.scenes._pixel_variance``: the
  ``[noise]`` section, else the signal-dependent fit to the image) plus the renders' own Monte Carlo variance;
  this is the frame's likelihood;
- ``patch``: over the estimator's patches (3 x 3 window means sampled as ``estimate_scene`` samples them) in the
  metric of the reference loop (stated or fitted noise, the render's noise, the 2 % relative model error);
  neighbouring windows overlap, so this counts pixels several times -- it is what the loop sees, not the frame's
  information.

Printed per scene and channel: chi^2 / n at the truth, delta-chi^2 (profile, sigma_a re-optimised) at each f
relative to f = 1, the fitted delta log sigma_a, and the *expected* delta-chi^2 at 0.9 and 1.1 -- sum over pixels
of (Q_f - Q_1)_perp^2 / var_frame, the part of the change not absorbed by sigma_a, as the cross product of the two
seeds' differences (the Monte Carlo noise of the renders does not bias it): the delta-chi^2 a frame with this noise
gives on average, with its standard error over pixels; divided by chi^2/n at the truth where that exceeds 1 (the
noise model understates the frame's noise: a ``[noise]`` section holds the camera noise, not the frame's own Monte
Carlo noise). Verdict on that calibrated value at -10 % and +10 %: "not resolved" when one side is below -2
standard errors (heavy-tailed render noise: sun lobes), "beyond the information limit" when one side is below 4
even at +2 standard errors (the frame cannot tell sigma_s' from 0.9 or 1.1 sigma_s' at 2 sigma),
"information there" when both exceed 4 at -2 standard errors, else "at the limit / not resolved by the renders".

Run: ``NUMBA_NUM_THREADS=2 python benchmarks/zoo/information.py --scenes 2,8,17,23,25 [--spp 256]
[--seeds 11,12] [--factors 0.8,0.9,1,1.1,1.25] [--json out.json]``; ``--from-json a.json,b.json`` reprints
saved results. Frames come from the zoo's cache
(benchmarks/out/zoo, rendered on first use); cost ~ 2 x len(factors) renders per scene at ``--spp``.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estimation.ridge_scan import profile_chi2  # noqa: E402 (the reference loop start's own profile)
from rig.files.provenance import write_json  # noqa: E402
from zoo.frames import build_scene, default_root  # noqa: E402
from zoo.nonconvex import draw_nonconvex  # noqa: E402
from zoo.scenes import draw_zoo  # noqa: E402

MODEL_ERROR = 0.02   # the reference loop's relative model error ([estimation].model_error default)


def frame_data(scene: Any) -> dict[str, Any]:
    """The frame as the estimator reads it (rig.estimate.scenes.estimate_scene): patches, valid pixels, the
    per-pixel variance of the noise model, the observations at the patches and their standard errors, all in
    radiance units (value / radiance_scale)."""
    from estimation.single_image import patches_from_mesh
    from rig.estimate.pixel_map import pixel_faces, sample_at_points
    from rig.estimate.scenes import _pixel_variance

    cam = scene.camera.model
    est = scene.estimation
    cos_min = math.cos(math.radians(est.max_view_angle_deg))
    patches = patches_from_mesh(scene.mesh_data, cam, cos_min=cos_min, occlusion=est.occlusion,
                                shadows=est.shadows)
    img = np.asarray(scene.image_data, float)
    faces = pixel_faces(scene.mesh_data, cam)
    on_object = faces >= 0
    valid = on_object[..., None] & np.isfinite(img)
    var, info = _pixel_variance(scene, np.all(valid, axis=2))
    obs, sig = sample_at_points(img, var, valid, cam, patches.centers_mm, window_px=est.window_px)
    obs[~patches.visible] = np.nan
    k = np.asarray(scene.image.radiance_scale, float)
    # pixels of the faces the estimator observes: view angle within its limit
    mesh = scene.mesh_data
    centre = np.asarray(mesh.triangles_center)[np.maximum(faces, 0)]
    view = np.asarray(scene.camera.camera.C)[None, None, :] - centre
    view /= np.linalg.norm(view, axis=2, keepdims=True)
    cos_v = np.einsum("hwk,hwk->hw", np.asarray(mesh.face_normals)[np.maximum(faces, 0)], view)
    seen = on_object & (cos_v >= cos_min)
    return {"patches": patches, "img": img / k, "var": var / k ** 2, "valid_px": np.all(valid, axis=2),
            "seen_px": seen & np.all(valid, axis=2), "obs": obs / k[None, :], "sig": sig / k[None, :],
            "noise": info, "window_px": est.window_px}


def render_at(ref: Any, ssp: np.ndarray, sa: np.ndarray, eta: float, seed: int, spp: int) -> dict[str, Any]:
    """One Monte Carlo render of the scene-file reference (radiance, stderr, d/d log sigma_a per pixel)."""
    from simulators.mc import Medium, render

    media = [Medium.from_reduced(float(s), float(a), g=ref.g, eta=float(eta)) for s, a in zip(ssp, sa)]
    t0 = time.perf_counter()
    img = render(ref.shape, media, ref.camera, ref.lights, spp=int(spp), seed=int(seed), derivatives=True,
                 fd_log_sigma_s=0.0)
    return {"q": img.radiance, "se": img.stderr, "da": img.d_log_sigma[..., 1], "mask": img.mask,
            "seconds": time.perf_counter() - t0}


def _perp(x: np.ndarray, d: np.ndarray, w: np.ndarray) -> np.ndarray:
    dd = float(np.sum(w * d * d))
    return x - (float(np.sum(w * x * d)) / dd) * d if dd > 0 else x


def scene_profile(index: int, *, spp: int, seeds: list[int], factors: list[float]) -> dict[str, Any]:
    from rig.estimate.pixel_map import sample_at_points
    from rig.files.scene_file import load_scene
    from rig.estimate.reference.scene_reference import scene_reference

    specs = draw_zoo() + draw_nonconvex()
    spec = specs[index]
    folder, _meta = build_scene(spec, default_root())
    scene = load_scene(folder / "scene.toml")
    fd = frame_data(scene)
    ref, _ = scene_reference(scene, fd["patches"], fd["valid_px"], spp=spp)
    s0, a0 = spec.sigma_s_prime_per_mm, spec.sigma_a_per_mm
    renders: dict[tuple[float, int], dict[str, Any]] = {}
    secs = 0.0
    for f in factors:
        for sd in seeds:
            rr = render_at(ref, f * s0, f * a0, spec.eta, sd, spp)
            secs += rr["seconds"]
            renders[(f, sd)] = rr
            print(f"  z{index:02d} f={f:g} seed {sd}: {rr['seconds']:.1f} s", file=sys.stderr, flush=True)
    n_ch = len(spec.channels)
    px = fd["seen_px"] & np.all([renders[(f, sd)]["mask"] for f in factors for sd in seeds], axis=0)
    cam = ref.camera
    pat = ref.patches
    valid_r = np.broadcast_to(fd["valid_px"][..., None], fd["img"].shape)
    out: dict[str, Any] = {"scene": spec.name, "index": index, "spp": spp, "seeds": seeds, "factors": factors,
                           "render_seconds": secs, "noise_model": fd["noise"].get("model"),
                           "pixels": int(px.sum()), "channels": []}
    for c in range(n_ch):
        o = fd["img"][px, c]
        v_frame = fd["var"][px, c]
        mean = {f: {k: np.mean([renders[(f, sd)][k][px, c] for sd in seeds], axis=0) for k in ("q", "da")}
                for f in factors}
        se2 = {f: np.mean([renders[(f, sd)]["se"][px, c] ** 2 for sd in seeds], axis=0) / len(seeds)
               for f in factors}
        row: dict[str, Any] = {"channel": spec.channels[c], "sigma_s_prime_true": float(s0[c]),
                               "sigma_a_true": float(a0[c]), "px": {}, "patch": {}, "expected_px": {}}
        # the frame's likelihood over pixels
        chi = {}
        for f in factors:
            w = 1.0 / (v_frame + se2[f])
            c0, cp, dl = profile_chi2(o - mean[f]["q"], mean[f]["da"], w)
            chi[f] = (c0, cp, dl)
        for f in factors:
            row["px"][f] = {"chi2": chi[f][0], "chi2_profile": chi[f][1], "delta_log_sigma_a": chi[f][2],
                            "dchi2_profile": chi[f][1] - chi[1.0][1], "dchi2_held": chi[f][0] - chi[1.0][0]}
        row["chi2_per_px_truth"] = chi[1.0][1] / max(1, o.size)
        # the expected delta-chi^2: cross product of the two seeds' differences, sigma_a's direction projected out
        if len(seeds) >= 2:
            w = 1.0 / v_frame
            for f in factors:
                if f == 1.0:
                    continue
                diffs = [_perp(renders[(f, sd)]["q"][px, c] - renders[(1.0, sd)]["q"][px, c], mean[f]["da"], w)
                         for sd in seeds[:2]]
                held = [renders[(f, sd)]["q"][px, c] - renders[(1.0, sd)]["q"][px, c] for sd in seeds[:2]]
                prod = w * diffs[0] * diffs[1]
                row["expected_px"][f] = {"profile": float(np.sum(prod)),
                                         "profile_se": float(np.sqrt(prod.size) * np.std(prod)),
                                         "held": float(np.sum(w * held[0] * held[1]))}
        # the reference loop's view: patches, its metric
        obs, sig = fd["obs"][:, c], fd["sig"][:, c]
        pq = {}
        for f in factors:
            qs, ses, das = [], [], []
            for sd in seeds:
                rr = renders[(f, sd)]
                v = np.broadcast_to(rr["mask"][..., None], rr["q"].shape) & valid_r
                q, qv = sample_at_points(rr["q"], rr["se"] ** 2, v, cam, pat.centers_mm, fd["window_px"])
                da, _ = sample_at_points(rr["da"], rr["se"] ** 2 * 0, v, cam, pat.centers_mm, fd["window_px"])
                qs.append(q[:, c])
                ses.append(qv[:, c] ** 2)
                das.append(da[:, c])
            pq[f] = (np.mean(qs, axis=0), np.mean(ses, axis=0) / len(seeds), np.mean(das, axis=0))
        ok = np.isfinite(obs) & np.isfinite(sig) & np.all([np.isfinite(pq[f][0]) for f in factors], axis=0)
        chi_p, chi_p0 = {}, {}
        for f in factors:
            q, q_se2, da = pq[f]
            w = 1.0 / (sig[ok] ** 2 + q_se2[ok] + (MODEL_ERROR * q[ok]) ** 2)
            chi_p[f] = profile_chi2(obs[ok] - q[ok], da[ok], w)
            # the same without the relative model error (the noise alone: what the metric's 2 % floor costs)
            chi_p0[f] = profile_chi2(obs[ok] - q[ok], da[ok], 1.0 / (sig[ok] ** 2 + q_se2[ok]))
        for f in factors:
            row["patch"][f] = {"chi2_profile": chi_p[f][1], "dchi2_profile": chi_p[f][1] - chi_p[1.0][1],
                               "delta_log_sigma_a": chi_p[f][2],
                               "dchi2_profile_no_model_error": chi_p0[f][1] - chi_p0[1.0][1]}
        row["patches"] = int(ok.sum())
        row["patch_chi2_per_n_truth"] = chi_p[1.0][1] / max(1, int(ok.sum()))
        row["expected_calibrated"], row["verdict"] = verdict(row)
        out["channels"].append(row)
    return out


def verdict(row: dict[str, Any]) -> tuple[dict[str, Any], str]:
    """The expected delta-chi^2 at 0.9 and 1.1, calibrated by the frame's residual level at the truth (chi^2/n > 1:
    the noise model understates the frame's noise, e.g. a [noise] section without the frame's Monte Carlo noise),
    with its standard error over pixels, and the verdict (module docstring)."""
    cal = max(1.0, row["chi2_per_px_truth"])
    ex = {str(k): v for k, v in row["expected_px"].items()}
    e = [ex.get(k, {}).get("profile", float("nan")) / cal for k in ("0.9", "1.1")]
    e_se = [ex.get(k, {}).get("profile_se", float("nan")) / cal for k in ("0.9", "1.1")]
    out = {"0.9": [e[0], e_se[0]], "1.1": [e[1], e_se[1]], "chi2_per_px": cal}
    if not all(np.isfinite(e + e_se)):
        return out, "not measured (one seed)"
    if any(x < -2 * sd for x, sd in zip(e, e_se)):
        return out, "not resolved: the renders' noise dominates"
    if any(x + 2 * sd < 4 for x, sd in zip(e, e_se)):
        return out, "beyond the information limit"
    if all(x - 2 * sd > 4 for x, sd in zip(e, e_se)):
        return out, "information there"
    return out, "at the limit / not resolved by the renders"


def print_table(results: list[dict[str, Any]]) -> None:
    print("| scene | ch | px | chi2/n px at truth | obs. dchi2 px 0.8 / 0.9 / 1.1 / 1.25 "
          "| delta log sigma_a at 0.9 / 1.1 "
          "| expected dchi2 px 0.9 / 1.1 (albedo held) | expected / (chi2/n) 0.9 / 1.1 | loop's dchi2 patches "
          "0.9 / 1.1 / 1.25 (without the 2 % model error) | verdict |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        for row in r["channels"]:
            def g(d: dict[Any, Any], f: float, k: str) -> str:
                x = d.get(f, {}).get(k, float("nan"))
                return f"{x:.1f}" if abs(x) < 1e4 else f"{x:.3g}"
            fs = [f for f in (0.8, 0.9, 1.1, 1.25) if f in row["px"]]
            print(f"| {r['scene']} | {row['channel']} | {r['pixels']} | {row['chi2_per_px_truth']:.2f} | "
                  + " / ".join(g(row["px"], f, "dchi2_profile") for f in fs) + " | "
                  + " / ".join(f"{row['px'][f]['delta_log_sigma_a']:+.3f}" for f in (0.9, 1.1) if f in row["px"])
                  + " | " + " / ".join(f"{g(row['expected_px'], f, 'profile')} ({g(row['expected_px'], f, 'held')})"
                                       for f in (0.9, 1.1)) + " | "
                  + " / ".join(f"{x:.1f} +- {s:.1f}" for x, s in (row["expected_calibrated"][k][:2]
                                                                 for k in ("0.9", "1.1"))) + " | "
                  + " / ".join(g(row["patch"], f, "dchi2_profile") for f in (0.9, 1.1, 1.25) if f in row["patch"])
                  + " (" + " / ".join(g(row["patch"], f, "dchi2_profile_no_model_error")
                                      for f in (0.9, 1.1, 1.25) if f in row["patch"]) + ")"
                  + f" | {row['verdict']} |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default="2,8,17,23,25")
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--seeds", default="11,12")
    ap.add_argument("--factors", default="0.8,0.9,1,1.1,1.25")
    ap.add_argument("--json", default=None)
    ap.add_argument("--from-json", default=None, help="print the table of saved results (comma-separated files)")
    a = ap.parse_args(argv)
    if a.from_json:
        saved = [r for f in a.from_json.split(",") for r in json.loads(Path(f).read_text())]
        for r in saved:
            for row in r["channels"]:
                for key in ("px", "patch", "expected_px"):
                    row[key] = {float(k): v for k, v in row[key].items()}
                row["expected_calibrated"], row["verdict"] = verdict(row)
        print_table(saved)
        return 0
    factors = [float(x) for x in a.factors.split(",")]
    if 1.0 not in factors:
        factors.append(1.0)
    seeds = [int(x) for x in a.seeds.split(",")]
    results = []
    for i in (int(x) for x in a.scenes.split(",")):
        results.append(scene_profile(i, spp=a.spp, seeds=seeds, factors=factors))
        print(f"z{i:02d} done ({results[-1]['render_seconds']:.0f} s of renders)", file=sys.stderr, flush=True)
        if a.json:
            write_json(a.json, results, indent=1)
    print(f"# likelihood profile along sigma_s' (sigma_a scaled with it, then re-optimised); {a.spp} spp x seeds "
          f"{seeds}")
    print_table(results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
