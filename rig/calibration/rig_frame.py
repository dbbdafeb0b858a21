"""Step 2: the rig frame — the camera's pose from surveyed targets, and the LED positions refined by survey.

Captures: one frame of the camera-pose plates (a quadrant target over a total-station reflector, named by the
ArUco marker above it: ``aruco_<id>``), and total-station measurements of those reflectors and of reflectors on a
subset of LEDs (``led_<index>``). Computes:

- the camera pose by solvePnP: each plate's marker is detected, the plate-to-image homography predicts the
  quadrant target's centre, ``cornerSubPix`` refines it on the saddle point, and it is undistorted with the
  calibrated intrinsics; SQPnP then Levenberg-Marquardt refinement on (surveyed reflector, normalized image point)
  pairs
  (Terzakis & Lourakis, "A consistently fast and globally optimal solution to the perspective-n-point problem",
  ECCV 2020; OpenCV ``solvePnP``). X_cam = R (X - C) as ``estimation.camera``.
- the LED positions: the design layout mapped onto the surveyed LEDs by a least-squares rigid (or similarity)
  transform (Umeyama 1991); surveyed LEDs take their measured positions. Residuals per surveyed LED show the
  mounting scatter the transform cannot explain.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from rig.calibration.capture import Captured, Shot, Survey, design_irradiance, exposure_for
from rig.files.camera_intrinsics import Intrinsics
from rig.calibration.common import angle_deg, fit_transform, rotation_angle_deg, to_uint8
from rig.calibration.context import StepContext, StepOutput
from rig.calibration.layout import LED_TARGET, POSE_TARGET, pose_targets, survey_leds
from rig.config.calibration_settings import aruco_dictionary

SECTION = "rig_frame"
FloatArray = npt.NDArray[np.float64]

__all__ = ["SECTION", "shots", "compute", "compare", "detect_marker_centers", "camera_pose_pnp", "refine_leds"]


def detect_marker_centers(image: npt.ArrayLike, dictionary: str, intrinsics: Intrinsics, *, marker_mm: float,
                          target_mm: float, margin_mm: float) -> dict[int, FloatArray]:
    """Plate id -> the quadrant target's centre (the reflector) in *normalized* (undistorted) image coordinates.

    Each plate's ArUco marker (Garrido-Jurado et al. 2014) is detected and its corners undistorted; the homography
    from the plate's plane to the image predicts the target centre, which ``cv2.cornerSubPix`` then refines on
    the quadrant's saddle point (the feature it is made for: ~0.02 px, against ~0.5 px for a marker's own convex
    corners), before undistorting it."""
    import cv2

    img = np.asarray(image, float)
    if img.ndim == 3:
        img = img.mean(axis=2)
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(aruco_dictionary(dictionary)),
                                  cv2.aruco.DetectorParameters())
    corners, ids, _ = det.detectMarkers(to_uint8(img))
    out: dict[int, FloatArray] = {}
    if ids is None:
        return out
    mx = -(target_mm / 2 + margin_mm + marker_mm / 2)        # the marker sits left of the target
    h = marker_mm / 2
    local = np.array([[mx - h, -h], [mx + h, -h], [mx + h, h], [mx - h, h]], np.float64)
    grey = (img / max(float(np.percentile(img, 99.5)), 1e-12)).astype(np.float32)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    for c, i in zip(corners, ids.ravel()):
        px = c.reshape(4, 2).astype(np.float64)
        H, _ = cv2.findHomography(local, intrinsics.normalized(px))
        guess_n = (H @ [0.0, 0.0, 1.0])
        guess = intrinsics.project(np.append(guess_n[:2] / guess_n[2], 1.0)[None, :])[0]
        side_px = float(np.mean(np.linalg.norm(px - np.roll(px, 1, axis=0), axis=1)))
        win = max(2, int(0.3 * side_px * target_mm / marker_mm))
        if not (win <= guess[0] < img.shape[1] - win and win <= guess[1] < img.shape[0] - win):
            continue
        pt = cv2.cornerSubPix(grey, guess.reshape(1, 1, 2).astype(np.float32), (win, win), (-1, -1), crit)
        pt = pt.reshape(2).astype(np.float64)
        if np.linalg.norm(pt - guess) > win:
            continue
        out[int(i)] = intrinsics.normalized(pt)
    return out


def camera_pose_pnp(points_mm: npt.ArrayLike, normalized: npt.ArrayLike, fx_px: float
                    ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Camera rotation (rows = camera axes in the rig frame), centre (mm) and per-point reprojection errors (px,
    as fx x normalized error) from >= 4 rig-frame points and their normalized image coordinates."""
    import cv2

    obj = np.asarray(points_mm, np.float64).reshape(-1, 1, 3)
    img = np.asarray(normalized, np.float64).reshape(-1, 1, 2)
    if len(obj) < 4:
        raise ValueError(f"solvePnP needs at least 4 surveyed targets seen by the camera, got {len(obj)}")
    ok, rvec, tvec = cv2.solvePnP(obj, img, np.eye(3), None, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        raise ValueError("solvePnP failed (targets collinear or behind the camera?)")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, np.eye(3), None, rvec, tvec,
                                      (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15))
    R, _ = cv2.Rodrigues(rvec)
    C = -R.T @ tvec.ravel()
    proj, _ = cv2.projectPoints(obj, rvec, tvec, np.eye(3), None)
    err = np.linalg.norm(proj.reshape(-1, 2) - img.reshape(-1, 2), axis=1) * fx_px
    return R, C, err


