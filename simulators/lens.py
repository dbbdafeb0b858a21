"""The simulated rig's true camera: a pinhole with Brown-Conrady lens distortion, and rotations for poses.

Conventions of :mod:`estimation.camera` (OpenCV axes: x right, y down, z forward; pixel centres at integers) and
OpenCV's distortion model (k1, k2, p1, p2, k3): Zhang 2000, "A flexible new technique for camera calibration",
IEEE PAMI 22(11); OpenCV ``calib3d`` documentation. The calibration targets rendered through it are
:mod:`simulators.targets`.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import numpy.typing as npt

from estimation.camera import PinholeCamera

FloatArray = npt.NDArray[np.float64]
Distortion = tuple[float, float, float, float, float]
NO_DISTORTION: Distortion = (0.0, 0.0, 0.0, 0.0, 0.0)

__all__ = ["Distortion", "NO_DISTORTION", "distort_normalized", "undistort_normalized", "LensCamera", "rotation_about"]


def _dist(d: Sequence[float]) -> FloatArray:
    a = np.zeros(5)
    v = np.asarray(d, float).ravel()
    a[:min(5, v.size)] = v[:5]
    return a


def distort_normalized(xy: npt.ArrayLike, distortion: Sequence[float]) -> FloatArray:
    """Apply OpenCV's (k1, k2, p1, p2, k3) model to normalized image coordinates (..., 2)."""
    k1, k2, p1, p2, k3 = _dist(distortion)
    p = np.asarray(xy, float)
    x, y = p[..., 0], p[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def undistort_normalized(xy_distorted: npt.ArrayLike, distortion: Sequence[float], *, iterations: int = 100,
                         tol: float = 1e-13) -> FloatArray:
    """Invert :func:`distort_normalized` by Newton's method (vectorized); exact to ``tol`` for any sane lens.

    Raises ``ValueError`` if some point does not converge (a distortion too strong for its position)."""
    k1, k2, p1, p2, k3 = _dist(distortion)
    target = np.asarray(xy_distorted, float)
    p = target.copy()
    if not np.any(_dist(distortion)):
        return p
    for _ in range(iterations):
        x, y = p[..., 0], p[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)        # d radial / d r2
        f = distort_normalized(p, distortion) - target
        j11 = radial + 2 * x * x * dradial + 2 * p1 * y + 6 * p2 * x
        j12 = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
        j21 = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
        j22 = radial + 2 * y * y * dradial + 6 * p1 * y + 2 * p2 * x
        det = j11 * j22 - j12 * j21
        dx = (j22 * f[..., 0] - j12 * f[..., 1]) / det
        dy = (-j21 * f[..., 0] + j11 * f[..., 1]) / det
        p = p - np.stack([dx, dy], axis=-1)
        if np.all(np.abs(f) < tol):
            break
    err = np.abs(distort_normalized(p, distortion) - target)
    if not np.all(err < 1e-9):
        raise ValueError(f"lens undistortion did not converge (max error {float(np.nanmax(err)):.3g} in "
                         "normalized units): the distortion is too strong for the image corners")
    return p


@dataclass(frozen=True)
class LensCamera:
    """A pinhole camera (``estimation.camera.PinholeCamera``: pose and intrinsics) with OpenCV lens distortion."""

    pinhole: PinholeCamera
    distortion: Distortion = NO_DISTORTION

    @property
    def width_px(self) -> int:
        return self.pinhole.width_px

    @property
    def height_px(self) -> int:
        return self.pinhole.height_px

    def project(self, points_mm: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """World points (..., 3) -> distorted pixel coordinates (..., 2) and depth (...) in mm."""
        c = self.pinhole
        p = np.asarray(points_mm, float)
        xc = (p - c.C) @ c.R.T
        z = xc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = xc[..., :2] / z[..., None]
        d = distort_normalized(xy, self.distortion)
        return np.stack([c.fx_px * d[..., 0] + c.cx_px, c.fy_px * d[..., 1] + c.cy_px], axis=-1), z

    def pixel_directions(self, uv: npt.ArrayLike) -> FloatArray:
        """Unit world directions (..., 3) of the rays through distorted pixel positions ``uv`` (..., 2)."""
        c = self.pinhole
        q = np.asarray(uv, float)
        xd = np.stack([(q[..., 0] - c.cx_px) / c.fx_px, (q[..., 1] - c.cy_px) / c.fy_px], axis=-1)
        xy = undistort_normalized(xd, self.distortion)
        d = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1) @ c.R
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def sample_directions(self, supersample: int = 1) -> FloatArray:
        """Ray directions (H, W, s*s, 3) through an s x s grid of sample points inside every pixel (cached;
        do not modify the returned array)."""
        return _sample_directions(self, int(supersample))

    def _sample_directions(self, supersample: int) -> FloatArray:
        s = int(supersample)
        off = (np.arange(s) + 0.5) / s - 0.5
        v, u = np.mgrid[0:self.height_px, 0:self.width_px].astype(float)
        shape = (self.height_px, self.width_px, s, s)
        su = np.broadcast_to(u[..., None, None] + off[None, None, None, :], shape).reshape(shape[:2] + (s * s,))
        sv = np.broadcast_to(v[..., None, None] + off[None, None, :, None], shape).reshape(shape[:2] + (s * s,))
        return self.pixel_directions(np.stack([su, sv], axis=-1))


@functools.lru_cache(maxsize=3)
def _sample_directions(camera: LensCamera, supersample: int) -> FloatArray:
    d = camera._sample_directions(supersample)
    d.flags.writeable = False
    return d


def rotation_about(axis: npt.ArrayLike, angle_rad: float) -> FloatArray:
    """Rodrigues rotation matrix about ``axis`` by ``angle_rad`` (right-handed)."""
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle_rad) * k + (1 - math.cos(angle_rad)) * (k @ k)
