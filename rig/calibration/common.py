"""Shared geometry of the calibration steps: silhouettes of spheres, rigid and similarity fits, mirror reflection,
angles (the camera model with distortion is :mod:`rig.files.camera_intrinsics`).

Camera conventions: ``estimation.camera`` (OpenCV axes, pixel centres at integers, X_cam = R (X - C)) and
OpenCV's distortion vector (k1, k2, p1, p2, k3) (Zhang 2000; OpenCV ``calib3d`` documentation).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from rig.files.camera_intrinsics import Intrinsics

FloatArray = npt.NDArray[np.float64]

__all__ = ["to_uint8", "split_error", "SphereFit", "sphere_from_silhouette", "fit_transform", "reflect",
           "rotation_angle_deg", "angle_deg"]


def to_uint8(image: npt.ArrayLike, percentile: float = 99.5) -> npt.NDArray[np.uint8]:
    """A linear frame (H, W) or (H, W, 3) as 8-bit grey for feature detectors (scaled to its percentile)."""
    img = np.asarray(image, float)
    if img.ndim == 3:
        img = img.mean(axis=2)
    top = np.percentile(img, percentile)
    if not top > 0:
        return np.zeros(img.shape, np.uint8)
    return np.clip(img / top * 255.0, 0, 255).astype(np.uint8)


def angle_deg(a: npt.ArrayLike, b: npt.ArrayLike) -> FloatArray:
    """Angle (deg) between vectors (..., 3)."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    c = np.sum(a * b, -1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def rotation_angle_deg(R1: npt.ArrayLike, R2: npt.ArrayLike) -> float:
    """Angle (deg) of the rotation R1 R2^T."""
    M = np.asarray(R1, float) @ np.asarray(R2, float).T
    return float(np.degrees(np.arccos(np.clip((np.trace(M) - 1.0) / 2.0, -1.0, 1.0))))


def split_error(error_mm: npt.ArrayLike, point_mm: npt.ArrayLike, camera_center_mm: npt.ArrayLike
                ) -> dict[str, float]:
    """A position error split into its parts across and along the camera's line of sight to ``point_mm``
    (a silhouette pins a sphere's centre across the view far better than along it)."""
    e = np.asarray(error_mm, float)
    v = np.asarray(point_mm, float) - np.asarray(camera_center_mm, float)
    v /= np.linalg.norm(v)
    along = float(e @ v)
    return {"total_mm": float(np.linalg.norm(e)), "across_view_mm": float(np.linalg.norm(e - along * v)),
            "along_view_mm": along}


def reflect(d: npt.ArrayLike, n: npt.ArrayLike) -> FloatArray:
    """Mirror reflection of directions ``d`` about unit normals ``n``: d - 2 (d.n) n."""
    d = np.asarray(d, float)
    n = np.asarray(n, float)
    return d - 2.0 * np.sum(d * n, -1, keepdims=True) * n


# ---------------------------------------------------------------------------------------------- silhouettes
@dataclass(frozen=True)
class SphereFit:
    """A sphere located from its silhouette: centre in the camera frame (mm), the image-cone half-angle, the
    edge points used and the RMS of their angular residuals expressed in pixels."""

    center_cam_mm: FloatArray
    half_angle_rad: float
    edge_px: FloatArray
    rms_px: float
    inliers: int
    radius_px: float

    def to_dict(self) -> dict[str, Any]:
        return {"center_cam_mm": self.center_cam_mm.tolist(), "half_angle_deg": float(np.degrees(self.half_angle_rad)),
                "edge_points": int(len(self.edge_px)), "inliers": self.inliers, "rms_px": self.rms_px,
                "radius_px": self.radius_px}