def refine_leds(design_mm: npt.ArrayLike, surveyed: dict[int, npt.ArrayLike], *, scale: bool = False
                ) -> tuple[FloatArray, list[str], dict[str, Any]]:
    """LED positions (N, 3): the design layout moved by the transform that best maps the surveyed LEDs' design
    positions onto their survey; surveyed LEDs keep their measurement. Returns positions, per-LED source
    ("survey" | "design+fit") and the fit (rotation, translation_mm, scale, residuals_mm by LED)."""
    design = np.asarray(design_mm, float)
    idx = sorted(surveyed)
    src = design[idx]
    dst = np.asarray([surveyed[i] for i in idx], float)
    R, t, s = fit_transform(src, dst, scale=scale)
    moved = s * design @ R.T + t
    resid = dst - moved[idx]
    out = moved.copy()
    out[idx] = dst
    source = ["design+fit"] * len(design)
    for i in idx:
        source[i] = "survey"
    fit = {"rotation": R.tolist(), "translation_mm": t.tolist(), "scale": s,
           "rotation_deg": rotation_angle_deg(R, np.eye(3)),
           "residuals_mm": {str(i): float(np.linalg.norm(r)) for i, r in zip(idx, resid)},
           "rms_mm": float(np.sqrt(np.mean(np.sum(resid ** 2, axis=1))))}
    return out, source, fit


def shots(ctx: StepContext) -> list[Shot | Survey]:
    cfg, s = ctx.config, ctx.settings.pose_targets
    geo = ctx.geometry
    look = np.asarray(cfg.camera.look_at_mm, float)
    normal = geo.camera.C - look
    normal /= np.linalg.norm(normal)
    e = design_irradiance(cfg, look, normal, geometry=geo)
    exposure = exposure_for(cfg, 0.5 * 0.85 / np.pi * e, s.white_fraction)
    items: list[Shot | Survey] = [Shot("pose_targets", exposure, "full", polarization="cross",
                                       operator={"say": "mount the camera-pose plates (quadrant targets with "
                                                        "reflectors, named by ArUco markers) in front of the camera",
                                                 "target": "pose_targets"})]
    items += [Survey(name) for name in pose_targets(cfg, ctx.settings)]
    items += [Survey(LED_TARGET.format(i)) for i in survey_leds(cfg, ctx.settings, geo)]
    return items


