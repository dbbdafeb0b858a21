"""The calibrated camera as the calibration file stores it: pinhole intrinsics (px) and OpenCV lens distortion.

Conventions: ``estimation.camera`` (OpenCV axes, pixel centres at integers, X_cam = R (X - C)) and OpenCV's
distortion vector (k1, k2, p1, p2, k3) (Zhang 2000; OpenCV ``calib3d`` documentation). Written by the intrinsics
step (:mod:`rig.calibration.intrinsics`), read back by :meth:`rig.files.calibration_store.Calibration.intrinsics`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from estimation.camera import PinholeCamera

FloatArray = npt.NDArray[np.float64]

__all__ = ["Intrinsics"]


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics (px) plus OpenCV lens distortion (k1, k2, p1, p2, k3)."""

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @property
    def K(self) -> FloatArray:
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> FloatArray:
        return np.asarray(self.distortion, float)

    @classmethod
    def from_pinhole(cls, camera: PinholeCamera) -> "Intrinsics":
        return cls(camera.width_px, camera.height_px, camera.fx_px, camera.fy_px, camera.cx_px, camera.cy_px)

    def to_dict(self) -> dict[str, Any]:
        return {"width_px": self.width_px, "height_px": self.height_px, "fx_px": self.fx_px, "fy_px": self.fy_px,
                "cx_px": self.cx_px, "cy_px": self.cy_px, "distortion": list(self.distortion),
                "distortion_model": "opencv (k1, k2, p1, p2, k3)"}

    def normalized(self, uv: npt.ArrayLike) -> FloatArray:
        """Distorted pixels (..., 2) -> ideal normalized image coordinates (..., 2) (iterative inverse)."""
        import cv2

        q = np.asarray(uv, float)
        if not np.any(self.dist):
            return np.stack([(q[..., 0] - self.cx_px) / self.fx_px, (q[..., 1] - self.cy_px) / self.fy_px], -1)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
        out = cv2.undistortPoints(q.reshape(-1, 1, 2).astype(np.float64), self.K, self.dist, None, np.eye(3),
                                  np.eye(3), crit)
        return out.reshape(q.shape)

    def rays(self, uv: npt.ArrayLike) -> FloatArray:
        """Unit ray directions (..., 3) in the camera frame through distorted pixels ``uv`` (..., 2)."""
        xy = self.normalized(uv)
        d = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def project(self, points_cam: npt.ArrayLike) -> FloatArray:
        """Camera-frame points (..., 3) -> distorted pixels (..., 2)."""
        import cv2

        p = np.asarray(points_cam, float)
        uv, _ = cv2.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.K, self.dist)
        return uv.reshape(p.shape[:-1] + (2,))

    def pinhole(self, rotation: npt.ArrayLike, center_mm: npt.ArrayLike) -> PinholeCamera:
        """The undistorted camera at a rig-frame pose (rows of ``rotation`` = camera axes in the rig frame)."""
        R = np.asarray(rotation, float)
        return PinholeCamera(self.width_px, self.height_px, self.fx_px, self.fy_px, self.cx_px, self.cy_px,
                             tuple(map(tuple, R.tolist())), tuple(float(c) for c in np.asarray(center_mm, float)))

    def undistort_image(self, image: FloatArray) -> FloatArray:
        """Resample a distorted frame (H, W[, C]) onto the ideal pinhole with the same K (bilinear)."""
        import cv2

        if not np.any(self.dist):
            return np.asarray(image, float)
        m1, m2 = cv2.initUndistortRectifyMap(self.K, self.dist, None, self.K, (self.width_px, self.height_px),
                                             cv2.CV_32FC1)
        img = np.asarray(image, np.float32)
        return cv2.remap(img, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0).astype(
            np.float64)
