"""The estimate on a capture folder (:func:`estimate_capture`, the entry of ``rig estimate gradients FOLDER``): the
gradient maps, the diffusion estimates (sphere, relief, seed), the Monte Carlo reference and the outputs.
"""
from __future__ import annotations

import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from numpy.typing import NDArray

from drivers.errors import ConfigError
from estimation.camera import OrthographicCamera, PinholeCamera
from estimation.gradients import LedRig
from rig.files.provenance import jsonable, sha256_file
from rig.files.session import software_version

from .spec import _AXES, CAPTURE_FILE, CAPTURE_FORMAT_VERSION, Capture, CaptureError, FrameKey, ReferenceTarget, _rel


# ------------------------------------------------------------------------------------------------ estimate
def _view_dirs(camera: PinholeCamera | OrthographicCamera) -> NDArray[np.float64]:
    _, d = camera.pixel_rays()
    return -d


def _reference_normal(camera: PinholeCamera | OrthographicCamera) -> NDArray[np.float64]:
    """Unit vector from the rig origin towards the camera: the albedo convention's n_ref (docs/gradients.md)."""
    if isinstance(camera, OrthographicCamera):
        return -camera.R[2]
    c = camera.C
    return c / np.linalg.norm(c)


def _reference_signal(cap: Capture, ref: ReferenceTarget) -> NDArray[np.float64]:
    """Median over the reference region of the ambient-subtracted cross full-on value per second."""
    x0, y0, x1, y1 = ref.region_px
    exp = {f.key: f.exposure_s for f in cap.frames}
    sat = cap.radiometry.saturation_level

    def per_s(key: FrameKey) -> NDArray[np.float64]:
        a = cap.images[key][y0:y1, x0:x1].astype(np.float64)
        if np.any(a >= sat):
            raise ConfigError(str(cap.file), "radiometry.reference.region_px", "a reference region without saturated "
                              f"pixels in frame {key[0]}/{key[1]}", list(ref.region_px))
        return a / exp[key]

    amb = per_s(("ambient", "cross"))
    if ("full", "cross") in cap.images:
        sig = per_s(("full", "cross")) - amb
    else:
        a = next(a for a in _AXES if (a, "cross") in cap.images and (a + "_c", "cross") in cap.images)
        sig = per_s((a, "cross")) + per_s((a + "_c", "cross")) - 2 * amb
    med = np.median(sig.reshape(-1, 3), axis=0)
    if np.any(~(med > 0)):
        raise ConfigError(str(cap.file), "radiometry.reference.region_px", "a region showing the lit reference "
                          "(ambient-subtracted full-on signal > 0 in every channel)", med.tolist())
    return med


def _albedo_scale(cap: Capture, leds: LedRig | None, n_ref: NDArray[np.float64]) -> tuple[NDArray[np.float64], dict]:
    from estimation.gradients import albedo_scale_from_lambertian, albedo_scale_from_radiometry

    rad = cap.radiometry
    if rad.albedo_scale is not None:
        return rad.albedo_scale, {"source": "albedo_scale (given)"}
    if rad.value_per_radiance_per_s is not None:
        assert leds is not None
        return (albedo_scale_from_radiometry(rad.value_per_radiance_per_s, leds, eta=rad.eta, reference_normal=n_ref),
                {"source": "value_per_radiance_per_s + LED calibration (albedo_scale_from_radiometry)",
                 "value_per_radiance_per_s": rad.value_per_radiance_per_s})
    assert rad.reference is not None
    sig = _reference_signal(cap, rad.reference)
    return (albedo_scale_from_lambertian(sig, rad.reference.reflectance, eta=rad.eta, leds=leds,
                                         reference_normal=n_ref),
            {"source": "Lambertian reference region (albedo_scale_from_lambertian)",
             "region_px": list(rad.reference.region_px), "reflectance": rad.reference.reflectance,
             "signal_per_s": sig})


