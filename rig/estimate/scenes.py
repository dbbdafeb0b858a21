"""Scene files, the estimate: :func:`estimate_scene` runs :func:`estimation.single_image.estimate_single_image`
(or the Monte-Carlo-reference-corrected form, :mod:`rig.estimate.reference.scene_reference`) on a scene read by
:func:`rig.files.scene_file.load_scene`, and :func:`run_cli` implements ``rig estimate single-image SCENE``
(docs/scene-file.md).

From image to observations the project's own helpers are reused (``rig.estimate.sessions``): each visible patch is found by
ray casting through the one ray engine (estimation.rays) and its centre sampled from the image by
``sample_at_points`` (mean over a ``window_px`` square, bilinear between window centres).
"""
from __future__ import annotations

import dataclasses
import json
import math
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from drivers.atomic import atomic_write

from rig.files.provenance import jsonable
from rig.files.scene_file import load_scene
from rig.files.scene_spec import (METHODS, MODELS, REFERENCE_MODEL, RESULT_FORMAT, Array, Scene, SceneFileError,
                         environment_directions, environment_grid_shape, patches_error, resolve_patches)
from rig.files.session import software_version


__all__ = ["estimate_scene", "format_table", "run_cli"]

#: mc-table+reference: the start's ridge scan (estimation.ridge_scan) renders at reference_spp / this, at least
#: RIDGE_SCAN_MIN_SPP (128 -> 32 spp: the scan compares points a factor 3 apart, which differ far more than that noise)
RIDGE_SCAN_SPP_DIVISOR, RIDGE_SCAN_MIN_SPP = 4, 8
#: reference_mode "adaptive" (issue 19): the reference's sample-count levels reference_spp / these, at least
#: REFERENCE_MIN_SPP; the first render at the cheapest, then the cheapest whose noise is at most half the fit's
#: (estimation.model_correction.RENDER_NOISE_FRACTION; re-checked after every refit, raised up to reference_spp / 2:
#: FINAL_SPP_FRACTION), converging and ending on renders at reference_spp / 2 at least; "legacy": every render at
#: reference_spp
REFERENCE_SPP_LEVEL_DIVISORS, REFERENCE_MIN_SPP = (8, 4, 2, 1), 8
#: "hybrid" (issue 19 line 2 at legacy's accuracy): "adaptive", and where any channel's sigma_s' is not "ok" the
#: "legacy" loop from the start (its renders and estimate exactly; the adaptive run's cost paid on top)
REFERENCE_MODES = ("adaptive", "hybrid", "legacy")
#: mc-table+reference's ridge line search (estimation.model_correction, ``refine_reference``): when no channel has
#: converged within reference_iterations renders, 3-6 renders along the ridge of constant albedo at reference_spp x
#: one of REFINE_SPP_FACTORS (the smallest whose noise is at most half the plain fit's standard errors, else the
#: largest), score-function derivatives only (the sigma_a refit): the zoo's sky-lit boxes z02 / z11
REFINE_SPP_FACTORS = (2, 4, 8)
#: the default is "hybrid" (2026-11-29): on the full zoo (benchmarks/scene_zoo.py --family all) "adaptive" alone is
#: honest on every pair (S-all, A-all 34/34, cover 68/68) in ~1/4 of legacy's time but within 10 % on 29/34 pairs
#: against legacy's 31/34 (issue 15's 90 % line); "hybrid" keeps adaptive's rows where its sigma_s' is ok (z10: 3.37x
#: the issue-19 anchor) and legacy's elsewhere: 31/34, every honesty rule 34/34 / 68/68, all 28 scenes run in hybrid
#: mode, each row identical to the adaptive or the legacy run (docs/model-error.md, "hybrid")
DEFAULT_REFERENCE_MODE = "hybrid"


def _irradiance(scene: Scene, patches: Any) -> Array:
    """Fresnel-transmitted irradiance E_t (K, C) of all the scene's lights on the patches."""
    from estimation.single_image import DirectionalLights, PointLights, patch_irradiance

    eta = scene.material.eta
    n_ch = scene.channels
    e = np.zeros((patches.centers_mm.shape[0], n_ch))
    if scene.point_lights:
        pl = PointLights(np.array([p.position_mm for p in scene.point_lights]),
                         np.array([p.intensity for p in scene.point_lights]))
        e += patch_irradiance(patches, pl, eta)
    if scene.directional_lights:
        dl = DirectionalLights(np.array([d.direction for d in scene.directional_lights]),
                               np.array([d.irradiance for d in scene.directional_lights]))
        e += patch_irradiance(patches, dl, eta)
    if scene.environment is not None and scene.environment_data is not None:
        d, w = environment_directions(scene.environment, scene.environment_data)
        grid = environment_grid_shape(scene.environment, scene.environment_data)   # per-cell cast shadows
        e += patch_irradiance(patches, DirectionalLights(d, np.broadcast_to(w, (w.shape[0], n_ch)), grid), eta)
    return e