def compute(ctx: StepContext, cap: Captured) -> StepOutput:
    s = ctx.settings
    intr = ctx.intrinsics()
    p = s.pose_targets
    centers = detect_marker_centers(cap.image("pose_targets"), p.dictionary, intr, marker_mm=p.marker_mm,
                                    target_mm=p.target_mm, margin_mm=p.margin_mm)
    names, pts, img = [], [], []
    for name, xyz in sorted(cap.surveys.items()):
        m = POSE_TARGET.match(name)
        if m and int(m.group(1)) in centers:
            names.append(name)
            pts.append(xyz)
            img.append(centers[int(m.group(1))])
    missing = sorted(n for n in cap.surveys if POSE_TARGET.match(n) and n not in names)
    R, C, err = camera_pose_pnp(pts, img, intr.fx_px)
    leds = {int(n[4:]): xyz for n, xyz in cap.surveys.items() if n.startswith("led_")}
    design = np.asarray(ctx.geometry.led_positions_mm, float)
    positions, source, fit = refine_leds(design, leds, scale=s.led_survey.fit == "similarity")
    result = {"camera": {"rotation": R.tolist(), "center_mm": C.tolist()},
              "led_positions_mm": positions.tolist(), "led_position_source": source,
              "led_transform": {k: fit[k] for k in ("rotation", "translation_mm", "scale", "rotation_deg")},
              "pose_targets_mm": {n: list(p) for n, p in zip(names, pts)}}
    residuals = {"pnp_rms_px": float(np.sqrt(np.mean(err ** 2))), "pnp_max_px": float(err.max()),
                 "pnp_px": {n: float(e) for n, e in zip(names, err)}, "targets_used": len(names),
                 "targets_not_seen": missing, "led_fit_rms_mm": fit["rms_mm"],
                 "led_fit_max_mm": max(fit["residuals_mm"].values()), "led_fit_mm": fit["residuals_mm"],
                 "leds_surveyed": len(leds)}
    design_cam = ctx.geometry.camera
    summary = [f"camera centre {np.round(C, 2).tolist()} mm ({np.linalg.norm(C - design_cam.C):.2f} mm from design, "
               f"turned {rotation_angle_deg(R, design_cam.R):.3f} deg); solvePnP RMS {residuals['pnp_rms_px']:.3f} px "
               f"over {len(names)} targets",
               f"LEDs: {len(leds)} surveyed, design moved by {np.linalg.norm(fit['translation_mm']):.2f} mm and "
               f"{fit['rotation_deg']:.3f} deg (scale {fit['scale']:.5f}); fit RMS {fit['rms_mm']:.2f} mm"]
    return StepOutput(result, residuals, {}, summary)


def pointing_error_deg(est: Intrinsics, R_est: npt.ArrayLike, true_cam: Any, grid: int = 15) -> float:
    """Largest angle (deg) between the estimated and the true rig-frame ray through the same pixel, over a grid
    of the image (the camera's pointing accuracy; ``true_cam`` is a ``simulators.targets.LensCamera``)."""
    p = true_cam.pinhole
    u, v = np.meshgrid(np.linspace(0, p.width_px - 1, grid), np.linspace(0, p.height_px - 1, grid))
    uv = np.stack([u, v], -1).reshape(-1, 2)
    est_world = est.rays(uv) @ np.asarray(R_est, float)
    true_world = true_cam.pixel_directions(uv)
    return float(angle_deg(est_world, true_world).max())


def compare(ctx: StepContext, result: dict[str, Any]) -> dict[str, Any]:
    truth = ctx.world.truth
    cam = truth.camera.pinhole
    R = np.asarray(result["camera"]["rotation"], float)
    C = np.asarray(result["camera"]["center_mm"], float)
    pos = np.asarray(result["led_positions_mm"], float)
    err = np.linalg.norm(pos - truth.led_positions_mm, axis=1)
    src = np.asarray(result["led_position_source"])
    dir_err = angle_deg(pos, truth.led_positions_mm)
    intr = ctx.prior.intrinsics() if ctx.prior is not None and ctx.prior.has("intrinsics") else \
        Intrinsics.from_pinhole(ctx.geometry.camera)
    return {"camera_center_error_mm": float(np.linalg.norm(C - cam.C)),
            "camera_rotation_error_deg": rotation_angle_deg(R, cam.R),
            "camera_pointing_error_deg": pointing_error_deg(intr, R, truth.camera),
            "led_position_error_mm": {"rms": float(np.sqrt(np.mean(err ** 2))), "max": float(err.max()),
                                      "surveyed_max": float(err[src == "survey"].max()),
                                      "fitted_rms": float(np.sqrt(np.mean(err[src != "survey"] ** 2)))},
            "led_direction_error_deg": {"max": float(dir_err.max()), "rms": float(np.sqrt(np.mean(dir_err ** 2)))},
            "led_transform_truth": truth.led_transform}
