"""Run the estimators on a session folder, read only through docs/session-format.md.

Radiometry: a frame's linear value v (white level = 1) is converted to radiance with the camera's
design response, L = v (white - black) / (gain x exposure); a cross-polarized frame holds half the
diffuse light (Ma et al. 2007), so diffuse radiance = 2 L.

With a calibration file (``rig calibrate``; ``estimate_session(calibration=...)``, or the one the session's
manifest records, ``rig capture --calibration``) the estimators use what it measured instead of the design
values, section by section (a missing section falls back to the design value, and ``inputs.calibration.used``
says which): frames black-corrected and linearized (``radiometry``), then resampled to the ideal pinhole
(``intrinsics``); the calibrated camera (``intrinsics`` + ``rig_frame`` pose); the LED rig (``rig_frame``
positions, ``led_directions``, ``gains``); the albedo scale (``radiometry``); the key light's gain (``gains``);
and the seed's D = k R_d / |n_z| (``seed_k``), reported beside the grounded gradient estimate.
"""
from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from drivers.camera.raw import load_linear

from rig.acquire.geometry import camera_from_dict
from rig.files.provenance import sha256_file
from rig.estimate.pixel_map import pixel_faces, sample_at_points
from rig.files.session import Session, SessionError

SATURATION = 0.98   # linear values at or above this fraction of white are masked
DARK_LEVEL = 0.01   # full-on signal (fraction of white) below which a pixel, or a whole channel's median, is dark


def _radiance_per_value(cam: dict[str, Any], exposure_s: float) -> float:
    return (cam["white_level_dn"] - cam["black_level_dn"]) / (cam["gain_dn_per_unit"] * exposure_s)



class SessionCalibration:
    """A calibration file as one session's estimators use it: which file (and how it was chosen), what it
    replaces, and the provenance each estimate records. Build with :func:`resolve_calibration`."""

    def __init__(self, cal: Any, source: str, sha256: str, manifest: dict[str, Any]) -> None:
        self.cal, self.source, self.sha256 = cal, source, sha256
        self.file = str(cal.path)
        self.recorded = manifest.get("calibration")
        cam = manifest["geometry"]["camera"]
        self.design_camera = camera_from_dict(cam)
        self._check(manifest)

    def _check(self, manifest: dict[str, Any]) -> None:
        from rig.files.calibration_store import CalibrationError

        rig_name = manifest.get("config", {}).get("name")
        if rig_name is not None and self.cal.doc.get("rig") != rig_name:
            raise CalibrationError(self.file, "rig", f"the session's rig ({rig_name!r}, manifest config.name)",
                                   self.cal.doc.get("rig"))
        if self.cal.has("intrinsics"):
            r = self.cal.result("intrinsics")
            want = (self.design_camera.width_px, self.design_camera.height_px)
            got = (int(r["width_px"]), int(r["height_px"]))
            if got != want:
                raise CalibrationError(self.file, "steps.intrinsics.result.width_px/height_px",
                                       f"{want[0]} x {want[1]} px (the session's camera)", f"{got[0]} x {got[1]} px")

    def has(self, section: str) -> bool:
        return self.cal.has(section)

    def revision(self, section: str) -> int:
        return int(self.cal.section(section)["revision"])

    def _used(self, section: str, what: str) -> str:
        if self.has(section):
            return f"calibrated ({section} revision {self.revision(section)})"
        return f"design values ({what}; the calibration has no {section} section)"

    # -- frames ---------------------------------------------------------------------------------------------
    def linearize(self, rgb: np.ndarray) -> np.ndarray:
        """``load_linear`` values -> black-corrected, linear values (unchanged without a radiometry section)."""
        return self.cal.linearizer()(rgb) if self.has("radiometry") else rgb

    def undistort(self, img: np.ndarray) -> np.ndarray:
        """A frame-shaped array resampled to the ideal pinhole of :meth:`camera` (unchanged without intrinsics)."""
        return self.cal.undistort(img) if self.has("intrinsics") else img

    # -- geometry -------------------------------------------------------------------------------------------
    def camera(self) -> Any:
        """The calibrated pinhole (intrinsics + rig-frame pose; design values for a missing section)."""
        from rig.files.camera_intrinsics import Intrinsics

        d = self.design_camera
        intr = self.cal.intrinsics() if self.has("intrinsics") else Intrinsics.from_pinhole(d)
        if self.has("rig_frame"):
            r = self.cal.result("rig_frame")["camera"]
            R, C = np.asarray(r["rotation"], float), np.asarray(r["center_mm"], float)
        else:
            R, C = d.R, d.C
        return intr.pinhole(R, C)

    def led_gain(self, led: int) -> tuple[np.ndarray, str]:
        """(gain (3,) of LED ``led``: true radiant intensity / design intensity, how it was obtained)."""
        if self.has("gains"):
            r = self.cal.result("gains")
            idx = [int(i) for i in r["led_indices"]]
            if led in idx:
                return (np.asarray(r["gains"], float)[idx.index(led)],
                        f"calibrated gain of LED {led} (gains revision {self.revision('gains')})")
            return np.ones(3), (f"design intensity: the gains step (revision {self.revision('gains')}) did not "
                                f"measure LED {led} (add it to [calibration.diffuse_sphere] leds)")
        return np.ones(3), "design intensity (the calibration has no gains section)"

    # -- provenance -----------------------------------------------------------------------------------------
    def provenance(self, used: dict[str, str]) -> dict[str, Any]:
        """``inputs.calibration`` of an estimate: ``cal.provenance()`` (file, revision, sections) plus the
        file's SHA-256, how it was chosen (``source``) and what this estimator took from it (``used``)."""
        out = {**self.cal.provenance(), "sha256": self.sha256, "source": self.source, "used": used}
        if self.source == "given" and isinstance(self.recorded, dict) and self.recorded.get("sha256") != self.sha256:
            out["manifest_calibration"] = self.recorded     # the session was captured with another file
        return out

    def radiometry_note(self, what: str) -> str:
        """``inputs.radiometry`` of an estimate that takes ``what`` from the radiometry section."""
        if self.has("radiometry"):
            return (f"calibrated: {self.file} revision {self.cal.doc['revision']} ({what} from radiometry revision "
                    f"{self.revision('radiometry')}; radiance in the camera config's design response, in which "
                    "the LED gains are expressed)")
        return (f"design values of the camera config ({self.file} revision {self.cal.doc['revision']} has no "
                "radiometry section)")

    def used_frames_camera(self) -> dict[str, str]:
        """``inputs.calibration.used`` entries for the frames and the camera."""
        return {"camera": ("intrinsics " + self._used("intrinsics", "config [camera]") + "; pose "
                           + self._used("rig_frame", "config [camera] position_mm, look_at_mm")),
                "frames": ("black level and linearity " + self._used("radiometry", "none") + "; undistorted "
                           + self._used("intrinsics", "no distortion"))}