def _specular_patches(scene: Scene, patches: Any) -> NDArray[np.bool_]:
    """Patches whose normal lies within ``specular_cone_deg`` of the half vector of any point/directional light
    and the camera: where a mirror-like highlight of that light can appear."""
    c = patches.centers_mm
    v = scene.camera.camera.C[None, :] - c
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    to_lights = [np.asarray(p.position_mm)[None, :] - c for p in scene.point_lights]
    to_lights += [np.broadcast_to(np.asarray(d.direction), c.shape) for d in scene.directional_lights]
    cos_cone = math.cos(math.radians(scene.image.specular_cone_deg))
    spec = np.zeros(c.shape[0], dtype=bool)
    for lvec in to_lights:
        lv = lvec / np.linalg.norm(lvec, axis=1, keepdims=True)
        h = lv + v
        h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)
        spec |= np.einsum("kc,kc->k", h, patches.normals) >= cos_cone
    return spec


# ---------------------------------------------------------------------------------------------- patches
@dataclass(frozen=True)
class _SceneGeometry:
    """The scene's patches, the full mesh's pixel-to-face map (H, W), and the decimation (None: one patch per
    face) with the reason the patch budget gave."""

    patches: Any
    pixel_face: NDArray[np.int32]
    decimated: Any
    reason: str
    pixel_points_mm: Array | None = None     # (H, W, 3) the surface point of each pixel (decimated patches only)

    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {"decimated": self.decimated is not None, "reason": self.reason}
        if self.decimated is not None:
            out.update(self.decimated.summary())
            out["method"] = ("quadric decimation (trimesh simplify_quadric_decimation); full faces -> nearest patch "
                             "centre; centres moved onto the full surface; visibility, pixel map and shadows on "
                             "the full mesh")
        return out


def _scene_patches(scene: Scene, budget: Any, cos_min: float, shadows: bool | str, model_name: str,
                   stage: dict[str, float]) -> _SceneGeometry:
    """Patches of the scene's mesh under the patch budget ``budget`` ("auto" or an integer; scene_spec.
    resolve_patches), the pixel map of the full mesh, and the stage times (added to ``stage``)."""
    from estimation.single_image import decimate_mesh, patches_from_decimated, patches_from_mesh

    from rig.estimate.pixel_map import pixel_faces

    mesh, cam, est = scene.mesh_data, scene.camera.model, scene.estimation
    if budget != est.patches:     # the --patches flag: validated like the file's key
        bad = patches_error(budget, len(mesh.faces), est.max_patches, scene.mesh.max_edge_mm)
        if bad is not None:
            raise SceneFileError(str(scene.path), "estimation.patches (--patches)", bad, budget)
    target, reason = resolve_patches(budget, len(mesh.faces), est.max_patches)
    if target is None:
        t = time.perf_counter()
        patches = patches_from_mesh(mesh, cam, cos_min=cos_min, occlusion=est.occlusion, shadows=shadows)
        stage["patches"] = time.perf_counter() - t
        t = time.perf_counter()
        faces = pixel_faces(mesh, cam, engine=patches.occluder)
        stage["pixel_map"] = time.perf_counter() - t
        return _SceneGeometry(patches, faces, None, reason)
    if model_name == REFERENCE_MODEL:
        raise SceneFileError(str(scene.path), "estimation.patches", "one patch per face (patches >= the mesh's "
                             f"{len(mesh.faces)} faces and max_patches >= them) for model {REFERENCE_MODEL}: its "
                             "Monte Carlo reference is not built for decimated patches", budget)
    t = time.perf_counter()
    patch_mesh = decimate_mesh(mesh, target)
    stage["decimation"] = time.perf_counter() - t
    dec = patches_from_decimated(mesh, patch_mesh, cam, cos_min=cos_min, occlusion=est.occlusion, shadows=shadows)
    stage.update(dec.seconds)
    t = time.perf_counter()
    points = np.empty((cam.height_px, cam.width_px, 3))
    faces = pixel_faces(mesh, cam, engine=dec.engine, points=points)
    stage["pixel_map"] = time.perf_counter() - t
    return _SceneGeometry(dec.patches, faces, dec, reason, points)


