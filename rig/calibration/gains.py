"""Step 3b: per-LED, per-channel gains from a diffuse (Lambertian) sphere of known reflectance.

Captures: the diffuse sphere (a Spectralon sphere or a matte-painted ball of known reflectance rho) at the
sphere's centre: one cross-polarized frame with every LED on (its outline), a cross-polarized ambient frame, and
one cross-polarized frame per LED lit alone.

Computes: the sphere's centre from its silhouette (known radius, calibrated camera pose); for every pixel on the
sphere its surface point p and normal n; for each LED l the predicted value of a unit-gain LED,
P_l(p) = k x (1/2) x rho/pi x I_design max(0, n.w_l)/|x_l - p|^2 (k: the camera's design value per unit radiance
at the frame's exposure, 1/2: the analyzer passes half the depolarized diffuse light; I_design the config's
``led_intensity`` times the drive the pattern displayed, ``pattern_peak`` quantized to 16 bits), with the LED position
x_l from the rig-frame step (direction from the mirror ball where measured); and the gain per channel as the
least-squares ratio g = sum V P / sum P^2 over pixels away from the outline and the terminator
(n.w_l >= ``min_cos``). g is the LED's true radiant intensity over the design intensity (in units of the design
camera response; the absolute scale is set by the radiometry step's reference target).
"""
from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from estimation.camera import intersect_sphere

from rig.calibration.capture import (Captured, Shot, design_irradiance, design_value_per_radiance, displayed_drive,
                                     exposure_for)
from rig.calibration.common import angle_deg, split_error
from rig.calibration.context import StepContext, StepOutput
from rig.calibration.led_directions import _spread, ball_in_rig

SECTION = "gains"
FloatArray = npt.NDArray[np.float64]

__all__ = ["SECTION", "shots", "compute", "compare", "lit_leds", "fit_gain"]


def lit_leds(led_positions_mm: npt.ArrayLike, center_mm: npt.ArrayLike, camera_center_mm: npt.ArrayLike,
             max_angle_deg: float = 120.0) -> list[int]:
    """LEDs lighting enough of the sphere's camera-facing side: within ``max_angle_deg`` of the camera as seen
    from the sphere's centre."""
    c = np.asarray(center_mm, float)
    to_cam = np.asarray(camera_center_mm, float) - c
    to_led = np.asarray(led_positions_mm, float) - c
    return [int(i) for i in np.flatnonzero(angle_deg(to_led, to_cam[None, :]) <= max_angle_deg)]


def _leds(ctx: StepContext) -> list[int]:
    d = ctx.settings.diffuse_sphere
    n = len(ctx.geometry.led_positions_mm)
    if d.leds:
        bad = [i for i in d.leds if not 0 <= i < n]
        if bad:
            raise ValueError(f"calibration.diffuse_sphere.leds: LED indices {bad} outside [0, {n})")
        return list(d.leds)
    cand = lit_leds(ctx.geometry.led_positions_mm, d.center_mm, ctx.geometry.camera.C)
    return _spread(ctx.geometry.led_directions, cand, d.count)


def shots(ctx: StepContext) -> list[Shot]:
    d, cfg, geo = ctx.settings.diffuse_sphere, ctx.config, ctx.geometry
    c = np.asarray(d.center_mm, float)
    to_cam = geo.camera.C - c
    to_cam /= np.linalg.norm(to_cam)
    rho = float(np.mean(d.albedo))
    e_full = design_irradiance(cfg, c + d.radius_mm * to_cam, to_cam, geometry=geo)
    t_sil = exposure_for(cfg, 0.5 * rho / np.pi * e_full, d.fraction)
    inten = float(np.mean(cfg.sphere.led_intensity)) * displayed_drive(cfg)
    leds = _leds(ctx)
    dist = np.linalg.norm(geo.led_positions_mm[leds] - c, axis=1) - d.radius_mm
    t_led = exposure_for(cfg, 0.5 * rho / np.pi * inten / float(np.min(dist)) ** 2, d.fraction)
    items = [Shot("silhouette", t_sil, "full", polarization="cross",
                  operator={"say": f"place the diffuse reference sphere (radius {d.radius_mm:g} mm) at the centre",
                            "target": "diffuse_sphere"}),
             Shot("ambient", t_led, "ambient", polarization="cross")]
    items += [Shot(f"led{i:04d}", t_led, "key", led=i, polarization="cross") for i in leds]
    return items