def _strip_gradients(prov: Mapping[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in prov.items() if k not in ("gradients", "maps")}


def _check_reference(cap: Capture, reference: Mapping[str, Any]) -> None:
    """--reference needs a known sphere (it renders it); refuse clearly otherwise. Ideal gradients are rendered with
    a dense synthetic LED set (:func:`rig.estimate.folder_diffusion.ideal_reference_leds`)."""
    if cap.geometry is None:
        raise ConfigError(str(cap.file), "object.shape", "shape = \"sphere\" with center_mm and radius_mm: "
                          "--reference renders the known sphere by Monte Carlo, and corrects only a sphere's "
                          "estimate", "no sphere ([object] missing or shape = \"unknown\")")
    for k, lo in (("spp", 2), ("iterations", 1), ("seed", 0)):
        v = reference.get(k)
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < lo):
            raise ConfigError(f"--reference-{k}", k, f"an integer >= {lo}", v)
    mode = reference.get("mode")
    if mode is not None and mode not in ("adaptive", "legacy"):
        raise ConfigError("--reference-mode", "mode", "\"adaptive\" or \"legacy\"", mode)


def _reference_summary(cap: Capture, reference: Mapping[str, Any], leds: LedRig | None, scale: Any, eta: float,
                       n_ref: NDArray[np.float64], normals: Any, obj: Any, maps: Any, folder_maps: Any,
                       tile_rows: int) -> dict[str, Any]:
    """The reference-corrected sphere summary (:func:`rig.estimate.reference.folder_reference.reference_corrected_sphere`)."""
    from rig.estimate.reference.folder_reference import (REFERENCE_ITERATIONS, REFERENCE_SEED, REFERENCE_SPP,
                                                         reference_corrected_sphere)

    assert cap.geometry is not None
    led_pos, led_int = cap.leds.positions_mm, cap.leds.intensity
    if cap.leds.ideal:      # continuous gradients: the renderer sees LEDs as a distant map anyway
        from rig.estimate.folder_diffusion import ideal_reference_leds
        led_pos, led_int = ideal_reference_leds()
        leds = LedRig.from_positions(led_pos, led_int)
    assert leds is not None and led_pos is not None and led_int is not None
    region = np.asarray(obj, dtype=bool) & ~np.asarray(maps.masks.saturated).any(axis=-1)
    try:
        out, _ = reference_corrected_sphere(
            camera=cap.camera, leds=leds, led_positions_mm=led_pos,
            led_intensity=led_int, frame_keys=[f.key for f in cap.frames],
            exposure_s={f.key: f.exposure_s for f in cap.frames}, albedo_scale=scale, eta=eta,
            reference_normal=n_ref, center_mm=cap.geometry.center_mm, radius_mm=cap.geometry.radius_mm,
            true_normals=normals, region=region, folder_maps=folder_maps, observed_maps=maps,
            spp=int(reference.get("spp") or REFERENCE_SPP),
            iterations=int(reference.get("iterations") or REFERENCE_ITERATIONS),
            seed=int(REFERENCE_SEED if reference.get("seed") is None else reference["seed"]), tile_rows=tile_rows,
            render_mode=str(reference.get("render_mode", "mc")),
            reference_mode=str(reference.get("mode") or "adaptive"))
    except ValueError as exc:
        raise CaptureError(f"{cap.file}: the reference-corrected sphere estimate failed: {exc}") from exc
    return out


MEMMAP_MIN_PX = 4_000_000


"""Frames of at least this many pixels get their full-size intermediate maps as memory maps in a scratch folder
inside the output folder (deleted afterwards) instead of RAM: a 24 MP capture's maps are ~4 frame sets."""


