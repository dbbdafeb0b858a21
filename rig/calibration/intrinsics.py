"""Step 1: camera intrinsics and lens distortion from a ChArUco board.

Captures: ``board.views`` frames of the board (every LED on, cross-polarized), the operator moving it between
frames (tilted, at varied depth, covering the image corners). Computes: ChArUco corners
(``cv2.aruco.CharucoDetector.detectBoard``; markers identify the corners, which are refined to sub-pixel on the
chessboard saddles), then Zhang's calibration (``cv2.calibrateCameraExtended``) for fx, fy, cx, cy and the
distortion (k1, k2, p1, p2[, k3]), with the design focal length as the starting guess.

References: Z. Zhang, "A flexible new technique for camera calibration", IEEE PAMI 22(11), 2000; OpenCV
documentation, "Detection of ChArUco Boards" and ``calib3d`` (calibrateCamera); Garrido-Jurado et al.,
"Automatic generation and detection of highly reliable fiducial markers under occlusion", Pattern Recognition
47(6), 2014.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np
import numpy.typing as npt

from rig.calibration.capture import Captured, Shot, design_irradiance, exposure_for
from rig.files.camera_intrinsics import Intrinsics
from rig.calibration.common import to_uint8
from rig.calibration.context import StepContext, StepOutput
from rig.config.calibration_settings import BoardSettings, aruco_dictionary

SECTION = "intrinsics"
# measured (issue 18): on the simulated rig k2 came out -1.74 against a true +0.22 while the model's rotation-free
# reprojection error stayed within tolerance: k1, k2 (and the focal length) trade off against each other
DISTORTION_NOTE = ("the distortion coefficients are correlated with each other and with the focal length: use them "
                   "together with fx, fy, cx, cy as one model (its rotation-free error is what is checked); "
                   "each coefficient alone is unreliable and is not a lens property to compare or reuse")
FloatArray = npt.NDArray[np.float64]

__all__ = ["SECTION", "shots", "compute", "compare", "charuco_board", "detect_charuco", "calibrate_views"]


def charuco_board(b: BoardSettings) -> Any:
    import cv2

    d = cv2.aruco.getPredefinedDictionary(aruco_dictionary(b.dictionary))
    return cv2.aruco.CharucoBoard((b.squares_x, b.squares_y), b.square_mm, b.marker_mm, d)


def detect_charuco(image: npt.ArrayLike, board: Any) -> tuple[FloatArray, npt.NDArray[np.int64]]:
    """ChArUco corners (K, 2) in pixels (distorted image) and their ids (K,); empty if the board is not seen."""
    import cv2

    det = cv2.aruco.CharucoDetector(board)
    corners, ids, _, _ = det.detectBoard(to_uint8(image))
    if ids is None or len(ids) == 0:
        return np.zeros((0, 2)), np.zeros(0, np.int64)
    return corners.reshape(-1, 2).astype(np.float64), ids.ravel().astype(np.int64)


def calibrate_views(views: Sequence[tuple[FloatArray, npt.NDArray[np.int64]]], board: Any, width_px: int,
                    height_px: int, *, guess: Intrinsics | None = None, fix_k3: bool = True
                    ) -> tuple[Intrinsics, dict[str, Any]]:
    """Zhang calibration from detected ChArUco views. Returns the intrinsics and residuals: RMS reprojection
    error (px), per-view RMS, standard deviations of the intrinsics, corner count."""
    import cv2

    objs, imgs = [], []
    for corners, ids in views:
        o, i = board.matchImagePoints(corners.reshape(-1, 1, 2).astype(np.float32), ids.reshape(-1, 1))
        objs.append(o.astype(np.float32))
        imgs.append(i.astype(np.float32))
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    K0 = None
    if guess is not None:
        K0 = guess.K.copy()
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, K, dist, rvecs, tvecs, std_in, _, per_view = cv2.calibrateCameraExtended(
        objs, imgs, (width_px, height_px), K0, np.zeros(5) if guess is not None else None, flags=flags,
        criteria=crit)
    d = np.zeros(5)
    d[:dist.size] = dist.ravel()[:5]
    intr = Intrinsics(width_px, height_px, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                      tuple(float(x) for x in d))
    std = std_in.ravel()
    residuals = {"rms_reprojection_px": float(rms), "per_view_rms_px": [float(x) for x in per_view.ravel()],
                 "corners": int(sum(len(i) for i in imgs)), "views": len(imgs),
                 "std_fx_px": float(std[0]), "std_fy_px": float(std[1]), "std_cx_px": float(std[2]),
                 "std_cy_px": float(std[3]), "std_distortion": [float(x) for x in std[4:9]]}
    return intr, residuals


def shots(ctx: StepContext) -> list[Shot]:
    b = ctx.settings.board
    geo = ctx.geometry
    normal = geo.camera.C - np.asarray(ctx.config.camera.look_at_mm, float)
    normal /= np.linalg.norm(normal)
    e = design_irradiance(ctx.config, ctx.config.camera.look_at_mm, normal, geometry=geo)
    exposure = exposure_for(ctx.config, 0.5 * 0.85 / np.pi * e, b.white_fraction)
    return [Shot(f"board{k:02d}", exposure, "full", polarization="cross",
                 operator={"say": f"place the ChArUco board in pose {k + 1} of {b.views} (tilted 20-40 degrees, "
                                  "at varied depth; over the views cover every image corner)",
                           "target": "charuco", "pose": k})
            for k in range(b.views)]


def compute(ctx: StepContext, cap: Captured) -> StepOutput:
    b = ctx.settings.board
    board = charuco_board(b)
    cam = ctx.geometry.camera
    views, used, dropped = [], [], {}
    for label in sorted(cap.frames):
        corners, ids = detect_charuco(cap.image(label), board)
        if len(ids) < b.min_corners:
            dropped[label] = f"{len(ids)} corners (< {b.min_corners})"
            continue
        views.append((corners, ids))
        used.append(label)
    if len(views) < 3:
        d = float(np.linalg.norm(np.asarray(ctx.config.camera.look_at_mm, float) - cam.C))
        marker_px = b.marker_mm * cam.fx_px / d
        hint = ""
        if marker_px < 20:
            hint = (f"; its markers are only ~{marker_px:.0f} px wide at the working distance (a 4x4 marker needs "
                    "~20 px): use a finer camera or larger squares ([calibration.board] square_mm)")
        raise ValueError(f"the board was found in {len(views)} of {len(cap.frames)} views (>= {b.min_corners} "
                         f"corners); Zhang's method needs at least 3{hint}")
    intr, res = calibrate_views(views, board, cam.width_px, cam.height_px,
                                guess=Intrinsics.from_pinhole(cam), fix_k3=b.fix_k3)
    res["views_used"] = used
    res["views_dropped"] = dropped
    result = intr.to_dict()
    result["board"] = {"squares": [b.squares_x, b.squares_y], "square_mm": b.square_mm, "marker_mm": b.marker_mm,
                       "dictionary": b.dictionary}
    result["distortion_note"] = DISTORTION_NOTE
    summary = [f"fx {intr.fx_px:.2f} px, fy {intr.fy_px:.2f} px, cx {intr.cx_px:.2f}, cy {intr.cy_px:.2f}; "
               f"k1 {intr.distortion[0]:.4f}, k2 {intr.distortion[1]:.4f}; RMS {res['rms_reprojection_px']:.3f} px "
               f"over {res['corners']} corners in {len(views)} views",
               "note: " + DISTORTION_NOTE]
    return StepOutput(result, res, {"design_fx_px": cam.fx_px}, summary)


def model_difference_px(a: Intrinsics, b: Intrinsics, grid: int = 25) -> dict[str, float]:
    """How differently two camera models image the same scene, over a grid of pixels u of ``b`` (px):

    - ``max_px`` / ``rms_px``: |project_a(ray_b(u)) - u|, the raw difference;
    - ``rotation_free_max_px`` / ``rotation_free_rms_px``: the same after the best rotation of a's rays onto b's
      (a small rotation is indistinguishable from a principal-point shift and is absorbed by the camera pose,
      so this is what the calibration must get right: where each pixel's ray points relative to the others);
    - ``distortion_only_max_px``: a's distortion with b's K against b."""
    from rig.calibration.common import fit_transform

    u, v = np.meshgrid(np.linspace(0, b.width_px - 1, grid), np.linspace(0, b.height_px - 1, grid))
    uv = np.stack([u, v], -1).reshape(-1, 2)
    rays_b = b.rays(uv)
    full = np.linalg.norm(a.project(rays_b) - uv, axis=1)
    rays_a = a.rays(uv)
    R, _, _ = fit_transform(rays_a, rays_b)
    rot_free = np.linalg.norm(b.project(rays_a @ R.T) - uv, axis=1)
    a_d = Intrinsics(b.width_px, b.height_px, b.fx_px, b.fy_px, b.cx_px, b.cy_px, a.distortion)
    dist_only = np.linalg.norm(a_d.project(rays_b) - uv, axis=1)
    return {"max_px": float(full.max()), "rms_px": float(np.sqrt(np.mean(full ** 2))),
            "rotation_free_max_px": float(rot_free.max()),
            "rotation_free_rms_px": float(np.sqrt(np.mean(rot_free ** 2))),
            "rotation_deg": float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))),
            "distortion_only_max_px": float(dist_only.max())}


def compare(ctx: StepContext, result: dict[str, Any]) -> dict[str, Any]:
    """Recovered vs the simulator's truth."""
    t = ctx.world.truth.camera
    p = t.pinhole
    truth = Intrinsics(p.width_px, p.height_px, p.fx_px, p.fy_px, p.cx_px, p.cy_px, t.distortion)
    est = Intrinsics(int(result["width_px"]), int(result["height_px"]), result["fx_px"], result["fy_px"],
                     result["cx_px"], result["cy_px"], tuple(result["distortion"]))
    out = {"fx_rel_error": est.fx_px / truth.fx_px - 1, "fy_rel_error": est.fy_px / truth.fy_px - 1,
           "cx_error_px": est.cx_px - truth.cx_px, "cy_error_px": est.cy_px - truth.cy_px,
           "truth": truth.to_dict(), "model_difference": model_difference_px(est, truth)}
    return out
