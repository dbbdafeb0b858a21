"""Pinhole and orthographic camera models (pure numpy), shared by the estimators and the simulated camera.

Conventions (see ``docs/architecture.md``): world = rig frame in mm, right-handed. Camera frame follows
OpenCV: +x right in the image, +y down, +z forward along the optical axis. A world point X maps to the
camera as ``Xc = R @ (X - C)`` where ``C`` is the camera centre and the rows of ``R`` are the camera axes
expressed in the world. Pixel (u, v) = (fx Xc/Zc + cx, fy Yc/Zc + cy); pixel centres are at integer
coordinates, (0, 0) being the centre of the top-left pixel.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


def look_at_rotation(position_mm: npt.ArrayLike, target_mm: npt.ArrayLike,
                     up: npt.ArrayLike = (0.0, 0.0, 1.0)) -> FloatArray:
    """Rotation whose rows are the camera's x (right), y (down), z (forward) axes in world coordinates."""
    c = np.asarray(position_mm, float)
    z = np.asarray(target_mm, float) - c
    norm = np.linalg.norm(z)
    if norm == 0:
        raise ValueError("camera position and look-at target coincide")
    z /= norm
    upv = np.asarray(up, float)
    x = np.cross(z, upv)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError(f"camera 'up' {tuple(upv)} is parallel to the viewing direction")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


@dataclass(frozen=True)
class PinholeCamera:
    """An ideal pinhole camera (distortion is removed upstream by calibration)."""

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    rotation: tuple[tuple[float, float, float], ...]
    center_mm: tuple[float, float, float]

    @classmethod
    def looking_at(cls, *, width_px: int, height_px: int, fx_px: float, position_mm: npt.ArrayLike,
                   target_mm: npt.ArrayLike, up: npt.ArrayLike = (0.0, 0.0, 1.0),
                   fy_px: float | None = None) -> "PinholeCamera":
        r = look_at_rotation(position_mm, target_mm, up)
        return cls(width_px, height_px, float(fx_px), float(fy_px or fx_px),
                   (width_px - 1) / 2.0, (height_px - 1) / 2.0,
                   tuple(map(tuple, r.tolist())), tuple(map(float, np.asarray(position_mm, float))))

    @property
    def R(self) -> FloatArray:
        return np.asarray(self.rotation, float)

    @property
    def C(self) -> FloatArray:
        return np.asarray(self.center_mm, float)

    @property
    def K(self) -> FloatArray:
        return np.array([[self.fx_px, 0, self.cx_px], [0, self.fy_px, self.cy_px], [0, 0, 1.0]])

    def project(self, points_mm: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Project (..., 3) world points: returns pixel coordinates (..., 2) and depth (...) in mm."""
        p = np.asarray(points_mm, float)
        xc = (p - self.C) @ self.R.T
        z = xc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx_px * xc[..., 0] / z + self.cx_px
            v = self.fy_px * xc[..., 1] / z + self.cy_px
        return np.stack([u, v], axis=-1), z

    def pixel_rays(self) -> tuple[FloatArray, FloatArray]:
        """Origins (H, W, 3) and unit directions (H, W, 3) of the rays through every pixel centre."""
        v, u = np.mgrid[0:self.height_px, 0:self.width_px].astype(float)
        d_cam = np.stack([(u - self.cx_px) / self.fx_px, (v - self.cy_px) / self.fy_px,
                          np.ones_like(u)], axis=-1)
        d = d_cam @ self.R
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return np.broadcast_to(self.C, d.shape).copy(), d

    def view_directions(self, points_mm: npt.ArrayLike) -> FloatArray:
        """Unit vectors from world points towards the camera centre."""
        w = self.C - np.asarray(points_mm, float)
        return w / np.linalg.norm(w, axis=-1, keepdims=True)


@dataclass(frozen=True)
class OrthographicCamera:
    """Orthographic camera: rig point X projects to pixel (u, v) = (Xc_x, Xc_y)/pixel_size_mm + (cx, cy) with
    Xc = R (X - target_mm) and the rows of R the camera's right, down and forward axes in the rig frame (the
    OpenCV convention of :class:`PinholeCamera`); ``target_mm`` images at (cx, cy). Used by capture folders
    (rig.estimate.capture_folder) and the Monte Carlo renderer (simulators.mc)."""

    width_px: int
    height_px: int
    pixel_size_mm: float
    rotation: tuple[tuple[float, float, float], ...]
    target_mm: tuple[float, float, float]
    cx_px: float
    cy_px: float
    ray_start_mm: float = 1e5  # rays start this far behind the image plane through target_mm

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
        """Pixel coordinates (..., 2) and depth along the forward axis (..., ) of rig points (..., 3)."""
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


def intersect_sphere(origins: npt.ArrayLike, directions: npt.ArrayLike, center_mm: npt.ArrayLike,
                     radius_mm: float) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
    """Nearest positive intersection of rays with a sphere: points (..., 3) (NaN where missed) and hit mask."""
    o = np.asarray(origins, float) - np.asarray(center_mm, float)
    d = np.asarray(directions, float)
    b = np.sum(o * d, axis=-1)
    c = np.sum(o * o, axis=-1) - radius_mm ** 2
    disc = b * b - c
    hit = disc > 0
    t = -b - np.sqrt(np.where(hit, disc, 0.0))
    hit &= t > 0
    pts = np.asarray(origins, float) + t[..., None] * d
    pts[~hit] = np.nan
    return pts, hit