def _edge_points(img: FloatArray, rays: int = 360) -> tuple[FloatArray, float, FloatArray]:
    """Sub-pixel points on the outline of the brightest blob: along ``rays`` radial profiles from its centroid,
    where the profile crosses halfway between its inner and outer levels (unbiased for a symmetric PSF)."""
    import cv2
    from scipy.ndimage import map_coordinates

    top = np.percentile(img, 99.0)
    if not top > 0:
        raise ValueError("silhouette frame is dark: nothing to fit")
    mask = (img > 0.3 * top).astype(np.uint8)
    n, labels, stats, cents = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n < 2:
        raise ValueError("silhouette frame: no bright region found")
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    c0 = cents[k]
    r0 = float(np.sqrt(stats[k, cv2.CC_STAT_AREA] / np.pi))
    if r0 < 5:
        raise ValueError(f"silhouette too small ({r0:.1f} px radius) to fit")
    ang = 2 * np.pi * np.arange(rays) / rays
    rr = np.arange(0.55 * r0, 1.45 * r0, 0.1)
    us = c0[0] + np.cos(ang)[:, None] * rr[None, :]
    vs = c0[1] + np.sin(ang)[:, None] * rr[None, :]
    prof = map_coordinates(img, [vs, us], order=1, mode="constant", cval=np.nan)
    inner = np.nanmedian(prof[:, (rr > 0.6 * r0) & (rr < 0.85 * r0)], axis=1)
    outer = np.nanmedian(prof[:, (rr > 1.2 * r0) & (rr < 1.4 * r0)], axis=1)
    mid = 0.5 * (inner + outer)
    pts = []
    for i in range(rays):
        p = prof[i]
        if not (np.isfinite(mid[i]) and inner[i] > 2 * max(outer[i], 0) + 1e-12):
            continue
        start = int(np.searchsorted(rr, 0.85 * r0))
        below = np.flatnonzero(p[start:] < mid[i])
        if not below.size:
            continue
        j = start + below[0]
        a, b = p[j - 1], p[j]
        f = (a - mid[i]) / (a - b) if a != b else 0.5
        r = rr[j - 1] + f * (rr[j] - rr[j - 1])
        pts.append((c0[0] + np.cos(ang[i]) * r, c0[1] + np.sin(ang[i]) * r))
    if len(pts) < 12:
        raise ValueError(f"silhouette: only {len(pts)} edge points found")
    return np.asarray(pts), r0, c0


def sphere_from_silhouette(image: npt.ArrayLike, intrinsics: Intrinsics, radius_mm: float, *, rays: int = 360,
                           reject_sigma: float = 4.0) -> SphereFit:
    """Locate a sphere of known ``radius_mm`` from its image outline (its brightest blob in ``image``).

    The outline of a sphere is where the viewing cone with apex at the camera centre touches it: the undistorted
    edge rays r_i make a constant angle alpha with the cone axis a (the direction to the centre), and
    |centre| = radius / sin(alpha). a and alpha are fitted by robust least squares on angle(r_i, a) - alpha
    (outliers beyond ``reject_sigma`` MADs, e.g. highlights crossing the outline, are dropped and the fit
    repeated). Exact under perspective and lens distortion (no ellipse approximation)."""
    from scipy.optimize import least_squares

    img = np.asarray(image, float)
    if img.ndim == 3:
        img = img.mean(axis=2)
    edge, r0, _ = _edge_points(img, rays)
    ray = intrinsics.rays(edge)
    a0 = ray.mean(axis=0)
    a0 /= np.linalg.norm(a0)
    e1 = np.cross(a0, [0.0, 1.0, 0.0] if abs(a0[1]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a0, e1)

    def axis(x: FloatArray) -> FloatArray:
        a = a0 + x[0] * e1 + x[1] * e2
        return a / np.linalg.norm(a)

    def resid(x: FloatArray, r: FloatArray) -> FloatArray:
        return np.arccos(np.clip(r @ axis(x), -1.0, 1.0)) - x[2]

    alpha0 = float(np.mean(np.arccos(np.clip(ray @ a0, -1, 1))))
    keep = np.ones(len(ray), bool)
    x = np.array([0.0, 0.0, alpha0])
    for _ in range(3):
        x = least_squares(resid, x, args=(ray[keep],), method="lm", xtol=1e-15, ftol=1e-15).x
        res = resid(x, ray)
        mad = 1.4826 * np.median(np.abs(res[keep] - np.median(res[keep])))
        new = np.abs(res) <= reject_sigma * max(mad, 1e-9)
        if np.array_equal(new, keep):
            break
        keep = new
    a, alpha = axis(x), float(x[2])
    rms = float(np.sqrt(np.mean(resid(x, ray[keep]) ** 2)) * intrinsics.fx_px)
    center = a * radius_mm / np.sin(alpha)
    return SphereFit(center, alpha, edge, rms, int(keep.sum()), r0)


# ---------------------------------------------------------------------------------------------- point sets
def fit_transform(src: npt.ArrayLike, dst: npt.ArrayLike, *, scale: bool = False
                  ) -> tuple[FloatArray, FloatArray, float]:
    """Least-squares rigid (or similarity, ``scale=True``) transform with dst ~ s R src + t (Umeyama 1991,
    "Least-squares estimation of transformation parameters between two point patterns", IEEE PAMI 13(4)).
    Returns (R, t, s)."""
    a = np.asarray(src, float)
    b = np.asarray(dst, float)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 3 or len(a) < 3:
        raise ValueError(f"fit_transform: need two (N, 3) point sets with N >= 3, got {a.shape} and {b.shape}")
    ma, mb = a.mean(0), b.mean(0)
    A, B = a - ma, b - mb
    U, S, Vt = np.linalg.svd(B.T @ A / len(a))
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1.0
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (np.sum(A * A) / len(a))) if scale else 1.0
    t = mb - s * R @ ma
    return R, t, s