def estimate_capture(capture: Capture, out_dir: str | Path, fmt: str = "exr", tile_rows: int | None = None, *,
                     preview: str = "auto", memmap_min_px: int = MEMMAP_MIN_PX,
                     model: str = "dipole-jensen", maps: Any = None, half: bool = False,
                     reference: Mapping[str, Any] | None = None, relief_window_px: int | None = None
                     ) -> dict[str, Any]:
    """Gradient maps (Ma et al. 2007), the grounded diffusion estimate (with a sphere) and the seed's D (with a
    seed calibration) for a loaded capture; writes the maps into ``out_dir`` (:func:`rig.files.maps_io.write_maps`) and
    returns a JSON-ready summary (per-channel medians, the diffusion summary with intervals, files, notes).

    ``fmt``: "exr" or "tiff"; ``tile_rows``: rows per processing tile of ``compute_maps`` (None: its default);
    ``memmap_min_px``: see :data:`MEMMAP_MIN_PX`. ``model``: profile model of the grounded estimate
    (:data:`estimation.diffusion.MODELS_GROUNDED`): "dipole-jensen" (default) uses the exact sphere integrals
    (method "sphere"); "dipole-better" and "mc-table" use the first-order method "small_blur" with that model's
    half-space R_d and <r^2>. The summary and sidecar record the model and its bias against the Monte Carlo table
    at the fitted parameters (``diffusion.model_bias``). ``maps``: names of the map files to write (None: all;
    :func:`rig.files.maps_io.select_maps`), ``half``: normals and albedos as EXR HALF (:data:`rig.files.maps_io.HALF_OK`);
    the sidecar lists what was written and how the left-out maps are derived.

    ``reference``: None, or {"spp": N, "iterations": K, "seed": S} (missing keys: the defaults of
    :mod:`rig.estimate.reference.folder_reference`): with a sphere and an LED calibration, the sphere summary is also corrected by
    Monte Carlo renders of the same capture (:func:`rig.estimate.reference.folder_reference.reference_corrected_sphere`) and reported
    as ``diffusion_reference_corrected`` beside the uncorrected ``diffusion``; the per-pixel maps stay uncorrected.

    Without a sphere: with ``[object] shape = "relief"`` (a normals or height file) or with specular normals
    (parallel-polarized frames), the relief-blur fit per window of ``relief_window_px`` pixels (default
    :data:`rig.estimate.folder_diffusion.RELIEF_WINDOW_PX`) and its region summary (:func:`rig.estimate.folder_diffusion.
    relief_estimate`) are the ``diffusion`` summary; otherwise D, sigma_s', sigma_a are unknown.
    """
    from estimation.diffusion import check_grounded_model

    try:
        check_grounded_model(model, "sphere" if model == "dipole-jensen" else "small_blur", capture.radiometry.eta)
    except ValueError as exc:
        raise ConfigError("--model", "model", str(exc), model) from None
    if reference is not None:
        _check_reference(capture, reference)
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    scratch = (tempfile.TemporaryDirectory(prefix=".scratch-", dir=out_dir)
               if capture.shape[0] * capture.shape[1] >= memmap_min_px else None)
    try:
        return _estimate_capture(capture, out_dir, fmt, tile_rows, preview,
                                 None if scratch is None else Path(scratch.name), model, maps, half, reference,
                                 relief_window_px)
    finally:
        if scratch is not None:
            scratch.cleanup()