def fit_gain(observed: npt.ArrayLike, predicted: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Least-squares gain per channel g = sum V P / sum P^2 (observed V (P, 3), predicted P (P,) for unit gain)
    and the relative RMS residual per channel."""
    V = np.asarray(observed, float)
    P = np.asarray(predicted, float)
    g = (P @ V) / (P @ P)
    r = V - np.outer(P, g)
    return g, np.sqrt(np.mean(r * r, axis=0)) / np.mean(V, axis=0)


def compute(ctx: StepContext, cap: Captured) -> StepOutput:
    d, cfg = ctx.settings.diffuse_sphere, ctx.config
    intr = ctx.intrinsics()
    R, C = ctx.camera_pose()
    pos = ctx.led_positions_mm().copy()
    if ctx.prior is not None and ctx.prior.has("led_directions"):
        r = ctx.prior.result("led_directions")
        idx = np.asarray(r["led_indices"], int)
        pos[idx] = np.asarray(r["directions"], float) * np.linalg.norm(pos[idx], axis=1, keepdims=True)
        ctx.used["led_directions"] = f"mirror ball (revision {ctx.prior.section('led_directions')['revision']})"
    center, fit = ball_in_rig(cap.image("silhouette")[..., 1], intr, R, C, d.radius_mm)
    from scipy.ndimage import binary_erosion

    uv = np.stack(np.meshgrid(np.arange(intr.width_px), np.arange(intr.height_px)), -1).reshape(-1, 2).astype(float)
    rays = intr.rays(uv) @ R
    p, hit = intersect_sphere(C, rays, center, d.radius_mm)
    hit2 = binary_erosion(hit.reshape(intr.height_px, intr.width_px), iterations=d.erode_px).ravel()
    n = (p - center) / d.radius_mm
    view = -rays
    use = hit2 & (np.sum(n * view, axis=1) > 0.2)
    p, n, uv = p[use], n[use], uv[use].astype(int)
    amb = cap.image("ambient")
    rho = np.asarray(d.albedo, float)
    inten = np.asarray(cfg.sphere.led_intensity, float)
    drive = displayed_drive(cfg, ctx.pattern_peak)
    idx, gains, rel = [], [], {}
    pixels = {}
    for label in sorted(l for l in cap.frames if l.startswith("led")):
        i = int(label[3:])
        t = cap.exposure_s(label)
        raw = cap.image(label)
        img = raw - amb * (t / cap.exposure_s("ambient"))
        w = pos[i] - p
        dist2 = np.sum(w * w, axis=1)
        cos = np.sum(w * n, axis=1) / np.sqrt(dist2)
        ok = (cos >= d.min_cos) & np.all(raw[uv[:, 1], uv[:, 0]] < 0.98, axis=1)
        if ok.sum() < 50:
            raise ValueError(f"{cap.session.root}: LED {i} lights only {int(ok.sum())} usable pixels of the sphere")
        k = design_value_per_radiance(cfg, t)
        pred = k * 0.5 / np.pi * cos[ok] / dist2[ok]                     # unit intensity, unit albedo
        V = img[uv[ok, 1], uv[ok, 0]] / (rho * inten * drive)
        g, r = fit_gain(V, pred)
        idx.append(i)
        gains.append(g)
        rel[str(i)] = r.tolist()
        pixels[str(i)] = int(ok.sum())
    G = np.asarray(gains)
    result = {"led_indices": idx, "gains": G.tolist(), "design_intensity": inten.tolist(),
              "reference_albedo": rho.tolist(), "sphere_center_mm": center.tolist(), "sphere_radius_mm": d.radius_mm,
              "units": "true radiant intensity / design led_intensity, in the design camera response"}
    residuals = {"relative_rms": rel, "pixels": pixels, "silhouette": fit.to_dict(),
                 "max_relative_rms": float(max(max(v) for v in rel.values()))}
    summary = [f"{len(idx)} LEDs: gains R {G[:, 0].min():.3f}..{G[:, 0].max():.3f}, G {G[:, 1].min():.3f}.."
               f"{G[:, 1].max():.3f}, B {G[:, 2].min():.3f}..{G[:, 2].max():.3f}; fit residual <= "
               f"{100 * residuals['max_relative_rms']:.2f}% (sphere centre {np.round(center, 2).tolist()} mm)"]
    return StepOutput(result, residuals, {}, summary)


def compare(ctx: StepContext, result: dict[str, Any]) -> dict[str, Any]:
    truth = ctx.world.truth
    idx = np.asarray(result["led_indices"], int)
    rel = np.asarray(result["gains"]) / truth.led_gains[idx] - 1.0
    return {"gain_rel_error": {"max_abs": float(np.abs(rel).max()), "rms": float(np.sqrt(np.mean(rel ** 2))),
                               "by_led": {str(i): r.tolist() for i, r in zip(idx, rel)}},
            "sphere_center_error": split_error(np.asarray(result["sphere_center_mm"])
                                               - ctx.world.placement("diffuse_sphere"),
                                               ctx.world.placement("diffuse_sphere"), truth.camera.pinhole.C)}

