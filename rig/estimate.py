"""Run the estimators on a session folder, read only through docs/session-format.md.

Radiometry: a frame's linear value v (white level = 1) is converted to radiance with the camera's
design response, L = v (white - black) / (gain x exposure); a cross-polarized frame holds half the
diffuse light (Ma et al. 2007), so diffuse radiance = 2 L. On a real rig these come from calibration.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from drivers.camera.raw import load_linear

from .geometry import camera_from_dict
from .session import Session, SessionError

SATURATION = 0.98   # linear values at or above this fraction of white are masked


def _radiance_per_value(cam: dict[str, Any], exposure_s: float) -> float:
    return (cam["white_level_dn"] - cam["black_level_dn"]) / (cam["gain_dn_per_unit"] * exposure_s)


class _Frames:
    """Loads each session frame once, ambient-subtracted, in radiance units, with a saturation mask."""

    def __init__(self, session: Session) -> None:
        self.session = session
        self.cam = session.manifest["config"]["camera"]
        self._cache: dict[tuple[str, str], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def has(self, pattern: str, pol: str = "cross") -> bool:
        return any(r.pattern == pattern and r.polarization == pol for r in self.session.frames())

    def raw(self, pattern: str, pol: str = "cross") -> tuple[np.ndarray, float]:
        rec = self.session.frame(pattern, pol)
        rgb, _ = load_linear(self.session.root / rec.file)
        return rgb.astype(np.float64), rec.exposure_s

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
            rgb, exp = self.raw(pattern, pol)
            saturated = rgb >= SATURATION
            var = self._variance(rgb)
            if self.has("ambient", pol):
                amb, amb_exp = self.raw("ambient", pol)
                rgb = rgb - amb * (exp / amb_exp)
                var = var + self._variance(amb) * (exp / amb_exp) ** 2
            k = _radiance_per_value(self.cam, exp)
            self._cache[key] = (rgb * k, var * k * k, saturated)
        return self._cache[key]


def requested_channels(manifest: dict[str, Any]) -> list[int]:
    """Indices (0..2) of the colour channels the session's request asked for (all three without a request).

    A channel not requested is dark in every pattern (rig/plan.py): it is not processed, and its
    parameters are reported as None ("not requested"), never fitted to darkness."""
    req = manifest.get("request") or {}
    names = [str(c).upper() for c in (req.get("channels") or "RGB")]
    return [i for i, c in enumerate("RGB") if c in names]


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


def pixel_faces(mesh, camera) -> np.ndarray:
    """Index of the mesh face seen by each pixel (H, W), -1 where no face covers the pixel centre.

    Front-facing faces are rasterized back to front (painter's order by centroid depth) into a face-ID
    buffer with OpenCV, at 1/256 px sub-pixel precision.
    """
    import cv2

    verts = np.asarray(mesh.vertices, float)
    faces = np.asarray(mesh.faces)
    uv, depth = camera.project(verts)
    centers = verts[faces].mean(axis=1)
    normals = np.asarray(mesh.face_normals, float)
    facing = np.sum(normals * (camera.C - centers), axis=1) > 0
    in_front = np.all(depth[faces] > 0, axis=1)
    idx = np.flatnonzero(facing & in_front)
    order = idx[np.argsort(-camera.project(centers[idx])[1])]      # far to near
    buf = np.full((camera.height_px, camera.width_px), -1, np.int32)
    shift = 8
    pts = np.round((uv[faces[order]] + 0.0) * (1 << shift)).astype(np.int32)   # pixel centres at integers
    for f, tri in zip(order, pts):
        cv2.fillConvexPoly(buf, tri, int(f), lineType=cv2.LINE_8, shift=shift)
    return buf


def sample_at_points(img: np.ndarray, var: np.ndarray, valid: np.ndarray, camera, points_mm: np.ndarray,
                      window_px: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Mean of valid pixels in a ``window_px`` square around each point's projection (bilinear between
    window centres), and the standard deviation of that mean. A symmetric window keeps the sampling
    centred on the point, so the radiance gradient across a patch does not bias the value (averaging all
    pixels of a face does: its pixel centroid is not the face centre). NaN where any pixel of the window
    is invalid (background, saturated, off-frame)."""
    from scipy.ndimage import map_coordinates, uniform_filter

    uv, z = camera.project(points_mm)
    n = window_px * window_px
    obs = np.full((len(points_mm), img.shape[2]), np.nan)
    sigma = np.full_like(obs, np.nan)
    for c in range(img.shape[2]):
        m = valid[..., c].astype(float)
        den = uniform_filter(m, window_px, mode="constant")
        mean = uniform_filter(img[..., c] * m, window_px, mode="constant") / np.maximum(den, 1e-12)
        vmean = uniform_filter(var[..., c] * m, window_px, mode="constant") / np.maximum(den, 1e-12) / n
        full = den > 1 - 1e-9
        mean[~full] = np.nan
        vmean[~full] = np.nan
        coords = [uv[:, 1], uv[:, 0]]
        obs[:, c] = map_coordinates(mean, coords, order=1, cval=np.nan)
        sigma[:, c] = np.sqrt(map_coordinates(vmean, coords, order=1, cval=np.nan))
    bad = ~(z > 0)
    obs[bad] = np.nan
    sigma[bad] = np.nan
    return obs, sigma


def run_single_image(frames: _Frames, manifest: dict[str, Any], surveys: dict[str, Any]) -> dict[str, Any]:
    """Mukaigawa et al.'s single-image method on the key-light frame (estimation.single_image)."""
    import trimesh

    from estimation.single_image import PointLights, estimate_single_image, patches_from_mesh

    t0 = time.perf_counter()
    cfg = manifest["config"]
    camera = camera_from_dict(manifest["geometry"]["camera"])
    center = _object_center(manifest, surveys)
    if "key_led" not in surveys:
        raise SessionError(f"{manifest['name']}: no survey of the key light ('key_led') in the journal")
    light_pos = np.asarray(surveys["key_led"]["xyz_mm"], float)
    peak = cfg["sphere"]["pattern_peak"]
    intensity = np.asarray(cfg["sphere"]["led_intensity"], float) * round(peak * 65535) / 65535
    mesh = trimesh.creation.icosphere(subdivisions=cfg["estimation"]["single_image_subdivisions"],
                                      radius=cfg["object"]["radius_mm"])
    mesh.apply_translation(center)
    patches = patches_from_mesh(mesh, camera)
    img, var, sat = frames.radiance("key")
    faces = pixel_faces(mesh, camera)
    obs, sigma = sample_at_points(img, var, (faces >= 0)[..., None] & ~sat, camera, patches.centers_mm)
    obs[~patches.visible] = np.nan      # back faces project onto the image too: never observed
    obs *= 2.0     # cross-polarized: half the diffuse light
    sigma *= 2.0
    eta = float(cfg["estimation"]["eta"])
    ch = requested_channels(manifest)
    res = estimate_single_image(obs[:, ch], patches, PointLights(light_pos[None, :], intensity[None, ch]), eta,
                                method=cfg["estimation"]["single_image_method"], noise_sigma=sigma[:, ch])
    seconds = time.perf_counter() - t0
    out: dict[str, Any] = {"estimator": "single-image", "success": bool(res), "message": res.message,
                           "method": res.method, "model": res.model, "eta": eta, "seconds": seconds,
                           "inputs": {"frame": manifest_frame(frames, "key"), "light_mm": light_pos.tolist(),
                                      "object_center_mm": center.tolist(), "patches": len(mesh.faces),
                                      "observed_patches": int(np.isfinite(obs[:, 0]).sum()),
                                      "radiometry": "design values of the camera config (uncalibrated)"}}
    out["channels"] = ["RGB"[i] for i in ch]
    if res:
        out.update({key: _expand_channels(getattr(res, key), ch) for key in (
            "sigma_s_prime_per_mm", "sigma_a_per_mm", "R_d", "l_d_mm", "D_mm", "sigma_s_prime_ci_per_mm",
            "sigma_a_ci_per_mm")})
        out.update({
            "sigma_a_identifiable": _expand_channels(list(res.sigma_a_identifiable_per_channel), ch),
            "identifiability_reason": res.identifiability_reason,
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

    from .patterns import pattern_values

    t0 = time.perf_counter()
    cfg = manifest["config"]
    geo = manifest["geometry"]
    camera = camera_from_dict(geo["camera"])
    center = _object_center(manifest, surveys)
    radius = float(cfg["object"]["radius_mm"])
    eta = float(cfg["estimation"]["eta"])
    dirs = np.asarray(geo["led_directions"], float)
    peak_q = round(cfg["sphere"]["pattern_peak"] * 65535) / 65535
    names = [p for p in ("full", "x", "y", "z", "x_c", "y_c", "z_c") if frames.has(p)]
    displayed = {p: np.round(pattern_values(p, dirs) * peak_q * 65535) / 65535 for p in names}
    intensity = np.broadcast_to(np.asarray(cfg["sphere"]["led_intensity"], float), dirs.shape)
    leds = LedRig.from_positions(geo["led_positions_mm"], intensity, patterns=displayed)
    raw = {}
    exposures = set()
    for p in ["ambient", *names]:
        rgb, exp = frames.raw(p)
        raw[(p, "cross")] = rgb
        exposures.add(exp)
    if len(exposures) != 1:
        raise SessionError(f"{manifest['name']}: gradient frames must share one exposure, got {sorted(exposures)}")
    exposure = exposures.pop()
    value_per_radiance = 1.0 / _radiance_per_value(frames.cam, exposure)
    scale = albedo_scale_from_radiometry(np.full(3, value_per_radiance), leds, eta=eta)
    normals, view, hit = sphere_geometry(camera, center, radius)
    maps = compute_maps(raw, albedo_scale=scale, leds=leds, eta=eta, view_dirs=view,
                        geometry_normals=np.where(hit[..., None], normals, 0.0), object_mask=hit,
                        surface_center_mm=center, surface_radius_mm=radius)
    t_maps = time.perf_counter() - t0
    est = estimate_sphere(maps, radius_mm=radius, true_normals=normals)
    summ = est.summary
    seconds = time.perf_counter() - t0
    out: dict[str, Any] = {
        "estimator": "gradients", "success": any(st != "unknown" for st in summ.status),
        "message": "ok" if any(st != "unknown" for st in summ.status) else "no usable pixels",
        "method": f"spherical gradients + normal-field blur on a sphere ({summ.method})",
        "eta": eta, "seconds": seconds, "seconds_maps": t_maps, "status": list(summ.status),
        "n_pixels": summ.n_pixels.tolist(),
        "inputs": {"frames": [frames.session.frame(p, "cross").file for p in ["ambient", *names]],
                   "object_center_mm": center.tolist(), "radius_mm": radius,
                   "albedo_scale": scale.tolist(),
                   "radiometry": "design values of the camera and LED config (uncalibrated)"}}
    ch = requested_channels(manifest)
    out["channels"] = ["RGB"[i] for i in ch]
    for key, name in (("R_d", "R_d"), ("sigma_s_prime_per_mm", "sigma_s_prime_per_mm"),
                      ("sigma_a_per_mm", "sigma_a_per_mm"), ("D_mm", "D_mm"), ("l_d_mm", "l_d_mm")):
        if name in summ.params:
            vals, intervals = np.asarray(summ.params[name].value), np.asarray(summ.params[name].interval)
            out[key] = _expand_channels(vals[ch], ch)
            out[key + "_interval"] = _expand_channels(intervals[ch], ch)
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


def _derived_truth(key: str, truth: dict[str, Any]) -> list[float] | None:
    from estimation.dipole import diffusion_coefficient_mm, total_diffuse_reflectance
    ssp = np.asarray(truth["sigma_s_prime_per_mm"], float)
    sa = np.asarray(truth["sigma_a_per_mm"], float)
    if key == "R_d":
        return list(total_diffuse_reflectance(ssp, sa, truth["eta"]))
    if key == "D_mm":
        return list(diffusion_coefficient_mm(ssp, sa))
    return None


def estimate_session(root: str | Path, *, log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run every estimator the session has frames for; write estimates/*.json; return table rows."""
    say = log or (lambda m: None)
    session = Session.open(root)
    manifest = session.manifest
    truth = manifest.get("truth")
    surveys = session.surveys()
    frames = _Frames(session)
    results: dict[str, Any] = {}
    rows: list[dict[str, Any]] = []
    notes: list[str] = []
    if frames.has("x"):
        est = run_gradients(frames, manifest, surveys)
        session.write_estimate("gradients", est)
        say(f"gradients estimate: {est['seconds']:.2f} s")
        results["gradients"] = est
        rows += _rows("gradients", est, truth)
    if frames.has("key"):
        est = run_single_image(frames, manifest, surveys)
        session.write_estimate("single-image", est)
        say(f"single-image estimate: {est['seconds']:.2f} s")
        results["single-image"] = est
        rows += _rows("single-image", est, truth)
        if est.get("success") and not all(v for v in est["sigma_a_identifiable"] if v is not None):
            notes.append("single-image: sigma_a not identifiable in some channels; "
                         + est.get("identifiability_reason", ""))
    return {"rows": rows, "notes": notes, "estimates": results}
