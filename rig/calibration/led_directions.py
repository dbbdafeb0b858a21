"""Step 3a: LED directions from a mirror ball (Debevec 1998; the light-stage practice of Debevec et al. 2000).

Captures: a chrome ball of known radius at the sphere's centre; one cross-polarized frame with every LED on
(the specular highlights are extinguished, the ball's faint diffuse residue outlines it against the dark
sphere), a parallel-polarized ambient frame, and one parallel-polarized frame per LED lit alone.

Computes: the ball's centre from its silhouette (a cone fit with the known radius,
:func:`rig.calibration.common.sphere_from_silhouette`), in the rig frame through the calibrated camera pose;
then for each LED the intensity-weighted centroid of its highlight, the camera ray through it (undistorted),
its intersection with the ball, the surface normal there and the mirror reflection of the ray. The LED lies
on the reflected ray; intersecting it with the sphere of the LED's surveyed distance from the rig origin gives
its position, hence its direction *from the rig origin* (the ball's offset from the origin would otherwise bias
directions by up to offset/distance rad).

References: P. Debevec, "Rendering synthetic objects into real scenes", SIGGRAPH 1998 (mirror-ball light probes);
P. Debevec et al., "Acquiring the reflectance field of a human face", SIGGRAPH 2000 (light stage).
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np
import numpy.typing as npt

from estimation.camera import intersect_sphere

from rig.calibration.capture import Captured, Shot, design_irradiance, exposure_and_peak, exposure_for
from rig.files.camera_intrinsics import Intrinsics
from rig.calibration.common import SphereFit, angle_deg, reflect, sphere_from_silhouette, split_error
from rig.calibration.context import StepContext, StepOutput

SECTION = "led_directions"
FloatArray = npt.NDArray[np.float64]
PSF_SIGMA_DESIGN_PX = 0.8     # design guess of the lens blur, for the highlight exposure only

__all__ = ["SECTION", "shots", "compute", "compare", "visible_leds", "highlight_centroid",
           "led_direction_from_highlight",
           "ball_in_rig"]


def _spread(dirs: FloatArray, candidates: Sequence[int], count: int) -> list[int]:
    cand = list(candidates)
    if count <= 0 or count >= len(cand):
        return sorted(cand)
    d = dirs[cand]
    chosen = [int(np.argmax(d @ np.mean(d, axis=0)))]
    dmin = np.full(len(cand), np.inf)
    while len(chosen) < count:
        dmin = np.minimum(dmin, np.linalg.norm(d - d[chosen[-1]], axis=1))
        chosen.append(int(np.argmax(dmin)))
    return sorted(cand[i] for i in chosen)


def visible_leds(led_positions_mm: npt.ArrayLike, ball_center_mm: npt.ArrayLike, camera_center_mm: npt.ArrayLike,
                 max_normal_deg: float) -> list[int]:
    """LEDs whose highlight on the ball lies where the surface normal is within ``max_normal_deg`` of the
    direction to the camera (the normal bisects the directions to the camera and to the LED)."""
    c = np.asarray(ball_center_mm, float)
    to_cam = np.asarray(camera_center_mm, float) - c
    to_cam /= np.linalg.norm(to_cam)
    to_led = np.asarray(led_positions_mm, float) - c
    to_led /= np.linalg.norm(to_led, axis=1, keepdims=True)
    half = 0.5 * np.degrees(np.arccos(np.clip(to_led @ to_cam, -1, 1)))
    return [int(i) for i in np.flatnonzero(half <= max_normal_deg)]


def _leds(ctx: StepContext) -> list[int]:
    b = ctx.settings.mirror_ball
    n = len(ctx.geometry.led_positions_mm)
    if b.leds:
        bad = [i for i in b.leds if not 0 <= i < n]
        if bad:
            raise ValueError(f"calibration.mirror_ball.leds: LED indices {bad} outside [0, {n})")
        return list(b.leds)
    pos = ctx.geometry.led_positions_mm
    vis = visible_leds(pos, b.center_mm, ctx.geometry.camera.C, b.max_normal_deg)
    return _spread(ctx.geometry.led_directions, vis, b.count)


def _highlight_exposure(ctx: StepContext) -> tuple[float, float]:
    """Design (exposure_s, pattern peak) for a highlight peak at ``highlight_fraction`` of full scale: a specular
    sphere of radius r at distance D_led from a point LED of intensity I reflects it with intensity
    I_b = R I r^2 / (4 D_led^2) towards any direction; the camera at d_cam collects sum(L_pix) = I_b f^2 / d_cam^2
    (radiance x px^2), spread by the lens PSF over 2 pi sigma^2 px^2. Highlights are bright: when the shortest
    exposure would still overexpose, the LEDs are dimmed instead."""
    b, cfg = ctx.settings.mirror_ball, ctx.config
    geo = ctx.geometry
    d_led = float(np.median(np.linalg.norm(geo.led_positions_mm - np.asarray(b.center_mm), axis=1)))
    d_cam = float(np.linalg.norm(geo.camera.C - np.asarray(b.center_mm)))
    inten = float(np.mean(cfg.sphere.led_intensity))
    i_b = b.specular_reflectance * inten * b.radius_mm ** 2 / (4 * d_led ** 2)
    peak = i_b * geo.camera.fx_px * geo.camera.fy_px / d_cam ** 2 / (2 * np.pi * PSF_SIGMA_DESIGN_PX ** 2)
    return exposure_and_peak(cfg, peak, b.highlight_fraction)


def shots(ctx: StepContext) -> list[Shot]:
    b, cfg = ctx.settings.mirror_ball, ctx.config
    t_hi, ctx.pattern_peak = _highlight_exposure(ctx)
    to_cam = ctx.geometry.camera.C - np.asarray(b.center_mm)
    to_cam /= np.linalg.norm(to_cam)
    e = design_irradiance(cfg, np.asarray(b.center_mm) + b.radius_mm * to_cam, to_cam, geometry=ctx.geometry,
                          peak=ctx.pattern_peak)
    t_sil = exposure_for(cfg, 0.5 * b.diffuse_albedo / np.pi * e, b.silhouette_fraction)
    items = [Shot("silhouette", t_sil, "full", polarization="cross",
                  operator={"say": f"place the mirror ball (radius {b.radius_mm:g} mm) at the sphere's centre",
                            "target": "mirror_ball"}),
             Shot("ambient", t_hi, "ambient", polarization="parallel")]
    items += [Shot(f"led{i:04d}", t_hi, "key", led=i, polarization="parallel") for i in _leds(ctx)]
    return items


def ball_in_rig(silhouette: npt.ArrayLike, intrinsics: Intrinsics, R: npt.ArrayLike, C: npt.ArrayLike,
                radius_mm: float) -> tuple[FloatArray, SphereFit]:
    """Ball centre in the rig frame from its silhouette frame, the camera pose and the known radius."""
    fit = sphere_from_silhouette(silhouette, intrinsics, radius_mm)
    return np.asarray(C, float) + np.asarray(R, float).T @ fit.center_cam_mm, fit


def highlight_centroid(image: npt.ArrayLike, region: npt.ArrayLike | None = None, half_window: int = 4
                       ) -> tuple[FloatArray, float]:
    """Sub-pixel centroid (u, v) of the brightest spot (background = median of the window's border removed,
    intensity-weighted) and its peak value. ``region``: boolean mask where to look (the ball's disc)."""
    img = np.asarray(image, float)
    if img.ndim == 3:
        img = img.sum(axis=2)
    search = np.where(region, img, -np.inf) if region is not None else img
    i, j = np.unravel_index(int(np.argmax(search)), img.shape)
    h = half_window
    i0, i1, j0, j1 = max(i - h, 0), min(i + h + 1, img.shape[0]), max(j - h, 0), min(j + h + 1, img.shape[1])
    win = img[i0:i1, j0:j1]
    border = np.concatenate([win[0], win[-1], win[1:-1, 0], win[1:-1, -1]])
    w = np.maximum(win - np.median(border), 0.0)
    if not w.sum() > 0:
        raise ValueError("no highlight found")
    vv, uu = np.mgrid[i0:i1, j0:j1]
    return np.array([np.sum(w * uu) / w.sum(), np.sum(w * vv) / w.sum()]), float(img[i, j])


def led_direction_from_highlight(uv: npt.ArrayLike, intrinsics: Intrinsics, R: npt.ArrayLike, C: npt.ArrayLike,
                                 ball_center_mm: npt.ArrayLike, ball_radius_mm: float, led_distance_mm: float
                                 ) -> FloatArray:
    """Unit direction from the rig origin to the LED whose highlight is at pixel ``uv``: camera ray -> ball
    surface point p and normal n -> reflected ray p + t r -> the point at ``led_distance_mm`` from the origin."""
    R = np.asarray(R, float)
    C = np.asarray(C, float)
    d = intrinsics.rays(np.asarray(uv, float)) @ R
    p, hit = intersect_sphere(C, d, ball_center_mm, ball_radius_mm)
    if not hit:
        raise ValueError(f"highlight at {np.round(uv, 2).tolist()} px is off the ball")
    n = (p - np.asarray(ball_center_mm, float)) / ball_radius_mm
    r = reflect(d, n)
    b = float(p @ r)
    c = float(p @ p) - led_distance_mm ** 2
    t = -b + np.sqrt(b * b - c)
    x = p + t * r
    return x / np.linalg.norm(x)


def compute(ctx: StepContext, cap: Captured) -> StepOutput:
    b = ctx.settings.mirror_ball
    intr = ctx.intrinsics()
    R, C = ctx.camera_pose()
    prior_pos = ctx.led_positions_mm()
    center, fit = ball_in_rig(cap.image("silhouette")[..., 1], intr, R, C, b.radius_mm)
    # the ball's disc in the image, a little inside its outline
    cam_pts = (np.stack(np.meshgrid(np.arange(intr.width_px), np.arange(intr.height_px)), -1)).reshape(-1, 2)
    rays = intr.rays(cam_pts.astype(float)) @ R
    _, on = intersect_sphere(C, rays, center, b.radius_mm * 0.995)
    disc = on.reshape(intr.height_px, intr.width_px)
    amb = cap.image("ambient")
    idx, dirs, ang, peaks, saturated = [], [], {}, {}, []
    for label in sorted(l for l in cap.frames if l.startswith("led")):
        i = int(label[3:])
        img = cap.image(label) - amb * (cap.exposure_s(label) / cap.exposure_s("ambient"))
        uv, peak = highlight_centroid(img, disc)
        if np.max(cap.image(label)[int(round(uv[1])), int(round(uv[0]))]) >= 0.98:
            saturated.append(i)
        dist = float(np.linalg.norm(prior_pos[i]))
        w = led_direction_from_highlight(uv, intr, R, C, center, b.radius_mm, dist)
        idx.append(i)
        dirs.append(w)
        ang[str(i)] = float(angle_deg(w, prior_pos[i]))
        peaks[str(i)] = peak
    if not idx:
        raise ValueError(f"{cap.session.root}: no LED frames")
    a = np.asarray(list(ang.values()))
    result = {"led_indices": idx, "directions": np.asarray(dirs).tolist(), "ball_center_mm": center.tolist(),
              "ball_radius_mm": b.radius_mm}
    residuals = {"angle_to_prior_deg": ang, "angle_to_prior_rms_deg": float(np.sqrt(np.mean(a ** 2))),
                 "angle_to_prior_max_deg": float(a.max()), "silhouette": fit.to_dict(), "highlight_peak": peaks,
                 "saturated": saturated}
    summary = [f"ball centre {np.round(center, 2).tolist()} mm (silhouette RMS {fit.rms_px:.3f} px); "
               f"{len(idx)} LED directions, {float(np.sqrt(np.mean(a ** 2))):.3f} deg RMS from the prior "
               f"({ctx.used.get('led_positions')})"]
    if saturated:
        summary.append(f"WARNING: saturated highlights for LEDs {saturated}: shorten the exposure")
    return StepOutput(result, residuals, {}, summary)


def compare(ctx: StepContext, result: dict[str, Any]) -> dict[str, Any]:
    truth = ctx.world.truth
    idx = np.asarray(result["led_indices"], int)
    err = angle_deg(np.asarray(result["directions"]), truth.led_positions_mm[idx])
    ball = ctx.world.placement("mirror_ball")
    return {"direction_error_deg": {"max": float(err.max()), "rms": float(np.sqrt(np.mean(err ** 2))),
                                    "by_led": {str(i): float(e) for i, e in zip(idx, err)}},
            "ball_center_error": split_error(np.asarray(result["ball_center_mm"]) - ball, ball,
                                             truth.camera.pinhole.C)}