# ---------------------------------------------------------------------------------------------- estimation
def _pixel_variance(scene: Scene, usable: NDArray[np.bool_]) -> tuple[Array, dict[str, Any]]:
    """Per-pixel variance of the image values (H, W, C) and a description of the noise model: the scene's
    ``[noise]``, or without one a signal-dependent fit var = a value + b to the usable pixels
    (:func:`estimation.noise.estimate_signal_dependent_noise`)."""
    from estimation.noise import estimate_signal_dependent_noise

    img = scene.image_data
    nz = scene.noise
    if nz is None:
        fit = estimate_signal_dependent_noise(img, usable)
        return fit.variance(img), {"source": "estimated from the image", "model": "var = a value + b",
                                   **fit.as_dict()}
    if nz.stderr_path is not None:
        assert scene.stderr_data is not None
        return np.square(scene.stderr_data), {"source": "given", "model": "standard-error image",
                                              "path": str(nz.stderr_path)}
    if nz.sigma is not None:
        return (np.broadcast_to(np.square(np.asarray(nz.sigma))[None, None, :], img.shape).copy(),
                {"source": "given", "model": "constant sigma", "sigma": list(nz.sigma)})
    assert nz.electrons_per_value is not None and nz.read_noise is not None
    var = np.maximum(img, 0.0) / nz.electrons_per_value + np.square(np.asarray(nz.read_noise))[None, None, :]
    if scene.image.format == "raw" and img.shape[2] == 3:
        var = var / np.array([1.0, 2.0, 1.0])  # G of a RAW superpixel is the mean of two photosites
    return var, {"source": "given", "model": "shot + read noise", "electrons_per_value": nz.electrons_per_value,
                 "read_noise": list(nz.read_noise)}




def _scene_summary(scene: Scene) -> dict[str, Any]:
    cam = scene.camera.camera
    out: dict[str, Any] = {
        "name": scene.name,
        "mesh": {"path": scene.mesh.path, "units": scene.mesh.units, "mm_per_unit": scene.mesh.mm_per_unit,
                 "translation_mm": scene.mesh.translation_mm, "faces": int(len(scene.mesh_data.faces)),
                 "notes": list(scene.mesh.notes)},
        "camera": {"width_px": cam.width_px, "height_px": cam.height_px, "fx_px": cam.fx_px, "fy_px": cam.fy_px,
                   "cx_px": cam.cx_px, "cy_px": cam.cy_px, "rotation": cam.rotation, "center_mm": cam.center_mm,
                   "distortion": scene.camera.distortion, "pose_from": scene.camera.pose_from,
                   "intrinsics_of": scene.camera.intrinsics_of},
        "image": {"path": scene.image.path, "format": scene.image.format, "shape": scene.image.shape,
                  "radiance_scale": scene.image.radiance_scale, "cross_polarized": scene.image.cross_polarized,
                  "specular_free": scene.image.specular_free, "saturation": scene.image.saturation,
                  "mask": scene.image.mask_path},
        "lights": {"point": [{"position_mm": p.position_mm, "intensity": p.intensity} for p in scene.point_lights],
                   "directional": [{"direction": d.direction, "irradiance": d.irradiance}
                                   for d in scene.directional_lights],
                   "environment": None if scene.environment is None else {
                       "path": scene.environment.path, "radiance_scale": scene.environment.radiance_scale,
                       "up": scene.environment.up, "phi0": scene.environment.phi0,
                       "azimuth": scene.environment.azimuth, "rotation_deg": scene.environment.rotation_deg,
                       "max_size": scene.environment.max_size}},
        "material": {"eta": scene.material.eta, "model": scene.material.model},
        "estimation": {"method": scene.estimation.method, "bin_mm": scene.estimation.bin_mm,
                       "window_px": scene.estimation.window_px,
                       "reference_spp": scene.estimation.reference_spp,
                       "reference_iterations": scene.estimation.reference_iterations,
                       "reference_seed": scene.estimation.reference_seed,
                       "max_view_angle_deg": scene.estimation.max_view_angle_deg,
                       "occlusion": scene.estimation.occlusion, "shadows": scene.estimation.shadows,
                       "cutoff_mm": scene.estimation.cutoff_mm,
                       "model_error": scene.estimation.model_error, "patches": scene.estimation.patches,
                       "max_patches": scene.estimation.max_patches},
        "noise": None if scene.noise is None else {"sigma": scene.noise.sigma,
                                                   "electrons_per_value": scene.noise.electrons_per_value,
                                                   "read_noise": scene.noise.read_noise,
                                                   "stderr_path": None if scene.noise.stderr_path is None
                                                   else str(scene.noise.stderr_path)},
    }
    return out


