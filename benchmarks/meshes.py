"""Benchmark of the ray engine (estimation.rays.RayEngine) on a scanned-like mesh, beside Embree's raw rate and
beside the brute-force visibility it replaced (issue 17).

The mesh: an icosphere displaced by smooth noise (a sum of random low-frequency sinusoids of the position, ~6 %
of the radius), a crater (a Gaussian pit 0.45 R deep: concave, self-occluding) and a handle (a torus half sunk
into the body: non-convex, with a hole), ~100k faces (``--quick``: ~26k). A pinhole camera sees it whole.

1. **Rays per second** on the same random rays aimed at the mesh (about half hit): Embree's raw rate (embreex
   scene built directly from float32 arrays, ``EmbreeScene.run`` on float32 rays prepared in advance — the
   floor no wrapper can beat), ``RayEngine.first_hit`` (faces and distances: what the package uses; acceptance:
   at least half the raw rate), trimesh's own Embree interface (``intersects_first``: faces only;
   ``intersects_location``: faces and hit points) and the numba BVH fallback.
2. **Patches + visibility** (the geometry stage of ``rig estimate single-image``): the pixel-to-face map of the
   camera (``rig.estimate.pixel_map.pixel_faces``, one ray per pixel; engine build included) and the camera visibility of
   ~10k patches (``patches_from_mesh`` on the same shape tessellated to ~10k faces, occlusion on; and the
   occlusion of 10k patch centres of the full mesh against all its faces), beside the old paths: the painter's
   order rasterizer (run whole), every pixel ray against every face (old ``MeshObject._hits``) and every patch
   segment against every face (old ``_occluded``), the last two timed on a subset and extrapolated linearly
   (they are O(rays x faces)). benchmarks/_brute_force_visibility.py holds the old code.
3. **Cast shadows** (issue 17 part 2): shadow rays of a point light from 10k face centres of the full mesh
   against all its faces (``estimation.shadows.point_light_visibility``), and the environment-map shadows of a
   sky with a sun (64 x 128 map, default 16 cell rows) on the ~10k patches (``environment_irradiance``).
4. **End to end**: ``rig estimate single-image`` (``rig.files.scene_file.load_scene`` + ``rig.estimate.scenes.estimate_scene``,
   model ``mc-table``, method direct, shadows auto = on) on a scene file of the full ~100k-face mesh itself with
   ``[estimation] patches = 10000`` (``--quick``: the 26k-face mesh at 2,500), lit by a point light; its image is
   the estimator's forward model with shadows on one patch per face of the full mesh (not timed), painted per
   face through the ray-cast pixel map. Each run loads the scene, decimates the mesh, builds the engine and fits
   afresh (nothing cached across runs; the direct system's in-memory cache is cleared); the stage split comes from
   the result's ``seconds_by_stage``: load, decimation, patch map (full faces -> patches), engine build,
   convexity test, snapping the centres onto the full surface, occlusion, pixel map (with the pixels' surface
   points), sampling (noise model, gathering each patch's pixels, exclusion counts), irradiance with shadow rays,
   fit. Visibility + shadows = engine build + convexity + snap + occlusion + pixel map + irradiance with shadows.
   Beside it the old path: one patch per face (refused above ``max_patches`` before decimation) with brute-force
   visibility (section 2's extrapolation) plus this run's load and fit.

Timings are wall-clock minima over ``--repeats`` runs; the load average is printed (on a shared machine the
absolute times are inflated; ratios within one run remain meaningful). Embree runs on its own thread pool (all
cores); the numba fallback on ``NUMBA_NUM_THREADS``.

Run: ``python benchmarks/meshes.py [--quick] [--json out.json]`` (about a minute; --quick < 30 s). Not run in CI.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Callable

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")   # as the rig command line (rig/cli.py)

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _brute_force_visibility import (hits_brute_force, occluded_brute_force,  # noqa: E402
                                     pixel_faces_painters_order)
from estimation.camera import PinholeCamera  # noqa: E402
from estimation.rays import RayEngine, embree_available  # noqa: E402
from estimation.shadows import environment_irradiance, point_light_visibility  # noqa: E402
from estimation.single_image import (EnvironmentMap, PointLights, patch_irradiance,  # noqa: E402
                                     patches_from_mesh, predict_radiance)
from estimation.single_image.geometry import occluded_from  # noqa: E402
from rig.estimate.pixel_map import pixel_faces  # noqa: E402
from rig.files.provenance import write_json  # noqa: E402

RADIUS_MM = 30.0


def scanned_like_mesh(sphere_subdivisions: int, handle_sections: tuple[int, int], seed: int = 7
                      ) -> trimesh.Trimesh:
    """Icosphere (radius 30 mm) displaced by smooth noise and a crater, plus a torus handle sunk into it."""
    rng = np.random.default_rng(seed)
    s = trimesh.creation.icosphere(subdivisions=sphere_subdivisions, radius=1.0)
    u = np.asarray(s.vertices)
    k = rng.normal(size=(12, 3)) * 2.5                      # spatial frequencies (1/radius)
    ph = rng.uniform(0, 2 * np.pi, 12)
    amp = rng.normal(size=12) * 0.06 / np.sqrt(12)
    r = 1.0 + np.sin(u @ k.T + ph) @ amp
    crater_axis = np.array([0.3, -0.8, 0.52]) / np.linalg.norm([0.3, -0.8, 0.52])
    ang = np.arccos(np.clip(u @ crater_axis, -1, 1))
    r -= 0.45 * np.exp(-(ang / 0.35) ** 2)                  # a pit ~40 deg wide, 0.45 R deep
    body = trimesh.Trimesh(u * r[:, None] * RADIUS_MM, s.faces, process=False)
    handle = trimesh.creation.torus(0.75 * RADIUS_MM, 0.16 * RADIUS_MM, major_sections=handle_sections[0],
                                    minor_sections=handle_sections[1])
    handle.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    handle.apply_translation((0.0, 0.0, 0.9 * RADIUS_MM))   # an arch over the top, its lower half inside the body
    return trimesh.util.concatenate([body, handle])


def _best(fn: Callable[[], Any], repeats: int) -> tuple[float, Any]:
    best, out = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def _random_rays(n: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n, 3))
    o *= 3 * RADIUS_MM / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.normal(size=(n, 3)) * 0.9 * RADIUS_MM - o       # aimed at a ball of the mesh's size: ~half hit
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def rates(mesh: trimesh.Trimesh, n_rays: int, repeats: int) -> dict[str, Any]:
    o, d = _random_rays(n_rays)
    out: dict[str, Any] = {"rays": n_rays, "faces": len(mesh.faces)}
    if embree_available():
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        scene = rtcore_scene.EmbreeScene()
        TriangleMesh(scene=scene, vertices=np.asarray(mesh.vertices, np.float32),
                     indices=np.asarray(mesh.faces, np.int32))
        o32, d32 = o.astype(np.float32), d.astype(np.float32)
        scene.run(o32[:10], d32[:10])
        t_raw, raw = _best(lambda: scene.run(o32, d32), repeats)
        eng = RayEngine(mesh.vertices, mesh.faces, backend="embree")
        t_eng, (face, _) = _best(lambda: eng.first_hit(o, d), repeats)
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        tm = RayMeshIntersector(mesh)
        tm.intersects_first(o[:10], d[:10])
        t_tm, _ = _best(lambda: tm.intersects_first(o, d), repeats)
        t_tml, _ = _best(lambda: tm.intersects_location(o, d, multiple_hits=False), repeats)
        out.update(trimesh_first_rays_per_s=n_rays / t_tm, trimesh_location_rays_per_s=n_rays / t_tml)
        out.update(embree_raw_rays_per_s=n_rays / t_raw, engine_rays_per_s=n_rays / t_eng,
                   engine_over_raw=t_raw / t_eng, hit_fraction=float(np.mean(face >= 0)),
                   same_face_as_raw=float(np.mean(face == raw)))
    bvh = RayEngine(mesh.vertices, mesh.faces, backend="bvh")
    bvh.first_hit(o[:10], d[:10])                           # numba compile (cached on disk after the first run)
    n_b = min(n_rays, 200_000)
    t_bvh, _ = _best(lambda: bvh.first_hit(o[:n_b], d[:n_b]), max(1, repeats - 1))
    out["bvh_rays_per_s"] = n_b / t_bvh
    return out


def visibility(mesh: trimesh.Trimesh, patch_mesh: trimesh.Trimesh, cam: PinholeCamera, n_patch: int,
               repeats: int, subset: int) -> dict[str, Any]:
    out: dict[str, Any] = {"faces": len(mesh.faces), "pixels": cam.width_px * cam.height_px,
                           "patch_mesh_faces": len(patch_mesh.faces)}
    # pixel map: new (engine build included) vs painter's order vs every pixel against every face
    t_pf, faces_new = _best(lambda: pixel_faces(mesh, cam), repeats)
    t_paint, faces_old = _best(lambda: pixel_faces_painters_order(mesh, cam), 1)
    on = faces_new >= 0
    o, d = cam.pixel_rays()
    # where both see a face but not the same one: is the painter's face a neighbour (a rasterization edge
    # effect: faces smaller than a pixel) or a surface behind the visible one (wrong order: a hidden face)?
    both = (faces_old != faces_new) & on & (faces_old >= 0)
    fo = faces_old[both]
    n = np.asarray(mesh.face_normals)[fo]
    v0 = np.asarray(mesh.vertices)[np.asarray(mesh.faces)[fo, 0]]
    t_old = np.einsum("ij,ij->i", v0 - o[both], n) / np.einsum("ij,ij->i", d[both], n)
    _, t_new = RayEngine(mesh.vertices, mesh.faces).first_hit(o[both], d[both])
    out.update(pixel_map_s=t_pf, painters_s=t_paint, object_pixels=int(on.sum()),
               painters_pixels_differing=int(np.sum(faces_old != faces_new)),
               painters_pixels_other_face=int(both.sum()),
               painters_pixels_hidden_face=int(np.sum(t_old - t_new > 0.01 * RADIUS_MM)),
               painters_pixels_object_mismatch=int(np.sum((faces_old >= 0) != on)))
    rng = np.random.default_rng(0)
    pick = rng.choice(o.shape[0] * o.shape[1], size=subset, replace=False)
    tri = np.asarray(mesh.triangles, float)
    t_sub, (t_bf, f_bf, _, _) = _best(
        lambda: hits_brute_force(tri, o.reshape(-1, 3)[pick], d.reshape(-1, 3)[pick]), 1)
    out["pixel_brute_force_s_extrapolated"] = t_sub * out["pixels"] / subset
    f_bf = np.where(np.isfinite(t_bf), f_bf, -1)
    out["pixel_brute_force_agrees"] = float(np.mean(f_bf == faces_new.reshape(-1)[pick]))
    # patches + camera visibility of ~10k patches of the same shape (its own faces occlude)
    t_pv, p = _best(lambda: patches_from_mesh(patch_mesh, cam, occlusion=True), repeats)
    out.update(patches_s=t_pv, patches=len(patch_mesh.faces), visible_patches=int(p.visible.sum()))
    t_pnone, _ = _best(lambda: patches_from_mesh(patch_mesh, cam, occlusion=False), repeats)
    facing = patches_from_mesh(patch_mesh, cam, occlusion=False).visible
    idx = np.flatnonzero(facing)
    pv = np.asarray(patch_mesh.vertices, float)
    pf = np.asarray(patch_mesh.faces)
    sub = idx[rng.choice(len(idx), size=min(subset, len(idx)), replace=False)]
    t_osub, _ = _best(lambda: occluded_brute_force(np.asarray(patch_mesh.triangles_center)[sub], cam.C, pv, pf, sub,
                                                   chunk=16), 1)
    out["patches_brute_force_s_extrapolated"] = t_pnone + t_osub * len(idx) / len(sub)
    # 10k patch centres of the full mesh, occlusion against all its faces
    centers = np.asarray(mesh.triangles_center, float)
    own = rng.choice(len(centers), size=n_patch, replace=False)
    eng = RayEngine(mesh.vertices, mesh.faces)
    t_build, _ = _best(lambda: RayEngine(mesh.vertices, mesh.faces), 1)
    t_occ, blocked = _best(lambda: occluded_from(eng, centers[own], cam.C, own), repeats)
    sub2 = own[:subset]
    t_osub2, blocked_bf = _best(lambda: occluded_brute_force(centers[sub2], cam.C, np.asarray(mesh.vertices, float),
                                                             np.asarray(mesh.faces), sub2, chunk=4), 1)
    out.update(engine_build_s=t_build, occlusion_full_mesh_s=t_occ, occlusion_patches=n_patch,
               occlusion_full_mesh_brute_force_s_extrapolated=t_osub2 * n_patch / len(sub2),
               occlusion_agrees_with_brute_force=float(np.mean(blocked[:subset] == blocked_bf)))
    out["visibility_s"] = t_pf + t_build + t_occ
    out["visibility_brute_force_s_extrapolated"] = (out["pixel_brute_force_s_extrapolated"]
                                                    + out["occlusion_full_mesh_brute_force_s_extrapolated"])
    return out


LIGHT_MM = np.array([[-120.0, -160.0, 140.0]])


def _sky(h: int = 64, w: int = 128) -> np.ndarray:
    th, ph = np.meshgrid(np.pi * (np.arange(h) + 0.5) / h, 2 * np.pi * (np.arange(w) + 0.5) / w, indexing="ij")
    d = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    s = np.array([-np.sin(0.7), -0.3, np.cos(0.7)])
    s /= np.linalg.norm(s)
    return (0.2 + 0.8 * np.clip(d[..., 2], 0, 1) + 400.0 * np.exp((d @ s - 1.0) / 0.003))[..., None]


def shadows(mesh: trimesh.Trimesh, patch_mesh: trimesh.Trimesh, cam: PinholeCamera, n_patch: int,
            repeats: int) -> dict[str, Any]:
    rng = np.random.default_rng(2)
    centers = np.asarray(mesh.triangles_center, float)
    own = rng.choice(len(centers), size=n_patch, replace=False)
    eng = RayEngine(mesh.vertices, mesh.faces)
    normals = np.asarray(mesh.face_normals, float)
    t_pt, vis = _best(lambda: point_light_visibility(eng, centers[own], normals[own], LIGHT_MM, own_face=own),
                      repeats)
    facing = np.einsum("kc,kc->k", LIGHT_MM[0] - centers[own], normals[own]) > 0
    p = patches_from_mesh(patch_mesh, cam)
    env = EnvironmentMap(_sky())
    d, w = env.directions_and_weights()
    stats: dict[str, Any] = {}
    t_env, _ = _best(lambda: environment_irradiance(p.occluder, p.centers_mm, p.normals, d, w, env.grid_shape(),
                                                    1.3, stats=stats), 1)
    t_env0, _ = _best(lambda: patch_irradiance(p, env, 1.3, shadows=False), 1)
    return {"point_shadow_rays": int(facing.sum()), "point_shadow_s": t_pt,
            "point_shadowed_fraction": float(np.mean(~vis[facing, 0])),
            "env_patches": len(p.areas_mm2), "env_rays": stats["rays"], "env_bright_pixels": stats["bright_pixels"],
            "env_shadows_s": t_env, "env_unshadowed_s": t_env0}


def end_to_end(mesh: trimesh.Trimesh, cam: PinholeCamera, folder: Path, n_patches: int, runs: int) -> dict[str, Any]:
    """Time rig estimate single-image on a scene file of the full ``mesh`` with ``patches = n_patches`` (see the
    module docstring, item 4): ``runs`` independent runs (scene loaded, mesh decimated, engine built afresh)."""
    from estimation.single_image import estimate as single_image_estimate
    from rig.files.imageio import write_exr
    from rig.estimate.scenes import estimate_scene
    from rig.files.scene_file import load_scene

    ssp, sa, eta, inten = 1.2, 0.01, 1.3, 1e6
    t_img = time.perf_counter()
    p = patches_from_mesh(mesh, cam)                  # one patch per face of the full mesh: the image's truth
    lights = PointLights(LIGHT_MM, [[inten]])
    lo = predict_radiance(p, lights, eta, [ssp], [sa], model="mc-table")   # visible faces, shadows on
    rad = np.zeros(len(p.areas_mm2))
    rad[p.visible] = lo[:, 0]
    faces = pixel_faces(mesh, cam)
    img = np.where(faces >= 0, rad[np.maximum(faces, 0)], 0.0)[..., None].astype(np.float32)
    write_exr(folder / "img.exr", img)
    mesh.export(folder / "mesh.ply")
    cam_rows = "\n".join(f"  {list(map(float, r))}," for r in cam.R)
    (folder / "scene.toml").write_text(
        "version = 1\n[mesh]\npath = \"mesh.ply\"\n"
        f"[camera]\nwidth_px = {cam.width_px}\nheight_px = {cam.height_px}\nfx_px = {cam.fx_px}\n"
        f"position_mm = {list(map(float, cam.C))}\nrotation = [\n{cam_rows}\n]\n"
        "[image]\npath = \"img.exr\"\nspecular_free = true\n"
        f"[[point_lights]]\nposition_mm = {list(map(float, LIGHT_MM[0]))}\nintensity = {inten}\n"
        f"[material]\neta = {eta}\nmodel = \"mc-table\"\n[estimation]\npatches = {n_patches}\n"
        f"[noise]\nsigma = {1e-3 * float(np.median(lo)):.6g}\n")
    out: dict[str, Any] = {"faces": len(mesh.faces), "image_visible_faces": int(p.visible.sum()),
                           "image_s": time.perf_counter() - t_img, "runs": []}
    for _ in range(runs):
        single_image_estimate._SYSTEMS.clear()        # nothing cached across runs
        t0 = time.perf_counter()
        scene = load_scene(folder / "scene.toml")
        t1 = time.perf_counter()
        res = estimate_scene(scene)
        t2 = time.perf_counter()
        st = res["seconds_by_stage"]
        run = {"load_s": t1 - t0, "estimate_s": t2 - t1, "total_s": t2 - t0, "stages_s": st,
               "patches": res["observations"]["patches"], "visible": res["observations"]["visible"],
               "observed": res["observations"]["observed_per_channel"][0],
               "decimation": res["observations"]["patch_decimation"],
               "sigma_s_prime_error": res["parameters"]["sigma_s_prime_per_mm"]["value"][0] / ssp - 1.0,
               "cast_shadows": res["observations"]["cast_shadows"]}
        vis = sum(st.get(k, 0.0) for k in ("engine_build", "snap", "occlusion", "pixel_map", "convexity"))
        run["visibility_s"] = vis
        run["visibility_and_shadows_s"] = vis + st.get("irradiance_and_shadows", 0.0)
        out["runs"].append(run)
    out["best"] = min(out["runs"], key=lambda r: r["total_s"])
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="a ~26k-face mesh, fewer rays and pixels (< 30 s)")
    ap.add_argument("--repeats", type=int, default=None)
    ap.add_argument("--json", type=str, default=None, help="write the figures to this file ('-' = stdout)")
    ap.add_argument("--end-to-end-only", action="store_true", help="section 4 only (rig estimate single-image)")
    ap.add_argument("--runs", type=int, default=None, help="section 4: independent runs (default 2; --quick 1)")
    a = ap.parse_args(argv)
    quick = a.quick
    repeats = a.repeats or (2 if quick else 3)
    t_start = time.perf_counter()
    mesh = scanned_like_mesh(5, (64, 40)) if quick else scanned_like_mesh(6, (128, 80))
    patch_mesh = scanned_like_mesh(4, (64, 40))              # 5120 + 5120 = 10,240 faces: the ~10k patches
    w, h = (320, 240) if quick else (1024, 768)
    cam = PinholeCamera.looking_at(width_px=w, height_px=h, fx_px=1.1 * w, position_mm=(40.0, -150.0, 90.0),
                                   target_mm=(0.0, 0.0, 8.0))
    load = os.getloadavg()
    say = (lambda *x: print(*x, file=sys.stderr)) if a.json == "-" else print
    say(f"# mesh: {len(mesh.faces)} faces (watertight body + handle), camera {w} x {h}; load average "
        f"{load[0]:.2f} {load[1]:.2f}; Embree {'available' if embree_available() else 'MISSING (numba BVH only)'}; "
        f"NUMBA_NUM_THREADS={os.environ.get('NUMBA_NUM_THREADS', 'default')}")
    r: dict[str, Any] = {}
    v: dict[str, Any] = {}
    sh: dict[str, Any] = {}
    if not a.end_to_end_only:
        r = rates(mesh, 200_000 if quick else 1_000_000, repeats)
        if "embree_raw_rays_per_s" in r:
            say(f"rays/s  Embree raw {r['embree_raw_rays_per_s'] / 1e6:.2f} M | RayEngine (embree) "
                f"{r['engine_rays_per_s'] / 1e6:.2f} M = {r['engine_over_raw']:.2f} x raw (target >= 0.5) | trimesh "
                f"intersects_first (faces only) {r['trimesh_first_rays_per_s'] / 1e6:.2f} M, intersects_location "
                f"(faces + points) {r['trimesh_location_rays_per_s'] / 1e6:.2f} M | numba BVH "
                f"{r['bvh_rays_per_s'] / 1e6:.2f} M  ({r['rays']} rays, {r['hit_fraction']:.0%} hit, same face as raw "
                f"{r['same_face_as_raw']:.4%})")
        else:
            say(f"rays/s  numba BVH {r['bvh_rays_per_s'] / 1e6:.2f} M (Embree not installed: no raw rate)")
        v = visibility(mesh, patch_mesh, cam, 10_000, repeats, 40 if quick else 60)
        say(f"pixel map ({v['pixels']} px, {v['faces']} faces): ray cast {v['pixel_map_s']:.3f} s | painter's order "
            f"{v['painters_s']:.3f} s ({v['painters_pixels_differing']} of {v['object_pixels']} object px differ: "
            f"{v['painters_pixels_hidden_face']} show a face > 0.3 mm behind the visible surface, "
            f"{v['painters_pixels_other_face'] - v['painters_pixels_hidden_face']} a neighbouring face, "
            f"{v['painters_pixels_object_mismatch']} object/background) | every pixel x every face "
            f"{v['pixel_brute_force_s_extrapolated']:.0f} s "
            f"(extrapolated; agrees {v['pixel_brute_force_agrees']:.1%}) -> "
            f"{v['pixel_brute_force_s_extrapolated'] / v['pixel_map_s']:.0f}x")
        say(f"patches + visibility ({v['patches']} patches, own mesh, occlusion on): {v['patches_s']:.3f} s | "
            f"brute force "
            f"{v['patches_brute_force_s_extrapolated']:.1f} s (extrapolated) -> "
            f"{v['patches_brute_force_s_extrapolated'] / v['patches_s']:.0f}x")
        say(f"occlusion of {v['occlusion_patches']} patch centres vs all {v['faces']} faces: "
            f"{v['occlusion_full_mesh_s']:.3f} s "
            f"(+ engine build {v['engine_build_s']:.3f} s) | brute force "
            f"{v['occlusion_full_mesh_brute_force_s_extrapolated']:.0f} s (extrapolated; agrees "
            f"{v['occlusion_agrees_with_brute_force']:.1%}) -> "
            f"{v['occlusion_full_mesh_brute_force_s_extrapolated'] / v['occlusion_full_mesh_s']:.0f}x")
        say(f"visibility total (pixel map + build + patch occlusion): {v['visibility_s']:.3f} s | brute force "
            f"{v['visibility_brute_force_s_extrapolated']:.0f} s (extrapolated) -> "
            f"{v['visibility_brute_force_s_extrapolated'] / v['visibility_s']:.0f}x; "
            f"run {time.perf_counter() - t_start:.1f} s")
        sh = shadows(mesh, patch_mesh, cam, 10_000, repeats)
        say(f"shadows: point light, {sh['point_shadow_rays']} shadow rays from face centres of the "
            f"{len(mesh.faces)}-face mesh ({sh['point_shadowed_fraction']:.1%} shadowed): {sh['point_shadow_s']:.3f} s "
            f"| sky + sun 64 x 128 on "
            f"{sh['env_patches']} patches: {sh['env_rays']} rays ({sh['env_bright_pixels']} bright px) "
            f"{sh['env_shadows_s']:.2f} s (unshadowed irradiance alone {sh['env_unshadowed_s']:.2f} s)")
    import tempfile
    with tempfile.TemporaryDirectory() as tmp:
        e = end_to_end(mesh, cam, Path(tmp), 10_000 if not quick else 2_500, a.runs or (1 if quick else 2))
    for i, run in enumerate(e["runs"]):
        st = run["stages_s"]
        dec = run["decimation"]
        say(f"rig estimate single-image, run {i + 1} (scene file of the {e['faces']}-face mesh, patches = "
            f"{run['patches']}, mc-table, point light, shadows {'on' if run['cast_shadows'] else 'off'}): "
            f"{run['total_s']:.2f} s = load {run['load_s']:.2f} + decimation {st.get('decimation', 0):.2f} + patch map "
            f"{st.get('patch_map', 0):.2f} + engine build {st.get('engine_build', 0):.2f} + convexity "
            f"{st.get('convexity', 0):.2f} + snap {st.get('snap', 0):.3f} + occlusion {st.get('occlusion', 0):.3f} + "
            f"pixel map {st.get('pixel_map', 0):.2f} + sampling "
            f"{st.get('sampling', 0):.2f} + irradiance/shadows {st.get('irradiance_and_shadows', 0):.3f} + fit "
            f"{st.get('fit', 0):.2f} + rest {run['total_s'] - run['load_s'] - sum(st.values()):.2f}; visibility + shadows {run['visibility_and_shadows_s']:.2f} s = "
            f"{run['visibility_and_shadows_s'] / run['total_s']:.0%}; sigma_s' {run['sigma_s_prime_error']:+.1%} "
            f"({run['visible']} visible, {run['observed']} observed; decimation deviation median "
            f"{dec['deviation_mm_median']:.3f} mm, 99 % {dec['deviation_mm_p99']:.3f} mm, {dec['not_snapped']} not "
            f"snapped)")
    best = e["best"]
    if a.end_to_end_only:
        say(f"end to end, {e['faces']}-face mesh at {best['patches']} patches: best {best['total_s']:.2f} s, "
            f"visibility + shadows {best['visibility_and_shadows_s'] / best['total_s']:.0%} (acceptance: < 5 s, "
            f"< 25 %); load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
        return 0
    old_path = (best["stages_s"].get("fit", 0.0) + best["load_s"] + v["visibility_brute_force_s_extrapolated"])
    say(f"end to end, {e['faces']}-face mesh at {best['patches']} patches: best {best['total_s']:.2f} s, visibility + "
        f"shadows {best['visibility_and_shadows_s'] / best['total_s']:.0%} (acceptance: < 5 s, < 25 %) | old path "
        f"(one patch per face would be refused above max_patches; brute-force visibility, no shadows): "
        f"{old_path:.0f} s (extrapolated)")
    data = {"quick": quick, "load_average": load, "rates": r, "visibility": v, "shadows": sh, "end_to_end": e}
    if a.json == "-":
        print(json.dumps(data, indent=1))
    elif a.json:
        write_json(a.json, data, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
