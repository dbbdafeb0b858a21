"""An orthographic camera for the Monte Carlo renderer (pinhole: :class:`estimation.camera.PinholeCamera`).

Same fields and conventions as ``rig.capture_folder.OrthographicCamera`` (OpenCV axes: rows of R are the camera's
right, down and forward axes in the rig frame; ``target_mm`` images at (cx, cy)); the renderer only needs
``width_px``, ``height_px`` and ``pixel_rays()``, so either class works.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from estimation.camera import look_at_rotation

__all__ = ["OrthographicCamera"]


@dataclass(frozen=True)
class OrthographicCamera:
    width_px: int
    height_px: int
    pixel_size_mm: float
    rotation: tuple[tuple[float, float, float], ...]
    target_mm: tuple[float, float, float]
    cx_px: float
    cy_px: float
    ray_start_mm: float = 1e4  # rays start this far behind the image plane through target_mm

    @classmethod
    def looking_at(cls, *, width_px: int, height_px: int, pixel_size_mm: float, direction: npt.ArrayLike,
                   target_mm: npt.ArrayLike = (0.0, 0.0, 0.0), up: npt.ArrayLike = (0.0, 0.0, 1.0),
                   ray_start_mm: float = 1e4) -> "OrthographicCamera":
        """Camera looking along ``direction`` (towards the scene) at ``target_mm``, centred on it."""
        t = np.asarray(target_mm, float)
        r = look_at_rotation(t - np.asarray(direction, float), t, up)
        return cls(int(width_px), int(height_px), float(pixel_size_mm), tuple(map(tuple, r.tolist())),
                   tuple(map(float, t)), (width_px - 1) / 2.0, (height_px - 1) / 2.0, float(ray_start_mm))

    @property
    def R(self) -> npt.NDArray[np.float64]:
        return np.asarray(self.rotation, dtype=np.float64)

    def project(self, points_mm: npt.ArrayLike) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        xc = (np.asarray(points_mm, dtype=np.float64) - np.asarray(self.target_mm)) @ self.R.T
        return np.stack([xc[..., 0] / self.pixel_size_mm + self.cx_px,
                         xc[..., 1] / self.pixel_size_mm + self.cy_px], axis=-1), xc[..., 2]

    def pixel_rays(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Origins (H, W, 3) and unit directions (H, W, 3) of the parallel rays through every pixel centre."""
        v, u = np.mgrid[0:self.height_px, 0:self.width_px].astype(np.float64)
        R = self.R
        o = (np.asarray(self.target_mm)[None, None, :] + ((u - self.cx_px) * self.pixel_size_mm)[..., None] * R[0]
             + ((v - self.cy_px) * self.pixel_size_mm)[..., None] * R[1] - self.ray_start_mm * R[2])
        return o, np.broadcast_to(R[2], o.shape).copy()