def estimate_scene(scene: Scene, *, method: str | None = None, model: str | None = None,
                   reference_spp: int | None = None, reference_iterations: int | None = None,
                   reference_seed: int | None = None, shadows: bool | str | None = None,
                   patches: int | str | None = None, reference_mode: str | None = None) -> dict[str, Any]:
    """Run the single-image method on a loaded scene; return a JSON-able result (docs/scene-file.md, "Output").

    ``method`` overrides the scene's ``[estimation].method``, ``model`` its ``[material].model``, and the
    ``reference_*`` arguments its ``[estimation].reference_*`` keys (used by ``model = "mc-table+reference"``:
    the Monte Carlo table fit corrected by Monte Carlo renders of the scene, :mod:`rig.estimate.reference.scene_reference`). A failed
    estimate returns ``success: false`` with the reason in ``message`` (never raises for that); input errors were
    raised by :func:`load_scene`, or are raised here as :class:`SceneFileError` when only the reference cannot
    handle them (e.g. point lights through a non-convex refracting mesh). ``shadows`` ("auto", True/"on",
    False/"off") overrides ``[estimation].shadows``: cast shadows of the lights on the mesh (docs/visibility.md).
    ``patches`` ("auto" or an integer) overrides ``[estimation].patches``: the patches come from a copy of the mesh
    decimated to that many faces, while visibility, the pixel map and cast shadows use the full mesh
    (:mod:`estimation.single_image.decimation`). ``seconds_by_stage`` in the result times the stages.
    ``reference_mode`` (None: :data:`DEFAULT_REFERENCE_MODE`): "adaptive" (issue 19: the reference's sample count
    matched to the fit's noise, :data:`REFERENCE_SPP_LEVEL_DIVISORS`), "legacy" (every render at
    ``reference_spp``) or "hybrid" (adaptive; where a channel's sigma_s' is not "ok", legacy from the start:
    ``reference["hybrid_fallback"]`` records the adaptive run's estimate, renders and seconds).
    """
    from estimation.single_image import SingleImageResult, estimate_single_image
    from estimation.single_image.decimation import PATCH_MIN_PIXELS, gather_patch_pixels

    from rig.estimate.pixel_map import sample_at_points

    t0 = time.perf_counter()
    budget = scene.estimation.patches if patches is None else patches
    meth = method or scene.estimation.method
    if meth not in METHODS:
        raise SceneFileError(str(scene.path), "estimation.method", "one of " + ", ".join(METHODS), meth)
    model_name = model or scene.material.model
    if model_name not in MODELS:
        raise SceneFileError(str(scene.path), "material.model", "one of " + ", ".join(MODELS), model_name)
    spp = scene.estimation.reference_spp if reference_spp is None else int(reference_spp)
    iterations = scene.estimation.reference_iterations if reference_iterations is None else int(reference_iterations)
    ref_seed = scene.estimation.reference_seed if reference_seed is None else int(reference_seed)
    mode = DEFAULT_REFERENCE_MODE if reference_mode is None else str(reference_mode)
    if mode not in REFERENCE_MODES:
        raise ValueError(f"reference_mode must be one of {REFERENCE_MODES}; got {reference_mode!r}")
    if spp < 2 or iterations < 1 or ref_seed < 0:
        raise ValueError(f"reference_spp must be >= 2, reference_iterations >= 1, reference_seed >= 0; got {spp}, "
                         f"{iterations}, {ref_seed}")
    cam = scene.camera.model
    mesh = scene.mesh_data
    est = scene.estimation
    cos_min = math.cos(math.radians(est.max_view_angle_deg))
    sh = est.shadows if shadows is None else {"on": True, "off": False}.get(shadows, shadows)  # type: ignore[call-overload]
    if not (sh == "auto" or isinstance(sh, bool)):
        raise ValueError(f"shadows must be 'auto', 'on', 'off', True or False; got {shadows!r}")
    stage: dict[str, float] = {}
    geo = _scene_patches(scene, budget, cos_min, sh, model_name, stage)
    patches = geo.patches
    dec = geo.decimated
    img = scene.image_data
    n_ch = img.shape[2]
    h, w = img.shape[:2]
    faces = geo.pixel_face
    on_object = faces >= 0
    t_obs = time.perf_counter()
    user_ok = np.ones((h, w), bool) if scene.mask_data is None else scene.mask_data
    sat_ok = np.ones((h, w), bool) if scene.image.saturation is None else ~np.any(
        img >= scene.image.saturation, axis=2)
    valid = (on_object & user_ok & sat_ok)[..., None] & np.isfinite(img)
    if scene.stderr_data is not None:
        valid &= np.isfinite(scene.stderr_data)
    var, noise_info = _pixel_variance(scene, np.all(valid, axis=2))
    if dec is None:
        obs, sigma = sample_at_points(img, var, valid, cam, patches.centers_mm, window_px=est.window_px)
    else:   # from the pixels of the full faces that belong to each patch
        assert geo.pixel_points_mm is not None
        obs, sigma, _ = gather_patch_pixels(img, var, valid, faces, dec.face_to_patch, geo.pixel_points_mm,
                                            patches.centers_mm, patches.normals)
    obs[~patches.visible] = np.nan

    # what excluded the visible patches (a patch can be counted under several reasons)
    ones = np.ones((h, w, 1))
    vis_centers = patches.centers_mm[patches.visible]

    def observable(ok_px: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """Which visible patches would be observed if only the pixels ``ok_px`` (H, W) were valid."""
        if dec is None:
            v, _ = sample_at_points(ones, ones * 0, ok_px[..., None], cam, vis_centers, window_px=est.window_px)
            return np.isfinite(v[:, 0])
        n_px = np.bincount(dec.face_to_patch[faces[ok_px & on_object]], minlength=len(patches.areas_mm2))
        return n_px[patches.visible] >= PATCH_MIN_PIXELS

    base = observable(on_object)

    def lost(extra_ok: NDArray[np.bool_]) -> int:
        return int(np.sum(base & ~observable(on_object & extra_ok)))

    excluded: dict[str, int] = {
        "off_object_or_frame": int(np.sum(~base)),
        "mask": lost(user_ok) if scene.mask_data is not None else 0,
        "saturated": lost(sat_ok) if scene.image.saturation is not None else 0,
    }
    spec = np.zeros(len(patches.areas_mm2), bool)
    if not scene.image.specular_free:
        spec = _specular_patches(scene, patches) & patches.visible
        obs[spec] = np.nan
    excluded["specular_cone"] = int(spec.sum())

    k = np.asarray(scene.image.radiance_scale, float)[None, :]
    factor = 2.0 if scene.image.cross_polarized else 1.0  # the analyzer passes half the depolarized diffuse light
    obs = obs / k * factor
    sigma = sigma / k * factor
    stage["sampling"] = time.perf_counter() - t_obs
    t_irr = time.perf_counter()
    e_t = _irradiance(scene, patches)
    stage["irradiance_and_shadows"] = time.perf_counter() - t_irr
    t_fit = time.perf_counter()
    n_obs = np.isfinite(obs[patches.visible]).sum(axis=0)
    fit_kw: dict[str, Any] = dict(method=meth, bin_mm=est.bin_mm, cutoff_mm=est.cutoff_mm,
                                  noise_sigma=sigma,
                                  model_error=est.model_error)
    reference_out: dict[str, Any] | None = None
    if model_name == REFERENCE_MODEL:
        from estimation.model_correction import estimate_with_reference

        from rig.estimate.reference.scene_reference import scene_reference

        valid_px = np.all(valid, axis=2)
        levels = tuple(sorted({min(spp, max(REFERENCE_MIN_SPP, spp // k)) for k in REFERENCE_SPP_LEVEL_DIVISORS}))

        def run_reference(adaptive: bool, line_search: bool = True) -> tuple[Any, dict[str, Any]]:
            ref, ref_info = scene_reference(scene, patches, valid_px, spp=spp,   # SceneFileError before any fit
                                            spp_levels=levels if adaptive and len(levels) > 1 else ())
            # the start's scan along the ridge of constant albedo (estimation.ridge_scan): cheap renders,
            # score-function derivatives only (the sigma_a refit; no paired difference in sigma_s')
            scan_ref = dataclasses.replace(ref, spp=max(RIDGE_SCAN_MIN_SPP, spp // RIDGE_SCAN_SPP_DIVISOR),
                                           fd_log_sigma_s=0.0, renders=[], spp_levels=(), level=-1)
            # the ridge line search's renderer: the same scene at more spp, its own render log (reference.renders
            # stays one entry per loop iteration)
            refine_ref = dataclasses.replace(ref, spp=spp * REFINE_SPP_FACTORS[-1], renders=[],
                                             fd_log_sigma_s=0.0, spp_levels=tuple(spp * k for k in REFINE_SPP_FACTORS),
                                             level=0)
            try:
                r = estimate_with_reference(obs, patches, e_t, scene.material.eta, ref, base_model="mc-table",
                                            max_iterations=iterations, seed=ref_seed, scan_reference=scan_ref,
                                            refine_reference=refine_ref if line_search else None, **fit_kw)
            except ValueError as exc:  # e.g. the reference has no value at any observed patch
                r = SingleImageResult(False, f"Monte Carlo reference: {exc}", meth, model_name, scene.material.eta)
            info = {**ref_info, "base_model": "mc-table", "max_iterations": iterations, "seed": ref_seed,
                    "steps": r.extra.get("reference", []), "converged": r.extra.get("converged"),
                    "interval_propagation": r.extra.get("interval_propagation"),
                    "renders": list(ref.renders),
                    "render_seconds_total": float(sum(x["seconds"] for x in ref.renders)),
                    "ridge_scan": r.extra.get("ridge_scan"), "scan_renders": list(scan_ref.renders),
                    "scan_render_seconds_total": float(sum(x["seconds"] for x in scan_ref.renders)),
                    "reference_mode": mode, "spp_levels": list(ref.spp_levels) or [spp],
                    "sample_count_levels": r.extra.get("sample_count_levels"),
                    "ridge_line_search": r.extra.get("ridge_line_search"),
                    "line_search_renders": list(refine_ref.renders),
                    "seconds_total": r.extra.get("seconds_total")}
            return r, info

        # hybrid: the adaptive pass without the ridge line search, which runs only where no channel converged, and
        # such an estimate stays weak: the fallback follows either way (the same decision and result, its renders
        # saved); with one level only the pass is the legacy loop and keeps it
        res, reference_out = run_reference(mode != "legacy", line_search=mode != "hybrid" or len(levels) < 2)
        if mode == "hybrid":
            # the adaptive loop's estimate stands where every channel's sigma_s' is "ok" (or where it had one level
            # only: it was the legacy loop); else the legacy loop's from the start (the same renders and estimate as
            # --reference-mode legacy; provenance: hybrid_fallback)
            st = (res.extra.get("status") or {}).get("sigma_s_prime_per_mm") if res else None
            if len(reference_out["spp_levels"]) > 1 and not (st and all(x == "ok" for x in st)):
                first, first_info = res, reference_out
                res, reference_out = run_reference(False)
                reference_out["hybrid_fallback"] = {
                    "why": f"adaptive sigma_s' status {st}" if first else f"adaptive failed: {first.message}",
                    "adaptive_sigma_s_prime_per_mm": None if first.sigma_s_prime_per_mm is None else
                    np.asarray(first.sigma_s_prime_per_mm, float).tolist(),
                    "adaptive_render_spp": [x.get("spp") for x in first_info["renders"]],
                    "adaptive_seconds_total": first_info["seconds_total"],
                    "adaptive_render_seconds_total": first_info["render_seconds_total"],
                    "adaptive_line_search_renders": len(first_info["line_search_renders"])}
            else:
                reference_out["hybrid_fallback"] = None
    else:
        res = estimate_single_image(obs, patches, e_t, scene.material.eta, model=model_name, **fit_kw)
    stage["fit"] = time.perf_counter() - t_fit
    seconds = time.perf_counter() - t0
    channels = ["R", "G", "B"] if n_ch == 3 else ["Y"]
    out: dict[str, Any] = {
        "format": RESULT_FORMAT, "format_version": 1, "estimator": "single-image",
        "success": bool(res), "message": res.message if patches.visible.any() else
        res.message + " (check the camera pose and that the mesh's face normals point outward)",
        "method": res.method, "model": model_name, "eta": scene.material.eta, "channels": channels,
        "seconds": seconds, "seconds_by_stage": stage,
        "observations": {"patches": int(len(patches.areas_mm2)), "visible": int(patches.visible.sum()),
                         "mesh_faces": int(len(mesh.faces)), "patch_decimation": geo.summary(),
                         "observed_per_channel": n_obs.tolist(), "excluded_patches": excluded,
                         "object_pixels": int(on_object.sum()), "patch_spacing_mm": patches.spacing_mm,
                         "cast_shadows": patches.shadows,
                         "nonfinite_pixels": int(scene.image_meta.get("nonfinite", 0))},
        "radiometry": {"radiance_scale": list(scene.image.radiance_scale), "cross_polarized_factor": factor,
                       "noise_model": noise_info},
    }
    if res:
        ssp, sa = res.sigma_s_prime_per_mm, res.sigma_a_per_mm
        out["parameters"] = {
            "sigma_s_prime_per_mm": {"value": ssp, "ci95": res.sigma_s_prime_ci_per_mm},
            "sigma_a_per_mm": {"value": sa, "ci95": res.sigma_a_ci_per_mm,
                               "ci95_wald": res.sigma_a_ci_jacobian_per_mm},
            "R_d": {"value": res.R_d, "ci95": res.R_d_ci},
            "l_d_mm": {"value": res.l_d_mm, "ci95": res.l_d_ci_mm},
            "D_mm": {"value": res.D_mm},
            "albedo": {"value": ssp / (ssp + sa)},
            "transport_mean_free_path_mm": {"value": 1.0 / (ssp + sa)},
        }
        out["correlation_log"] = res.correlation_log
        out["sigma_a_identifiable"] = list(res.sigma_a_identifiable_per_channel)
        out["identifiability_reason"] = res.identifiability_reason
    out["model_bias"] = res.extra.get("model_bias")
    if res:
        out["status"] = res.extra.get("status")
        out["status_reasons"] = res.extra.get("status_reasons")
    else:  # a failed estimate is no measurement of anything
        out["status"] = {"sigma_s_prime_per_mm": ["unknown"] * n_ch, "sigma_a_per_mm": ["unknown"] * n_ch}
        out["status_reasons"] = [f"channel {c}: the estimate failed: {res.message}" for c in range(n_ch)]
    if reference_out is not None:
        out["reference"] = reference_out
        out["converged"] = reference_out["converged"]
    d = res.diagnostics
    if d is not None:
        out["diagnostics"] = {"condition_number": d.condition_number, "n_bins": d.n_bins,
                              "empty_bins": d.empty_bins, "residual_rms": d.residual_rms,
                              "relative_residual_rms": d.relative_residual_rms, "n_observations": d.n_observations,
                              "n_patches": d.n_patches, "nfev": d.nfev, "solver_seconds": d.seconds,
                              "regularization": d.regularization, "notes": list(d.notes)}
    out["scene"] = _scene_summary(scene)
    out["provenance"] = {
        "scene": str(scene.path), "scene_sha256": scene.sha256,
        "image": str(scene.image.path), "image_sha256": scene.image.sha256,
        "mesh": str(scene.mesh.path), "mesh_sha256": scene.mesh.sha256,
        "mask": None if scene.image.mask_path is None else str(scene.image.mask_path),
        "mask_sha256": scene.image.mask_sha256,
        "environment": None if scene.environment is None else str(scene.environment.path),
        "environment_sha256": None if scene.environment is None else scene.environment.sha256,
        "method": res.method, "software": "sssrig", "software_version": software_version(),
        "python": platform.python_version(), "numpy": np.__version__,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    return jsonable(out)


# ---------------------------------------------------------------------------------------------- CLI
def _fmt(v: Any) -> str:
    return "-" if v is None else f"{v:.4g}"


def _cells(values: Any) -> str:
    return "[" + ", ".join(_fmt(v) for v in (values or [])) + "]"


def _reference_lines(result: dict[str, Any]) -> list[str]:
    """The reference iteration of model mc-table+reference: parameters and render seconds per step, converged,
    and the bias of the flat mc-table model in this scene."""
    ref = result.get("reference")
    if not ref:
        return []
    lines = [f"  Monte Carlo reference ({ref.get('spp')} spp per render, seed {ref.get('seed')}, at most "
             f"{ref.get('max_iterations')} renders, window {ref.get('window_px')} px): converged "
             f"{'yes' if ref.get('converged') else 'NO'}, {len(ref.get('renders', []))} renders, "
             f"{ref.get('render_seconds_total', 0.0):.1f} s rendering",
             f"    {'step':<10}{'sigma_s_prime [1/mm]':<28}{'sigma_a [1/mm]':<28}{'render s':<10}"
             f"{'kappa median (reference / mc-table)'}"]
    for st in ref.get("steps", []):
        it = st.get("iteration")
        label = "0 mc-table" if it == 0 else f"{it}"
        lines.append(f"    {label:<10}{_cells(st.get('sigma_s_prime_per_mm')):<28}{_cells(st.get('sigma_a_per_mm')):<28}"
                     f"{st.get('render_seconds', 0.0):<10.1f}{_cells(st.get('kappa_median'))}")
    bias = result.get("model_bias") or {}
    if "radiance_ratio_median" in bias:
        lines.append(f"  model bias in this scene (mc-table / reference radiance per patch): median "
                     f"{_cells(bias.get('radiance_ratio_median'))}, 5-95 % {_cells(bias.get('radiance_ratio_p05'))}"
                     f"-{_cells(bias.get('radiance_ratio_p95'))}, rms log {_cells(bias.get('rms_log_ratio'))}")
    fb = ref.get("hybrid_fallback")
    if fb:
        lines.append(f"  reference mode hybrid: the adaptive loop ({fb['adaptive_render_spp']} spp, "
                     f"{fb['adaptive_seconds_total'] or 0.0:.1f} s; sigma_s' "
                     f"{_cells(fb['adaptive_sigma_s_prime_per_mm'])} 1/mm) was not ok ({fb['why']}): the legacy "
                     "loop's estimate above")
    for n in ref.get("notes", []):
        lines.append(f"  reference: {n}")
    return lines


def format_table(result: dict[str, Any]) -> str:
    """A readable table of the parameters with their 95 % intervals."""
    prov = result.get("provenance", {})
    obs = result.get("observations", {})
    lines = [f"single-image estimate of {prov.get('scene', '?')}",
             f"  method {result.get('method')}, model {result.get('model')}, eta {result.get('eta')}, "
             f"{obs.get('visible', 0)} visible of {obs.get('patches', 0)} patches, observed per channel "
             f"{obs.get('observed_per_channel')}, {result.get('seconds', 0.0):.1f} s"]
    dec = obs.get("patch_decimation") or {}
    if dec.get("decimated"):
        lines.append(f"  {dec.get('reason')} (decimation deviation median {dec.get('deviation_mm_median', 0.0):.3g} "
                     f"mm, 99 % {dec.get('deviation_mm_p99', 0.0):.3g} mm)")
    if not result.get("success"):
        lines.append(f"  FAILED: {result.get('message')}")
        lines += _reference_lines(result)
        return "\n".join(lines)
    chans = result["channels"]
    lines.append("  " + f"{'quantity':<26}" + "".join(f"{c:<28}" for c in chans))
    labels = [("sigma_s_prime_per_mm", "sigma_s' [1/mm]"), ("sigma_a_per_mm", "sigma_a [1/mm]"),
              ("R_d", "R_d"), ("l_d_mm", "l_d = 1/sigma_tr [mm]"), ("D_mm", "D [mm]"),
              ("albedo", "albedo alpha'"), ("transport_mean_free_path_mm", "1/sigma_t' [mm]")]
    for key, label in labels:
        p = result["parameters"][key]
        cells = []
        for c in range(len(chans)):
            v = p["value"][c]
            ci = p.get("ci95")
            cell = _fmt(v) + (f" ({_fmt(ci[c][0])}-{_fmt(ci[c][1])})" if ci is not None else "")
            cells.append(f"{cell:<28}")
        lines.append("  " + f"{label:<26}" + "".join(cells))
    ident = result.get("sigma_a_identifiable", [])
    lines.append("  " + f"{'sigma_a identifiable':<26}" + "".join(f"{('yes' if i else 'NO'):<28}" for i in ident))
    status = result.get("status") or {}
    for key, label in (("sigma_s_prime_per_mm", "status sigma_s'"), ("sigma_a_per_mm", "status sigma_a")):
        if key in status:
            lines.append("  " + f"{label:<26}" + "".join(f"{v.upper() if v != 'ok' else 'ok':<28}" for v in status[key]))
    lines.append("  (95 % intervals in parentheses; sigma_a: profile likelihood, lower bound 0 when one-sided)")
    if not all(ident):
        lines.append(f"  {result.get('identifiability_reason', '')}")
    if any(v != "ok" for vals in status.values() for v in vals):
        lines.append("  WEAK = not a measurement to quote without its interval: " +
                     "; ".join(result.get("status_reasons") or []))
    lines += _reference_lines(result)
    notes = result.get("diagnostics", {}).get("notes", [])
    for n in notes:
        lines.append(f"  note: {n}")
    if result.get("message") not in (None, "ok"):
        lines.append(f"  message: {result['message']}")
    return "\n".join(lines)


def run_cli(args: Any) -> int:
    """``rig estimate single-image SCENE [--method M] [--model MODEL] [--reference-spp N]
    [--reference-iterations K] [--reference-seed S] [--shadows auto|on|off] [--patches auto|N] [--out FILE]
    [--json]``.

    Prints a table (or the JSON with ``--json``) and writes the JSON atomically to ``--out`` or
    ``<scene>.estimate.json`` beside the scene file. Returns 0 on success, 1 if the estimate failed (the reason
    is printed); input errors raise :class:`SceneFileError` (the CLI prints them and returns 2).
    """
    scene = load_scene(args.scene)
    result = estimate_scene(scene, method=getattr(args, "method", None), model=getattr(args, "model", None),
                            reference_spp=getattr(args, "reference_spp", None),
                            reference_iterations=getattr(args, "reference_iterations", None),
                            reference_seed=getattr(args, "reference_seed", None),
                            shadows=getattr(args, "shadows", None), patches=getattr(args, "patches", None),
                            reference_mode=getattr(args, "reference_mode", None))
    out = getattr(args, "out", None)
    out_path = Path(out) if out is not None else Path(args.scene).with_suffix(".estimate.json")
    text = json.dumps(result, indent=2, allow_nan=False) + "\n"

    def write(tmp: Path) -> None:
        tmp.write_text(text, encoding="utf-8")

    atomic_write(out_path, write)
    if getattr(args, "json", False):
        print(text, end="")
        print(f"wrote {out_path}", file=sys.stderr)
    else:
        print(format_table(result))
        print(f"wrote {out_path}")
    if not result["success"]:
        print(f"rig estimate single-image: estimation failed: {result['message']}", file=sys.stderr)
        return 1
    return 0