def _estimate_capture(capture: Capture, out_dir: str | Path, fmt: str, tile_rows: int | None, preview: str,
                      scratch: Path | None, model: str = "dipole-jensen", select: Any = None,
                      half: bool = False, reference: Mapping[str, Any] | None = None,
                      relief_window_px: int | None = None) -> dict[str, Any]:
    from estimation.diffusion import compare_estimates, diffusion_seed, estimate_sphere, sphere_geometry
    from estimation.gradients import compute_maps
    from rig.files.maps_io import write_maps

    t0 = time.perf_counter()
    cap = capture
    rad = cap.radiometry
    leds = cap.leds.rig(cap.gradient_patterns)
    n_ref = _reference_normal(cap.camera)
    H, W = cap.shape
    normals = None
    if cap.geometry is not None:
        normals, view, hit = sphere_geometry(cap.camera, cap.geometry.center_mm, cap.geometry.radius_mm)
        if not hit.any():
            raise ConfigError(str(cap.file), "object.center_mm", "a sphere that the camera sees (no pixel hits "
                              "the sphere at center_mm / radius_mm)", cap.geometry.center_mm.tolist())
        obj = hit if cap.mask is None else hit & cap.mask
        geo_normals = np.where(hit[..., None], np.nan_to_num(normals), 0.0)
        center, radius = cap.geometry.center_mm, cap.geometry.radius_mm
    else:
        view = _view_dirs(cap.camera)
        obj = cap.mask
        geo_normals = None
        center, radius = np.zeros(3), 0.0
    scale, scale_prov = _albedo_scale(cap, leds, n_ref)
    exposure = {f.key: f.exposure_s for f in cap.frames}

    lut_memo: dict[str, Any] = {}

    def folder_maps(images: Mapping[FrameKey, Any], out: Path | None = None) -> Any:
        """The folder's map computation (also applied to the reference renders, converted to frame units). The LED
        response LUT depends only on the LEDs, eta and the surface model: built once per LED layout (compute_maps'
        defaults; kept in the process and on disk, keyed by content: :mod:`rig.estimate.response_cache`), not once
        per capture or reference render."""
        if not cap.leds.ideal and "lut" not in lut_memo:
            from rig.estimate.response_cache import response_lut
            lut_memo["lut"] = response_lut(leds, eta=rad.eta, reference_normal=n_ref, surface_center_mm=center,
                                           surface_radius_mm=radius)
        return compute_maps(images, albedo_scale=scale, leds=leds, ideal=cap.leds.ideal, eta=rad.eta,
                            lut=lut_memo.get("lut"),
                            view_dirs=view, tile_rows=tile_rows or 256, white_level=1.0,
                            saturation=rad.saturation_level, dark_threshold=rad.dark_level, object_mask=obj,
                            geometry_normals=geo_normals, reference_normal=n_ref, surface_center_mm=center,
                            surface_radius_mm=radius, exposure_s=exposure, consistency=False, out_dir=out)

    try:
        maps = folder_maps(cap.images, None if scratch is None else scratch / "gradients")
    except ValueError as exc:
        raise CaptureError(f"{cap.file}: gradient maps failed: {exc}") from exc
    t_maps = time.perf_counter() - t0
    notes = list(cap.notes)
    from rig.estimate.folder_diffusion import apply_dark_channels, relief_branch, write_albedo_apparent
    from rig.estimate.folder_regions import channel_medians, grounded_summary, region_summaries
    dark = apply_dark_channels(cap, maps, obj, exposure, notes)
    known = ~maps.unknown
    noise = None
    if cap.noise is not None:       # the frames' noise through the maps (issue 16: intervals that mean something)
        from rig.estimate.folder_noise import propagate_capture_noise
        noise = propagate_capture_noise(cap, maps, dark, folder_maps_kwargs={
            "albedo_scale": scale, "leds": leds, "ideal": cap.leds.ideal, "eta": rad.eta, "lut": lut_memo.get("lut"),
            "white_level": 1.0, "saturation": rad.saturation_level, "dark_threshold": rad.dark_level,
            "reference_normal": n_ref, "surface_center_mm": center, "surface_radius_mm": radius,
            "exposure_s": exposure, "consistency": False}, view=view, obj=obj, geo_normals=geo_normals,
            true_normals=normals)
    from rig.estimate.folder_noise import reference_scale_rel_stderr
    scale_rel = reference_scale_rel_stderr(cap)
    sphere_stderr = None if noise is None or noise.shortening is None else {
        "albedo": noise.albedo, "shortening": noise.shortening,
        **({} if scale_rel is None else {"albedo_rel_common": scale_rel})}
    seed_est = None
    if cap.seed is not None:
        seed_est = diffusion_seed(maps, cap.seed.k_mm, cap.seed.provenance, true_normals=normals)
    diffusion = None
    diff_summary: dict[str, Any]
    relief_files: dict[str, Path] = {}
    relief_fit = None
    ref_summary: dict[str, Any] | None = None
    if cap.geometry is not None:
        assert normals is not None
        method = "sphere" if model == "dipole-jensen" else "small_blur"
        est = estimate_sphere(maps, radius_mm=cap.geometry.radius_mm, true_normals=normals, region=obj,
                              tile_rows=tile_rows or 256, out_dir=None if scratch is None else scratch / "diffusion",
                              method=method, model=model,
                              pixel_stderr=sphere_stderr)
        diffusion = est.maps        # the dipole's measured shortening bias widens the intervals (issue 16)
        diff_summary = grounded_summary(est.summary, cap.geometry.radius_mm, rad.eta)
        if reference is not None:
            ref_summary = _reference_summary(cap, reference, leds, scale, rad.eta, n_ref, normals, obj, maps,
                                             folder_maps, tile_rows or 256)
            notes.append("diffusion_reference_corrected: the sphere summary corrected by Monte Carlo reference "
                         "renders; the per-pixel maps are uncorrected")
    elif cap.relief is not None or maps.specular_normals is not None:
        diff_summary, relief_files, relief_fit = relief_branch(
            cap, maps, obj, Path(out_dir), fmt, relief_window_px, notes,
            seed_D_mm=None if seed_est is None else seed_est.D_mm, noise=noise)
    else:
        diff_summary = {"estimator": "grounded", "status": ["unknown"] * 3,
                        "reason": "no geometry ([object] shape = \"sphere\" with center_mm, radius_mm): a region "
                                  "without curvature information carries no information about a length, so D, "
                                  "sigma_s' and sigma_a are unknown (docs/gradients.md sec. 5)"}
        notes.append("diffusion unknown: no object geometry in capture.toml and no specular normals")
    seed_summary = None
    seed_maps: dict[str, Any] = {}
    if seed_est is not None:
        assert cap.seed is not None
        seed_summary = {"estimator": "seed D = k R_d/|n_z| (Zhu et al.)", "k_mm": cap.seed.k_mm,
                        "D_mm_median": channel_medians(seed_est.D_mm, ~seed_est.unknown),
                        "provenance": cap.seed.provenance,
                        "caveat": "k is an empirical length valid for the reference's geometry and material "
                                  "(docs/gradients.md sec. 6)"}
        if diffusion is not None:
            cmp = compare_estimates(seed_est, diffusion, region=obj)
            seed_summary["versus_grounded"] = {"median_ratio": cmp.median_ratio,
                                               "fraction_disagree": cmp.fraction_disagree, "rel_tol": cmp.rel_tol}
            from rig.estimate.folder_diffusion import sphere_seed_disagreement
            ratio_map, dis_map, dis_info = sphere_seed_disagreement(
                seed_est.D_mm, diff_summary, obj, albedo=maps.albedo, shortening=diffusion.shortening,
                albedo_stderr=None if noise is None else noise.albedo,
                shortening_stderr=None if noise is None else noise.shortening)
            seed_summary["versus_grounded"].update(dis_info)
            seed_maps = {"D_seed_ratio": ratio_map, "D_seed_disagree": dis_map}
        elif "versus_seed" in diff_summary:
            seed_summary["versus_relief"] = diff_summary["versus_seed"]
    alb_app, app_write = write_albedo_apparent(cap, maps, geo_normals, leds, n_ref, Path(out_dir), fmt)
    summary: dict[str, Any] = {
        "capture": str(cap.folder), "name": cap.name, "out_dir": str(Path(out_dir)), "format": fmt,
        "mode": "ideal" if cap.leds.ideal else "leds", "eta": rad.eta, "image_px": [W, H],
        "albedo_scale": scale, "albedo_scale_source": scale_prov["source"],
        "maps": {"known_pixels": [int(known[..., c].sum()) for c in range(3)],
                 "albedo_median": channel_medians(maps.albedo, known),
                 "R_d_median": channel_medians(maps.albedo, known),
                 "albedo_apparent_median": channel_medians(alb_app, known),
                 "albedo_definitions": {
                     "R_d": "albedo_diffuse file: the dipole's total diffuse reflectance, exit Fresnel divided out: "
                            "I_full = F_t(eta, n.v) E_full(n)/E_full(n_ref) R_d / albedo_scale",
                     "albedo_apparent": "albedo_apparent file: pi L / E = R_d F_t(eta, n.v) E_t/E (Ma et al. "
                                        "2007's diffuse albedo; a renderer's diffuse texture)"},
                 "diffuse_length_median": channel_medians(maps.diffuse_length(), known),
                 "specular": maps.specular_normals is not None},
        "diffusion": diff_summary, "seed": seed_summary, "notes": notes,
    }
    noise_files: dict[str, Path] = {}
    if noise is not None:
        from rig.estimate.folder_noise import noise_summary
        summary["noise"] = noise_summary(cap, noise, known)
        if scale_rel is not None:
            summary["noise"]["albedo_scale_rel_stderr"] = scale_rel.tolist()
    if ref_summary is not None:
        summary["diffusion_reference_corrected"] = ref_summary
    if cap.regions is not None:     # rig.estimate.folder_regions: the same summaries restricted to each labelled region
        summary["regions"] = region_summaries(cap.regions, maps, alb_app, diffusion=diffusion, relief_fit=relief_fit,
                                              radius_mm=radius, eta=rad.eta, unknown_reason=diff_summary.get("reason"),
                                              pixel_stderr=sphere_stderr)
    prov: dict[str, Any] = {
        "name": cap.name,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "software": {"name": "sssrig", "version": software_version(),
                     "python": sys.version.split()[0], "numpy": np.__version__},
        "capture": {"folder": str(cap.folder.resolve()), "file": CAPTURE_FILE, "sha256": cap.sha256,
                    "format_version": CAPTURE_FORMAT_VERSION},
        "frames": [{"file": _rel(f.file, cap.folder), "pattern": f.pattern, "polarization": f.polarization,
                    "exposure_s": f.exposure_s, "sha256": f.sha256, "format": f.source_format} for f in cap.frames],
        "leds": cap.leds.provenance(),
        "camera": cap.camera_spec,
        "radiometry": {"eta": rad.eta, "albedo_scale_per_s": scale, **scale_prov,
                       "saturation_level": rad.saturation_level, "dark_level": rad.dark_level,
                       "reference_normal": n_ref},
        "object": {"mask": None if cap.mask_file is None else
                   {"file": _rel(cap.mask_file, cap.folder), "sha256": sha256_file(cap.mask_file)},
                   "shape": "sphere" if cap.geometry else ("relief" if cap.relief is not None else "unknown"),
                   **({"center_mm": cap.geometry.center_mm, "radius_mm": cap.geometry.radius_mm}
                      if cap.geometry else {}), "regions": cap.regions and cap.regions.provenance(cap.folder)},
        "seed": None if cap.seed is None else {"k_mm": cap.seed.k_mm, **cap.seed.provenance},
        "noise": None if cap.noise is None else cap.noise.provenance(cap.folder),
        "parameters": {"format": fmt, "tile_rows": tile_rows or 256, "model": model,
                       "maps": "all" if select is None else list(select), "half": bool(half),
                       "reference": None if ref_summary is None else ref_summary["reference"]},
        "gradients": maps.provenance,
        "diffusion": None if diffusion is None else _strip_gradients(diffusion.provenance),
    }
    try:
        files = write_maps(out_dir, maps, diffusion, fmt=fmt, provenance=prov, seed=seed_est, preview=preview,
                           extra_sidecar={"summary": jsonable(summary)}, select=select, half=half)
    except ValueError as exc:
        raise ConfigError("--maps/--half", "maps", str(exc), select) from None
    except OSError as exc:
        raise CaptureError(f"{out_dir}: cannot write the maps ({exc})") from exc
    try:
        app_path = app_write()
        if noise is not None:
            from rig.estimate.folder_noise import write_noise_maps
            noise_files = write_noise_maps(noise, Path(out_dir), fmt)
        for name, a in seed_maps.items():       # the seed against the grounded sphere summary
            from rig.files.imageio import write_exr, write_float_tiff
            noise_files[name] = (write_exr if fmt == "exr" else write_float_tiff)(
                Path(out_dir) / (name + (".exr" if fmt == "exr" else ".tif")), a)
    except OSError as exc:
        raise CaptureError(f"{out_dir}: cannot write the maps ({exc})") from exc
    summary["files"] = {k: str(p) for k, p in {**files, **relief_files, "albedo_apparent": app_path,
                                                **noise_files}.items()}
    summary["seconds_maps"] = t_maps
    summary["seconds"] = time.perf_counter() - t0
    return jsonable(summary)