def resolve_calibration(session: Session, calibration: Any = None) -> SessionCalibration | None:
    """The calibration a session's estimates use: ``calibration`` (a path or a loaded
    ``rig.files.calibration_store.Calibration``) if given; else the file the manifest records (``rig capture
    --calibration``), which must still have the recorded SHA-256; else None (design values).
    ``calibration=False`` forces the design values even when the manifest records a file."""
    from rig.files.calibration_store import Calibration, load_calibration

    if calibration is False:
        return None
    manifest = session.manifest
    mpath = session.root / "manifest.json"
    if calibration is not None:
        cal = calibration if isinstance(calibration, Calibration) else load_calibration(calibration)
        return SessionCalibration(cal, "given", sha256_file(Path(cal.path)), manifest)
    rec = manifest.get("calibration")
    if rec is None:
        return None
    if not isinstance(rec, dict) or not isinstance(rec.get("file"), str) or not isinstance(rec.get("sha256"), str):
        raise SessionError(f"{mpath}: field 'calibration': expected an object with 'file' and 'sha256' strings, "
                           f"got {rec!r}")
    path = Path(rec["file"])
    if not path.is_file():
        raise SessionError(f"{mpath}: field 'calibration.file': the calibration file {path} the session was "
                           "captured with is missing; give --calibration FILE (or restore it)")
    now = sha256_file(path)
    if now != rec["sha256"]:
        raise SessionError(f"{path}: the calibration file changed since the session was captured (manifest "
                           f"{mpath} field 'calibration.sha256': recorded sha256 {rec['sha256']}, file now has "
                           f"sha256 {now}); give --calibration {path} to use it as it is now")
    return SessionCalibration(load_calibration(path), "manifest", now, manifest)


class _Frames:
    """Loads each session frame once, ambient-subtracted, in radiance units, with a saturation mask.

    With a calibration (``cal``), frames are black-corrected and linearized, then undistorted to the
    calibrated pinhole; the saturation mask is taken on the raw values and undistorted with them (a pixel
    touched by a saturated one is saturated), the variance comes from the sensor's noise model of the raw
    values (the linearization's slope, within a few percent of 1, is neglected)."""

    def __init__(self, session: Session, cal: SessionCalibration | None = None) -> None:
        self.session = session
        self.cal = cal
        self.cam = session.manifest["config"]["camera"]
        self._cache: dict[tuple[str, str], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def has(self, pattern: str, pol: str = "cross") -> bool:
        return any(r.pattern == pattern and r.polarization == pol for r in self.session.frames())

    def _load(self, pattern: str, pol: str = "cross") -> tuple[np.ndarray, float]:
        rec = self.session.frame(pattern, pol)
        rgb, _ = load_linear(self.session.root / rec.file)
        return rgb.astype(np.float64), rec.exposure_s

    def raw(self, pattern: str, pol: str = "cross") -> tuple[np.ndarray, float]:
        """(frame, exposure_s): linear values (white = 1); calibrated: linearized and undistorted."""
        rgb, exp = self._load(pattern, pol)
        if self.cal is not None:
            rgb = self.cal.undistort(self.cal.linearize(rgb))
        return rgb, exp

    def _variance(self, rgb: np.ndarray) -> np.ndarray:
        """Poisson-Gaussian variance of linear values (white = 1) from the sensor's noise model.

        Each RGB value is the mean of the CFA cell's photosites of that colour (two for green)."""
        span = self.cam["white_level_dn"] - self.cam["black_level_dn"]
        dn = np.maximum(rgb, 0.0) * span
        var_dn = dn / self.cam["electrons_per_dn"] + self.cam["read_noise_dn"] ** 2
        var_dn = var_dn / np.array([1.0, 2.0, 1.0])
        return var_dn / span ** 2

    def radiance(self, pattern: str, pol: str = "cross") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(radiance, its variance, saturated mask), each (H, W, 3), of the ambient-subtracted frame."""
        key = (pattern, pol)
        if key not in self._cache:
            if self.cal is None:
                rgb, exp = self.raw(pattern, pol)
                saturated = rgb >= SATURATION
                var = self._variance(rgb)
                if self.has("ambient", pol):
                    amb, amb_exp = self.raw("ambient", pol)
                    rgb = rgb - amb * (exp / amb_exp)
                    var = var + self._variance(amb) * (exp / amb_exp) ** 2
            else:
                rgb, exp = self._load(pattern, pol)
                saturated = rgb >= SATURATION
                var = self._variance(rgb)
                rgb = self.cal.linearize(rgb)
                if self.has("ambient", pol):
                    amb, amb_exp = self._load("ambient", pol)
                    var = var + self._variance(amb) * (exp / amb_exp) ** 2
                    rgb = rgb - self.cal.linearize(amb) * (exp / amb_exp)
                rgb, var = self.cal.undistort(rgb), self.cal.undistort(var)
                saturated = self.cal.undistort(saturated.astype(np.float64)) > 0
            k = _radiance_per_value(self.cam, exp)
            self._cache[key] = (rgb * k, var * k * k, saturated)
        return self._cache[key]


def requested_channels(manifest: dict[str, Any]) -> list[int]:
    """Indices (0..2) of the colour channels the session's request asked for (all three without a request).

    A channel not requested is dark in every pattern (rig/acquire/plan.py): it is not processed, and its
    parameters are reported as None ("not requested"), never fitted to darkness."""
    req = manifest.get("request") or {}
    names = [str(c).upper() for c in (req.get("channels") or "RGB")]
    return [i for i, c in enumerate("RGB") if c in names]


def roi_mask(manifest: dict[str, Any], shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: the pixels the session's request asks to process (``roi_px``; all without one)."""
    mask = np.ones(shape, bool)
    roi = (manifest.get("request") or {}).get("roi_px")
    if roi is not None:
        x0, y0, x1, y1 = (int(v) for v in roi)
        if x1 > shape[1] or y1 > shape[0]:
            raise SessionError(f"{manifest.get('name', 'session')}: request roi_px {list(roi)} reaches outside "
                               f"the {shape[1]}x{shape[0]} frames")
        mask[:] = False
        mask[y0:y1, x0:x1] = True
    return mask


def _expand_channels(values: Any, idx: list[int]) -> list[Any]:
    """Per-channel values of the requested channels -> a 3-list with None for the others."""
    out: list[Any] = [None, None, None]
    for j, i in enumerate(idx):
        v = values[j]
        out[i] = v.tolist() if isinstance(v, np.ndarray) else (v.item() if isinstance(v, np.generic) else v)
    return out


def _object_center(manifest: dict[str, Any], surveys: dict[str, Any]) -> np.ndarray:
    obj = manifest["config"]["object"]
    target = obj["survey_target"]
    if target not in surveys:
        raise SessionError(f"{manifest['name']}: no survey of the object's target {target!r} in the journal")
    return np.asarray(surveys[target]["xyz_mm"], float) - np.asarray(obj["target_offset_mm"], float)


def run_single_image(frames: _Frames, manifest: dict[str, Any], surveys: dict[str, Any], *,
                     method: str | None = None) -> dict[str, Any]:
    """Mukaigawa et al.'s single-image method on the key-light frame (estimation.single_image).

    ``method`` overrides ``[estimation] single_image_method`` (the report asks for ``"tikhonov"`` to get the
    binned profile R'(d) as data points). ``profile`` in the result holds the bins and values per channel
    (None for channels not requested)."""
    import trimesh

    from estimation.single_image import PointLights, estimate_single_image, patches_from_mesh

    t0 = time.perf_counter()
    cfg = manifest["config"]
    cal = frames.cal
    camera = camera_from_dict(manifest["geometry"]["camera"]) if cal is None else cal.camera()
    center = _object_center(manifest, surveys)
    key_led = manifest["geometry"].get("key_led")
    used: dict[str, str] = {}
    if "key_led" in surveys:
        light_pos = np.asarray(surveys["key_led"]["xyz_mm"], float)
        used["light_position"] = "session survey of 'key_led'"
    elif cal is not None and cal.has("rig_frame") and key_led is not None:
        light_pos = cal.cal.led_positions_mm()[int(key_led)]
        used["light_position"] = (f"calibrated position of LED {key_led} (rig_frame revision "
                                  f"{cal.revision('rig_frame')}; no survey of 'key_led' in the session)")
    else:
        raise SessionError(f"{manifest['name']}: no survey of the key light ('key_led') in the journal")
    peak = cfg["sphere"]["pattern_peak"]
    intensity = np.asarray(cfg["sphere"]["led_intensity"], float) * round(peak * 65535) / 65535
    if cal is not None:
        gain, used["light_intensity"] = (cal.led_gain(int(key_led)) if key_led is not None else
                                         (np.ones(3), "design intensity (the manifest names no key LED)"))
        intensity = intensity * gain
        used.update(cal.used_frames_camera())
    mesh = trimesh.creation.icosphere(subdivisions=cfg["estimation"]["single_image_subdivisions"],
                                      radius=cfg["object"]["radius_mm"])
    mesh.apply_translation(center)
    patches = patches_from_mesh(mesh, camera)
    img, var, sat = frames.radiance("key")
    faces = pixel_faces(mesh, camera)
    valid = ((faces >= 0) & roi_mask(manifest, faces.shape))[..., None] & ~sat   # outside the region: unobserved
    obs, sigma = sample_at_points(img, var, valid, camera, patches.centers_mm)
    obs[~patches.visible] = np.nan      # back faces project onto the image too: never observed
    obs *= 2.0     # cross-polarized: half the diffuse light
    sigma *= 2.0
    eta = float(cfg["estimation"]["eta"])
    ch = requested_channels(manifest)
    lights = PointLights(light_pos[None, :], intensity[None, ch])
    est_cfg = cfg["estimation"]
    model = est_cfg.get("single_image_model", "dipole-jensen")
    meth = method or est_cfg["single_image_method"]
    res = estimate_single_image(obs[:, ch], patches, lights, eta, method=meth, model=model, noise_sigma=sigma[:, ch])
    seconds = time.perf_counter() - t0
    comparison: dict[str, Any] = {}
    if est_cfg.get("compare_models", True) and method is None:
        from estimation.single_image import MODELS_ALL

        for other in MODELS_ALL:
            t1 = time.perf_counter()
            r = res if other == model else estimate_single_image(obs[:, ch], patches, lights, eta, method=meth,
                                                                  model=other, noise_sigma=sigma[:, ch])
            comparison[other] = {
                "success": bool(r), "message": r.message, "channels": ["RGB"[i] for i in ch],
                "seconds": seconds if other == model else time.perf_counter() - t1,
                "sigma_s_prime_per_mm": _expand_channels(r.sigma_s_prime_per_mm, ch) if r else None,
                "sigma_a_per_mm": _expand_channels(r.sigma_a_per_mm, ch) if r else None,
                "model_bias": r.extra.get("model_bias")}
    out: dict[str, Any] = {"estimator": "single-image", "success": bool(res), "message": res.message,
                           "method": res.method, "model": res.model, "eta": eta, "seconds": seconds,
                           "inputs": {"frame": manifest_frame(frames, "key"), "light_mm": light_pos.tolist(),
                                      "object_center_mm": center.tolist(), "patches": len(mesh.faces),
                                      "observed_patches": int(np.isfinite(obs[:, 0]).sum()),
                                      "radiometry": "design values of the camera config (uncalibrated)"}}
    if cal is not None:
        out["inputs"].update(radiometry=cal.radiometry_note("black level and linearity"),
                             light_intensity=intensity.tolist(),
                             calibration=cal.provenance(used))
    out["channels"] = ["RGB"[i] for i in ch]
    if comparison:
        out["models"] = comparison
    if res:
        out.update({key: _expand_channels(getattr(res, key), ch) for key in (
            "sigma_s_prime_per_mm", "sigma_a_per_mm", "R_d", "l_d_mm", "D_mm", "sigma_s_prime_ci_per_mm",
            "sigma_a_ci_per_mm")})
        out.update({
            "sigma_a_identifiable": _expand_channels(list(res.sigma_a_identifiable_per_channel), ch),
            "identifiability_reason": res.identifiability_reason,
            "profile": None if res.profile_bins_mm is None else {
                "bins_mm": np.asarray(res.profile_bins_mm).tolist(),
                "values": [_expand_channels(row, ch) for row in np.asarray(res.profile_values)]},
            "diagnostics": {"condition_number": res.diagnostics.condition_number,
                            "relative_residual_rms": res.diagnostics.relative_residual_rms,
                            "notes": list(res.diagnostics.notes)}})
    return out


def run_gradients(frames: _Frames, manifest: dict[str, Any], surveys: dict[str, Any]) -> dict[str, Any]:
    """Polarized spherical gradients (Ma et al. 2007) -> albedo and diffuse normals per channel, then the
    diffusion parameters from the blur of the normal field on the known sphere (Zhu et al., grounded form;
    estimation.gradients and estimation.diffusion)."""
    from estimation.diffusion import estimate_sphere, sphere_geometry
    from estimation.gradients import LedRig, albedo_scale_from_radiometry, compute_maps
    from estimation.sphere_bias import widen_sphere_summary

    from rig.estimate.folder_diffusion import dark_channels, mark_channels_unknown

    from rig.acquire.patterns import pattern_values

    t0 = time.perf_counter()
    cfg = manifest["config"]
    geo = manifest["geometry"]
    cal = frames.cal
    camera = camera_from_dict(geo["camera"]) if cal is None else cal.camera()
    center = _object_center(manifest, surveys)
    radius = float(cfg["object"]["radius_mm"])
    eta = float(cfg["estimation"]["eta"])
    dirs = np.asarray(geo["led_directions"], float)     # the patterns were computed from the design layout
    peak_q = round(cfg["sphere"]["pattern_peak"] * 65535) / 65535
    names = [p for p in ("full", "x", "y", "z", "x_c", "y_c", "z_c") if frames.has(p)]
    displayed = {p: np.round(pattern_values(p, dirs) * peak_q * 65535) / 65535 for p in names}
    intensity = np.broadcast_to(np.asarray(cfg["sphere"]["led_intensity"], float), dirs.shape)
    if cal is None:
        leds = LedRig.from_positions(geo["led_positions_mm"], intensity, patterns=displayed)
    else:
        leds = cal.cal.led_rig(geo["led_positions_mm"], np.asarray(cfg["sphere"]["led_intensity"], float),
                               patterns=displayed)
    raw = {}
    exposures = set()
    for p in ["ambient", *names]:
        rgb, exp = frames.raw(p)
        raw[(p, "cross")] = rgb
        exposures.add(exp)
    if len(exposures) != 1:
        raise SessionError(f"{manifest['name']}: gradient frames must share one exposure, got {sorted(exposures)}")
    exposure = exposures.pop()
    used: dict[str, str] = {}
    if cal is not None and cal.has("radiometry"):
        scale = _calibrated_albedo_scale(cal, exposure, peak_q)
        used["albedo_scale"] = (f"calibrated (radiometry revision {cal.revision('radiometry')}) at "
                                f"{exposure:g} s")
    else:
        value_per_radiance = 1.0 / _radiance_per_value(frames.cam, exposure)
        scale = albedo_scale_from_radiometry(np.full(3, value_per_radiance), leds, eta=eta)
        if cal is not None:
            used["albedo_scale"] = "design camera response (the calibration has no radiometry section)"
    if cal is not None:
        used.update(cal.used_frames_camera())
        n_dir = len(cal.cal.result("led_directions")["led_indices"]) if cal.has("led_directions") else 0
        n_gain = len(cal.cal.result("gains")["led_indices"]) if cal.has("gains") else 0
        used.update(led_positions=cal._used("rig_frame", "geodesic layout of [sphere]"),
                    led_directions=(f"mirror ball for {n_dir} LEDs (led_directions revision "
                                    f"{cal.revision('led_directions')}), from the positions elsewhere" if n_dir else
                                    "from the LED positions (the calibration has no led_directions section)"),
                    led_gains=(f"calibrated for {n_gain} LEDs (gains revision {cal.revision('gains')}), design "
                               "led_intensity elsewhere" if n_gain else
                               "design led_intensity (the calibration has no gains section)"))
    normals, view, hit = sphere_geometry(camera, center, radius)
    hit = hit & roi_mask(manifest, hit.shape)       # pixels outside the requested region: not processed
    maps = compute_maps(raw, albedo_scale=scale, leds=leds, eta=eta, view_dirs=view,
                        geometry_normals=np.where(hit[..., None], normals, 0.0), object_mask=hit,
                        surface_center_mm=center, surface_radius_mm=radius)
    # the capture folder's two honesty rules (issue 16): a channel whose full-on signal over the object is
    # within its noise is unknown as a whole (the per-pixel dark test alone keeps its noise-high pixels and
    # reports a biased albedo), and the dipole's measured shortening bias widens the sphere intervals
    notes: list[str] = []
    dark, dark_info = dark_channels(raw, {k: exposure for k in raw}, hit, DARK_LEVEL)
    dark = [d and c in requested_channels(manifest) for c, d in enumerate(dark)]   # unrequested: None anyway
    if any(dark):
        mark_channels_unknown(maps, dark)
        notes.append("channel(s) " + ", ".join("RGB"[c] for c in range(3) if dark[c]) + " unknown: the median "
                     f"full-on signal over the object is below max({DARK_LEVEL:g}, its pixel noise) "
                     f"({dark_info['median_full_signal']} vs noise {dark_info['pixel_noise']})")
    t_maps = time.perf_counter() - t0
    est = estimate_sphere(maps, radius_mm=radius, true_normals=normals)
    summ = est.summary
    summary = widen_sphere_summary(summ.as_dict(), radius, eta)
    status = list(summary["status"])
    seed = None
    if cal is not None and cal.has("seed_k"):
        seed = _seed_beside(maps, est, normals, hit, cal, requested_channels(manifest))
        used["seed_k"] = f"calibrated (seed_k revision {cal.revision('seed_k')})"
    seconds = time.perf_counter() - t0
    ch = requested_channels(manifest)
    out: dict[str, Any] = {
        "estimator": "gradients", "success": any(status[c] != "unknown" for c in ch),
        "message": "ok" if any(status[c] != "unknown" for c in ch) else "no usable pixels",
        "method": f"spherical gradients + normal-field blur on a sphere ({summ.method})",
        "eta": eta, "seconds": seconds, "seconds_maps": t_maps, "status": status, "notes": notes,
        "model_shortening_bias": summary.get("model_shortening_bias"),
        "n_pixels": summ.n_pixels.tolist(),
        "inputs": {"frames": [frames.session.frame(p, "cross").file for p in ["ambient", *names]],
                   "object_center_mm": center.tolist(), "radius_mm": radius,
                   "albedo_scale": scale.tolist(),
                   "radiometry": "design values of the camera and LED config (uncalibrated)"}}
    out["channels"] = ["RGB"[i] for i in ch]
    for key in ("R_d", "sigma_s_prime_per_mm", "sigma_a_per_mm", "D_mm", "l_d_mm"):
        if key in summary:
            vals = np.array(summary[key]["value"], dtype=float)
            intervals = np.array(summary[key]["interval"], dtype=float)
            out[key] = _expand_channels(vals[ch], ch)
            out[key + "_interval"] = _expand_channels(intervals[ch], ch)
    if cal is not None:
        out["inputs"].update(radiometry=cal.radiometry_note("black level, linearity and albedo scale"),
                             calibration=cal.provenance(used))
    if seed is not None:
        out["seed"] = seed
    return out


def _calibrated_albedo_scale(cal: SessionCalibration, exposure_s: float, drive: float) -> np.ndarray:
    """The calibration's albedo scale for frames of ``exposure_s`` whose full pattern shows ``drive``: the
    radiometry step's reference frame was taken at ``pattern_drive`` (when recorded), and the albedo scale is
    inversely proportional to the full pattern's irradiance."""
    scale = np.asarray(cal.cal.albedo_scale(exposure_s), float)
    cal_drive = cal.cal.result("radiometry").get("pattern_drive")
    if cal_drive is not None:
        scale = scale * float(cal_drive) / float(drive)
    return scale


def _seed_beside(maps: Any, est: Any, normals: np.ndarray, hit: np.ndarray, cal: SessionCalibration,
                 ch: list[int]) -> dict[str, Any]:
    """The seed's D = k R_d / |n_z| (``estimation.diffusion.diffusion_seed`` with the calibrated k) over the
    grounded estimate's region, and how it compares with the grounded D (``compare_estimates``)."""
    from scipy.ndimage import binary_erosion

    from estimation.diffusion import compare_estimates, diffusion_seed

    region = binary_erosion(hit, iterations=2)       # as estimate_sphere's default region
    k = cal.cal.k_mm()
    sd = diffusion_seed(maps, k, cal.cal.provenance(), true_normals=normals)
    D = np.full(3, np.nan)
    n = np.zeros(3, int)
    for c in range(3):
        m = region & ~sd.unknown[..., c]
        n[c] = int(m.sum())
        if n[c]:
            D[c] = float(np.median(sd.D_mm[..., c][m]))
    out: dict[str, Any] = {"estimator": "seed D = k R_d / |n_z| (Zhu et al.; estimation.diffusion.diffusion_seed)",
                           "k_mm": _expand_channels(k[ch], ch), "D_mm": _expand_channels(D[ch], ch),
                           "n_pixels": _expand_channels(n[ch], ch),
                           "k_reference": cal.cal.result("seed_k").get("reference")}
    try:
        cmp = compare_estimates(sd, est.maps, region=region)
    except (ValueError, AttributeError, TypeError) as exc:     # the grounded maps lack what the comparison needs
        out["comparison"] = f"not available ({type(exc).__name__}: {exc})"
    else:
        out["comparison"] = {"median_ratio_to_grounded": _expand_channels(np.asarray(cmp.median_ratio)[ch], ch),
                             "fraction_disagree": _expand_channels(np.asarray(cmp.fraction_disagree)[ch], ch),
                             "rel_tol": cmp.rel_tol}
    return out


def manifest_frame(frames: _Frames, pattern: str, pol: str = "cross") -> str:
    return frames.session.frame(pattern, pol).file


def _rows(name: str, est: dict[str, Any], truth: dict[str, Any] | None) -> list[dict[str, Any]]:
    rows = []
    if not est.get("success"):
        return [{"quantity": f"{name}: failed ({est.get('message')})", "truth": None, "estimate": None,
                 "error": None, "seconds": est.get("seconds", 0.0)}]
    t_ssp = t_sa = None
    if truth:
        t_ssp, t_sa = truth["sigma_s_prime_per_mm"], truth["sigma_a_per_mm"]
    for key, label, tvals in (("R_d", "R_d", None), ("sigma_s_prime_per_mm", "sigma_s' [1/mm]", t_ssp),
                              ("sigma_a_per_mm", "sigma_a [1/mm]", t_sa), ("D_mm", "D [mm]", None)):
        vals = est.get(key)
        if vals is None:
            continue
        if truth and tvals is None:
            tvals = _derived_truth(key, truth)
        for c, ch in enumerate("RGB"):
            if ch not in est.get("channels", "RGB"):
                continue        # not requested: not captured, not processed
            v = None if vals[c] is None or not np.isfinite(vals[c]) else float(vals[c])
            t = None if tvals is None else float(tvals[c])
            err = None if (v is None or t is None or t == 0) else (v - t) / t
            rows.append({"quantity": f"{name} {label} {ch}", "truth": t, "estimate": v, "error": err,
                         "seconds": est["seconds"]})
    return rows


def _model_rows(est: dict[str, Any], truth: dict[str, Any] | None) -> list[dict[str, Any]]:
    """The single-image fit of every profile model side by side: one row per (quantity, channel) with the truth
    and, per model, the estimate and its relative error (None where a model failed or has no truth)."""
    models = est.get("models") or {}
    rows: list[dict[str, Any]] = []
    for key, label in (("sigma_s_prime_per_mm", "sigma_s' [1/mm]"), ("sigma_a_per_mm", "sigma_a [1/mm]")):
        tvals = None if not truth else truth[key]
        for c, ch in enumerate("RGB"):
            if ch not in est.get("channels", "RGB"):
                continue
            t = None if tvals is None else float(tvals[c])
            per: dict[str, Any] = {}
            for name, m in models.items():
                vals = m.get(key)
                v = None if not vals or vals[c] is None or not np.isfinite(vals[c]) else float(vals[c])
                per[name] = {"estimate": v, "error": None if (v is None or not t) else (v - t) / t,
                             "seconds": m.get("seconds")}
            rows.append({"quantity": f"{label} {ch}", "truth": t, "models": per})
    return rows


def _derived_truth(key: str, truth: dict[str, Any]) -> list[float] | None:
    from estimation.dipole import diffusion_coefficient_mm, total_diffuse_reflectance
    ssp = np.asarray(truth["sigma_s_prime_per_mm"], float)
    sa = np.asarray(truth["sigma_a_per_mm"], float)
    if key == "R_d":
        return list(total_diffuse_reflectance(ssp, sa, truth["eta"]))
    if key == "D_mm":
        return list(diffusion_coefficient_mm(ssp, sa))
    return None


def estimate_session(root: str | Path, *, calibration: str | os.PathLike[str] | Any = None,
                     log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run every estimator the session has frames for; write estimates/*.json; return table rows.

    ``calibration``: a calibration file (``rig calibrate``) to use; by default the one the manifest records
    (``rig capture --calibration``; its SHA-256 must match), else the design values; ``False``: the design
    values regardless (:func:`resolve_calibration`)."""
    say = log or (lambda m: None)
    session = Session.open(root)
    manifest = session.manifest
    truth = manifest.get("truth")
    surveys = session.surveys()
    cal = resolve_calibration(session, calibration)
    if cal is not None:
        say(f"calibration {cal.file} (revision {cal.cal.doc['revision']}, {cal.source}): "
            + ", ".join(sorted(cal.cal.doc["steps"])))
    frames = _Frames(session, cal)
    results: dict[str, Any] = {}
    rows: list[dict[str, Any]] = []
    notes: list[str] = []
    if frames.has("x"):
        say("gradients estimate: maps and diffusion ...")
        est = run_gradients(frames, manifest, surveys)
        session.write_estimate("gradients", est)
        say(f"gradients estimate: {est['seconds']:.2f} s")
        results["gradients"] = est
        rows += _rows("gradients", est, truth)
    if frames.has("key"):
        say("single-image estimate: fitting every profile model ...")
        est = run_single_image(frames, manifest, surveys)
        session.write_estimate("single-image", est)
        say(f"single-image estimate: {est['seconds']:.2f} s")
        results["single-image"] = est
        rows += _rows("single-image", est, truth)
        model_rows = _model_rows(est, truth)
        if model_rows and truth:
            renderer = truth.get("renderer", "the Jensen dipole (fast renderer)")
            why = ("the model that renderer uses is favoured here (Monte Carlo frames: render = \"mc\" in [scene])"
                   if "dipole" in renderer else
                   "every flat-surface model is biased by the sphere's curvature at this size (docs/model-error.md)")
            notes.append(f"single-image models: the simulated frames were rendered with {renderer}; {why}")
        if est.get("success") and not all(v for v in est["sigma_a_identifiable"] if v is not None):
            notes.append("single-image: sigma_a not identifiable in some channels; "
                         + est.get("identifiability_reason", ""))
        if cal is not None and "light_intensity" in est.get("inputs", {}).get("calibration", {}).get("used", {}):
            li = est["inputs"]["calibration"]["used"]["light_intensity"]
            if li.startswith("design"):
                notes.append(f"single-image: key light at {li}")
    if cal is not None:
        notes.append(f"calibrated with {cal.file} revision {cal.cal.doc['revision']} ({cal.source})")
    out: dict[str, Any] = {"rows": rows, "notes": notes, "estimates": results}
    if frames.has("key") and model_rows:
        out["model_rows"] = model_rows
    return out


def format_rows(result: dict[str, Any]) -> str:
    """The table of :func:`estimate_session`'s rows (quantity, truth, estimate, error, seconds; 4 significant
    digits), the single-image model comparison and the notes."""
    head = f"{'quantity':<34} {'truth':>10} {'estimate':>10} {'error':>9} {'seconds':>8}"
    lines = [head, "-" * len(head)]
    for r in result.get("rows", []):
        truth = "-" if r["truth"] is None else f"{r['truth']:.4g}"
        est = "unknown" if r["estimate"] is None else f"{r['estimate']:.4g}"
        err = "-" if r["error"] is None else f"{100 * r['error']:+.1f}%"
        lines.append(f"{r['quantity']:<34} {truth:>10} {est:>10} {err:>9} {r['seconds']:>8.2f}")
    lines.append("")
    model_rows = result.get("model_rows") or []
    if model_rows:
        names = list(model_rows[0]["models"])
        lines.append("single-image, every profile model (estimate, error vs truth):")
        head2 = f"{'quantity':<20} {'truth':>9} " + " ".join(f"{n:>22}" for n in names)
        lines += [head2, "-" * len(head2)]
        for r in model_rows:
            truth = "-" if r["truth"] is None else f"{r['truth']:.4g}"
            cells = []
            for n in names:
                m = r["models"][n]
                if m["estimate"] is None:
                    cells.append(f"{'failed':>22}")
                else:
                    err = "" if m["error"] is None else f" ({100 * m['error']:+.1f}%)"
                    cells.append(f"{m['estimate']:.4g}{err}".rjust(22))
            lines.append(f"{r['quantity']:<20} {truth:>9} " + " ".join(cells))
        lines.append("")
    for note in result.get("notes", []):
        lines.append(f"note: {note}")
    return "\n".join(lines)
