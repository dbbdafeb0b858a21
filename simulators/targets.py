"""Calibration targets of the simulated rig, rendered through a pinhole camera with lens distortion.

The simulated world of issue 7 (``docs/calibration.md``): a *true* rig that differs from the design file by
known amounts (camera intrinsics, Brown-Conrady distortion and pose; LED positions moved by a rigid transform
plus mounting scatter; per-LED, per-channel LED gains; a polarizer extinction ratio; a black-level pedestal
the DNG does not declare; a sensor nonlinearity) and the calibration targets an operator would place in the
sphere:

- a ChArUco board (OpenCV ``aruco`` texture, ray-cast per sample onto the board plane, so distortion is exact),
- plates carrying ArUco markers whose centres hold total-station reflectors (the camera-pose targets),
- a mirror (chrome) ball: each lit LED is a finite disc whose reflection point is found by fixed-point
  iteration of the bisector condition (Alhazen's problem); the LED's image is splatted with the energy
  R x L_led x (its image area), plus a faint diffuse residue; crossed polarizers pass ``extinction_ratio`` of
  the specular light (Debevec 1998 light probes; Ma et al. 2007 for the polarization),
- a diffuse (Lambertian) sphere and a flat Spectralon tile lit by point LEDs (radiance rho/pi E),
- a translucent reference sphere rendered by ``simulators.scene.render`` (pinhole) and resampled through the
  lens distortion.

Radiance images are in the same linear units as :mod:`simulators.camera` (radiance = emission x geometry),
blurred by a Gaussian lens PSF, and exposed by :func:`expose_raw` (photon and read noise, a black-level
pedestal, a quadratic nonlinearity) into the RGGB mosaic the simulated camera writes as a DNG, so the
calibration reads them exactly as it would real frames. The camera with lens distortion is :mod:`simulators.lens`. :meth:`TargetWorld.attach` makes a running
:class:`simulators.camera.SimulatedCamera` render the current target instead of its object.

Camera conventions follow :mod:`estimation.camera` (OpenCV axes: x right, y down, z forward; pixel centres at
integers) and OpenCV's distortion model (k1, k2, p1, p2, k3): Zhang 2000, "A flexible new technique for camera
calibration", IEEE PAMI 22(11); OpenCV ``calib3d`` documentation.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from drivers.contracts import Polarization
from estimation.camera import PinholeCamera, intersect_sphere

from .lens import (NO_DISTORTION, Distortion, LensCamera, distort_normalized, rotation_about,
                   undistort_normalized)

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "Distortion", "NO_DISTORTION", "distort_normalized", "undistort_normalized", "LensCamera",
    "lambert_irradiance", "polarization_factors", "CharucoBoardTarget", "MarkerPlate", "MarkerPlatesTarget",
    "MirrorBallTarget", "DiffuseSphereTarget", "TileTarget", "TranslucentSphereTarget", "DarkTarget",
    "expose_raw", "CalibrationTruth", "TargetWorld", "rotation_about", "charuco_poses", "resample_through_distortion",
]


# ----------------------------------------------------------------------------------------------- shading
def polarization_factors(polarization: Polarization, extinction_ratio: float) -> tuple[float, float]:
    """(diffuse, specular) transmission of the polarizer pair: depolarized diffuse light is halved by any
    analyzer; specular light keeps the source polarization, so it passes parallel and is reduced to
    ``extinction_ratio`` crossed (Ma et al. 2007; science.md sec. 3). Without polarizers both pass."""
    pol = Polarization(polarization)
    if pol == Polarization.NONE:
        return 1.0, 1.0
    if pol == Polarization.PARALLEL:
        return 0.5, 1.0
    return 0.5, float(extinction_ratio)


def lambert_irradiance(points_mm: FloatArray, normals: FloatArray, led_positions_mm: FloatArray,
                       emission: FloatArray, *, chunk: int = 48) -> FloatArray:
    """Irradiance (P, 3) on surface points from point LEDs: sum_l I_l max(0, n.w_l) / d_l^2 (lit LEDs only)."""
    pts = np.asarray(points_mm, float).reshape(-1, 3)
    nrm = np.asarray(normals, float).reshape(-1, 3)
    out = np.zeros((len(pts), 3))
    lit = np.flatnonzero(np.any(emission > 0, axis=1))
    for start in range(0, len(lit), chunk):
        idx = lit[start:start + chunk]
        d = led_positions_mm[idx][None, :, :] - pts[:, None, :]
        dist2 = np.einsum("plk,plk->pl", d, d)
        cos = np.maximum(np.einsum("plk,pk->pl", d, nrm), 0.0) / np.sqrt(dist2)
        out += (cos / dist2) @ emission[idx]
    return out


def _plane_hits(origin: FloatArray, dirs: FloatArray, center: FloatArray, normal: FloatArray
                ) -> tuple[FloatArray, FloatArray]:
    """Ray parameters t (...) and hit points (..., 3) of rays with a plane; t = inf where parallel/behind."""
    denom = dirs @ normal
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((center - origin) @ normal) / denom
    t = np.where((np.abs(denom) > 1e-12) & (t > 0), t, np.inf)
    return t, origin + np.where(np.isfinite(t), t, 0.0)[..., None] * dirs


def _bilinear_grid(values: FloatArray, gu: FloatArray, gv: FloatArray, u: FloatArray, v: FloatArray
                   ) -> FloatArray:
    """Bilinear interpolation of ``values`` (nu, nv, C) sampled on the regular grid gu x gv at (u, v)."""
    fu = np.clip((u - gu[0]) / (gu[-1] - gu[0]) * (len(gu) - 1), 0, len(gu) - 1 - 1e-9)
    fv = np.clip((v - gv[0]) / (gv[-1] - gv[0]) * (len(gv) - 1), 0, len(gv) - 1 - 1e-9)
    i, j = fu.astype(int), fv.astype(int)
    a, b = (fu - i)[..., None], (fv - j)[..., None]
    return ((1 - a) * (1 - b) * values[i, j] + a * (1 - b) * values[i + 1, j] + (1 - a) * b * values[i, j + 1]
            + a * b * values[i + 1, j + 1])


def _plane_irradiance(center: FloatArray, ax_u: FloatArray, ax_v: FloatArray, normal: FloatArray,
                      half_u: float, half_v: float, leds: FloatArray, emission: FloatArray, u: FloatArray,
                      v: FloatArray, grid: int = 9) -> FloatArray:
    """Irradiance on a plane at local coordinates (u, v) mm, from a ``grid`` x ``grid`` exact evaluation
    interpolated bilinearly (the LEDs are ~1 m away: the field is smooth over a target)."""
    gu = np.linspace(-half_u, half_u, grid)
    gv = np.linspace(-half_v, half_v, grid)
    pts = center + gu[:, None, None] * ax_u + gv[None, :, None] * ax_v
    e = lambert_irradiance(pts.reshape(-1, 3), np.broadcast_to(normal, (grid * grid, 3)), leds, emission)
    return _bilinear_grid(e.reshape(grid, grid, 3), gu, gv, u, v)


def _prefiltered(texture: npt.NDArray[np.uint8], black: float, white: float, sigma_texels: float
                 ) -> npt.NDArray[np.float32]:
    import cv2

    a = (black + (white - black) * texture.astype(np.float32) / 255.0).astype(np.float32)
    return cv2.GaussianBlur(a, (0, 0), sigma_texels) if sigma_texels > 0 else a


def _sample_map(albedo: npt.NDArray[np.float32], col: FloatArray, row: FloatArray, valid: npt.NDArray[np.bool_]
                ) -> FloatArray:
    """Bilinear samples of ``albedo`` at continuous texel coordinates (texel i spans [i, i + 1)); 0 outside."""
    import cv2

    shape = col.shape
    n = int(np.prod(shape))
    width = 4096                                     # cv2.remap maps must stay below 32767 columns
    pad = (-n) % width
    mx = np.concatenate([np.where(valid, col - 0.5, -10.0).ravel(), np.full(pad, -10.0)]).astype(np.float32)
    my = np.concatenate([np.where(valid, row - 0.5, -10.0).ravel(), np.full(pad, -10.0)]).astype(np.float32)
    out = cv2.remap(albedo, mx.reshape(-1, width), my.reshape(-1, width), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    return out.ravel()[:n].reshape(shape).astype(np.float64)


# ----------------------------------------------------------------------------------------------- targets
class _Target:
    """A calibration target: ``render(camera, leds, emission, polarization) -> radiance (H, W, 3)``."""

    kind = "target"

    def render(self, camera: LensCamera, led_positions_mm: FloatArray, emission: FloatArray,
               polarization: Polarization) -> FloatArray:  # pragma: no cover - interface
        raise NotImplementedError


@dataclass
class DarkTarget(_Target):
    """Nothing in front of the camera (lens cap / empty sphere with black velvet)."""

    kind = "dark"

    def render(self, camera: LensCamera, led_positions_mm: FloatArray, emission: FloatArray,
               polarization: Polarization) -> FloatArray:
        return np.zeros((camera.height_px, camera.width_px, 3))


@dataclass
class CharucoBoardTarget(_Target):
    """A flat ChArUco board printed on a matte white plate, in one of several poses (the operator moves it).

    Board frame as OpenCV's ``CharucoBoard``: origin at the top-left chessboard corner, x along the columns,
    y along the rows, z into the board; ``poses`` are (R, t) with X_world = R @ X_board + t (mm).
    ``margin_mm``: white border of the plate around the squares."""

    squares_x: int
    squares_y: int
    square_mm: float
    marker_mm: float
    dictionary_id: int
    poses: list[tuple[FloatArray, FloatArray]]
    albedo_white: float = 0.85
    albedo_black: float = 0.03
    margin_mm: float = 6.0
    texture_px_per_mm: float = 16.0
    supersample: int = 2
    prefilter_texels: float = 1.2
    pose_index: int = 0
    kind = "charuco"
    _texture: npt.NDArray[np.uint8] | None = field(default=None, repr=False)
    _albedo: npt.NDArray[np.float32] | None = field(default=None, repr=False)

    def board(self) -> Any:
        import cv2

        d = cv2.aruco.getPredefinedDictionary(self.dictionary_id)
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_mm, self.marker_mm, d)

    def _grid(self) -> tuple[int, int, float]:
        """(texels per square, margin texels, texels per mm): a whole number of texels per square, so that the
        texture's squares are exactly ``square_mm`` wide (a rounded board width would shrink the board)."""
        n_sq = max(8, int(round(self.square_mm * self.texture_px_per_mm)))
        ppm = n_sq / self.square_mm
        return n_sq, int(round(self.margin_mm * ppm)), ppm

    def texture(self) -> npt.NDArray[np.uint8]:
        """The plate's texture (rows, cols) in 0..255, margin included (:meth:`_grid` texels per mm)."""
        if self._texture is None:
            n_sq, margin, _ = self._grid()
            w = self.squares_x * n_sq + 2 * margin
            h = self.squares_y * n_sq + 2 * margin
            self._texture = self.board().generateImage((w, h), marginSize=margin, borderBits=1)
        return self._texture

    def corners_world(self, pose_index: int | None = None) -> FloatArray:
        """True rig-frame positions (K, 3) of the board's chessboard corners in ``pose_index``."""
        R, t = self.poses[self.pose_index if pose_index is None else pose_index]
        return np.asarray(self.board().getChessboardCorners(), float) @ np.asarray(R).T + np.asarray(t)

    def albedo_map(self) -> npt.NDArray[np.float32]:
        """The plate's albedo on the texture grid, pre-filtered (Gaussian, ``prefilter_texels``) so that bilinear
        sampling is band-limited: edges then land at exact sub-pixel positions (no sample quantization)."""
        if self._albedo is None:
            self._albedo = _prefiltered(self.texture(), self.albedo_black, self.albedo_white, self.prefilter_texels)
        return self._albedo

    def render(self, camera: LensCamera, led_positions_mm: FloatArray, emission: FloatArray,
               polarization: Polarization) -> FloatArray:
        R, t = (np.asarray(a, float) for a in self.poses[self.pose_index])
        dirs = camera.sample_directions(self.supersample)
        origin = camera.pinhole.C
        normal = R[:, 2]
        tt, hit = _plane_hits(origin, dirs, t, normal)
        local = (hit - t) @ R                                   # board coordinates (mm)
        w_mm, h_mm = self.squares_x * self.square_mm, self.squares_y * self.square_mm
        _, margin, ppm = self._grid()
        m = margin / ppm
        albedo = _sample_map(self.albedo_map(), (local[..., 0] + m) * ppm, (local[..., 1] + m) * ppm,
                             np.isfinite(tt))
        cx, cy = w_mm / 2.0, h_mm / 2.0
        e = _plane_irradiance(t + R[:, 0] * cx + R[:, 1] * cy, R[:, 0], R[:, 1], -normal, cx + m, cy + m,
                              led_positions_mm, emission, local[..., 0] - cx, local[..., 1] - cy)
        kd, _ = polarization_factors(polarization, 0.0)
        rad = kd * albedo[..., None] / np.pi * e
        return rad.mean(axis=2)


@dataclass(frozen=True)
class MarkerPlate:
    """A matte survey plate: a black-and-white quadrant target (``target_mm`` square, its centre a saddle point)
    over a total-station reflector at ``center_mm``, with ArUco marker ``marker_id`` (``marker_mm``) to its left
    that names the plate. The plate faces ``normal``; 'up' is ``up``; ``margin_mm`` of white around and between
    the two."""

    marker_id: int
    center_mm: tuple[float, float, float]
    normal: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    marker_mm: float = 10.0
    target_mm: float = 10.0
    margin_mm: float = 3.0

    def axes(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(x right, y down, n) of the plate as seen from the side its normal points to."""
        n = np.asarray(self.normal, float)
        n = n / np.linalg.norm(n)
        up = np.asarray(self.up, float)
        x = np.cross(up, n)         # seen from +n: right = up x n
        x /= np.linalg.norm(x)
        y = np.cross(x, n)          # down (minus the component of 'up' across the plate)
        return x, y, n

    def marker_center_local_mm(self) -> tuple[float, float]:
        """The marker's centre in plate coordinates (x right, y down, origin at the reflector)."""
        return -(self.target_mm / 2 + self.margin_mm + self.marker_mm / 2), 0.0


@dataclass
class MarkerPlatesTarget(_Target):
    """Several :class:`MarkerPlate` s (the camera-pose targets of the rig-frame step)."""

    plates: list[MarkerPlate]
    dictionary_id: int
    albedo_white: float = 0.85
    albedo_black: float = 0.03
    supersample: int = 2
    texture_px_per_mm: float = 16.0
    prefilter_texels: float = 1.2
    kind = "marker_plates"
    _maps: dict[int, tuple[npt.NDArray[np.float32], float, float, float]] = field(default_factory=dict, repr=False)

    def albedo_map(self, plate: MarkerPlate) -> tuple[npt.NDArray[np.float32], float, float, float]:
        """(pre-filtered albedo texture, texels per mm, column and row of the reflector in texels). Whole texel
        counts per feature keep the marker ``marker_mm`` wide and the quadrant centre exactly on a texel corner."""
        if plate.marker_id not in self._maps:
            import cv2

            n_m = max(16, int(round(plate.marker_mm * self.texture_px_per_mm)))
            ppm = n_m / plate.marker_mm
            n_t = 2 * max(4, int(round(plate.target_mm * ppm / 2)))             # even: a centre on a texel edge
            n_g = int(round(plate.margin_mm * ppm))
            h = max(n_m, n_t) + 2 * n_g
            h += (h - n_t) % 2
            w = n_g + n_m + n_g + n_t + n_g
            tex = np.full((h, w), 255, np.uint8)
            d = cv2.aruco.getPredefinedDictionary(self.dictionary_id)
            om = (h - n_m) // 2
            tex[om:om + n_m, n_g:n_g + n_m] = cv2.aruco.generateImageMarker(d, plate.marker_id, n_m, borderBits=1)
            rt, ct = (h - n_t) // 2, 2 * n_g + n_m
            q = n_t // 2
            tex[rt:rt + q, ct:ct + q] = 0
            tex[rt + q:rt + n_t, ct + q:ct + n_t] = 0
            col0, row0 = ct + q, rt + q
            amap = _prefiltered(tex, self.albedo_black, self.albedo_white, self.prefilter_texels)
            self._maps[plate.marker_id] = (amap, ppm, float(col0), float(row0))
        return self._maps[plate.marker_id]

    def render(self, camera: LensCamera, led_positions_mm: FloatArray, emission: FloatArray,
               polarization: Polarization) -> FloatArray:
        dirs = camera.sample_directions(self.supersample)
        origin = camera.pinhole.C
        best_t = np.full(dirs.shape[:-1], np.inf)
        albedo = np.zeros(dirs.shape[:-1])
        light = np.zeros(dirs.shape[:-1] + (3,))
        for plate in self.plates:
            x, y, n = plate.axes()
            c = np.asarray(plate.center_mm, float)
            t, hit = _plane_hits(origin, dirs, c, n)
            lu, lv = (hit - c) @ x, (hit - c) @ y
            amap, ppm, col0, row0 = self.albedo_map(plate)
            col, row = col0 + lu * ppm, row0 + lv * ppm
            on = np.isfinite(t) & (col > -16) & (row > -16) & (col < amap.shape[1] + 16) & \
                (row < amap.shape[0] + 16) & (t < best_t)
            if not on.any():
                continue
            a = _sample_map(amap, col, row, on)
            e = lambert_irradiance(c[None, :], n[None, :], led_positions_mm, emission)[0]
            best_t = np.where(on, t, best_t)
            albedo = np.where(on, a, albedo)
            light = np.where(on[..., None], e, light)
        kd, _ = polarization_factors(polarization, 0.0)
        return (kd * albedo[..., None] / np.pi * light).mean(axis=2)


def _sphere_irradiance(center: FloatArray, radius: float, points_mm: FloatArray, led_positions_mm: FloatArray,
                       emission: FloatArray, *, exact_below: int = 16) -> FloatArray:
    """Irradiance (P, 3) on sphere points: exact when few LEDs are lit (single-LED frames: the terminator is
    sharp), else bilinear in (polar, azimuth) from a 2 degree table of the exact values (many LEDs: smooth)."""
    normals = (points_mm - center) / radius
    if np.count_nonzero(np.any(emission > 0, axis=1)) <= exact_below:
        return lambert_irradiance(points_mm, normals, led_positions_mm, emission)
    th = np.linspace(0.0, np.pi, 91)
    ph = np.linspace(-np.pi, np.pi, 181)
    T, P = np.meshgrid(th, ph, indexing="ij")
    n = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
    table = lambert_irradiance(center + radius * n, n, led_positions_mm, emission).reshape(len(th), len(ph), 3)
    theta = np.arccos(np.clip(normals[:, 2], -1.0, 1.0))
    phi = np.arctan2(normals[:, 1], normals[:, 0])
    return _bilinear_grid(table, th, ph, theta, phi)


def _sphere_samples(camera: LensCamera, center: FloatArray, radius: float, supersample: int
                    ) -> tuple[FloatArray, npt.NDArray[np.bool_], FloatArray]:
    dirs = camera.sample_directions(supersample)
    origin = np.broadcast_to(camera.pinhole.C, dirs.shape)
    pts, hit = intersect_sphere(origin, dirs, center, radius)
    return pts, hit, dirs


@dataclass
class DiffuseSphereTarget(_Target):
    """A Lambertian sphere (painted ball / Spectralon sphere) of per-channel ``albedo``."""

    center_mm: tuple[float, float, float]
    radius_mm: float
    albedo: tuple[float, float, float] = (0.99, 0.99, 0.99)
    supersample: int = 3
    kind = "diffuse_sphere"

    def render(self, camera: LensCamera, led_positions_mm: FloatArray, emission: FloatArray,
               polarization: Polarization) -> FloatArray:
        c = np.asarray(self.center_mm, float)
        pts, hit, _ = _sphere_samples(camera, c, self.radius_mm, self.supersample)
        out = np.zeros(hit.shape + (3,))
        e = _sphere_irradiance(c, self.radius_mm, pts[hit], led_positions_mm, emission)
        kd, _ = polarization_factors(polarization, 0.0)
        out[hit] = kd * np.asarray(self.albedo) / np.pi * e
        return out.mean(axis=2)


def _reflection_points(camera_center: FloatArray, center: FloatArray, radius: float, sources: FloatArray,
                       iterations: int = 100) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
    """Points (S, 3) on a mirror sphere where light from ``sources`` (S, 3) reflects into the camera.

    Fixed point of the bisector condition n = normalize(normalize(C - p) + normalize(S - p)), p = c + r n
    (Alhazen's problem for a sphere); returns a convergence mask (sources almost exactly behind the ball
    graze its limb and do not converge)."""
    to_cam = camera_center - center
    to_src = sources - center
    n = to_cam / np.linalg.norm(to_cam) + to_src / np.linalg.norm(to_src, axis=-1, keepdims=True)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    active = np.ones(len(sources), bool)
    step = np.full(len(sources), np.inf)
    for _ in range(iterations):
        a_idx = np.flatnonzero(active)
        if not len(a_idx):
            break
        p = center + radius * n[a_idx]
        a = camera_center - p
        b = sources[a_idx] - p
        m = a / np.linalg.norm(a, axis=-1, keepdims=True) + b / np.linalg.norm(b, axis=-1, keepdims=True)
        nn = m / np.linalg.norm(m, axis=-1, keepdims=True)
        step[a_idx] = np.linalg.norm(nn - n[a_idx], axis=-1)
        n[a_idx] = nn
        active[a_idx] = step[a_idx] >= 1e-15
    ok = step < 1e-10
    return center + radius * n, ok


@dataclass
class MirrorBallTarget(_Target):
    """A chrome ball: specular reflectance ``specular`` (R, G, B) plus a faint Lambertian residue
    ``diffuse_albedo`` (dust, micro-scratches: this is what makes its outline visible cross-polarized).

    Each lit LED is a Lambertian disc of radius ``led_radius_mm`` facing the sphere's centre with radiance
    L = I / (pi r_led^2) (so its intensity is I). Its image in the ball is found by reflecting
    ``disc_samples`` points of the disc (Alhazen's problem); the highlight carries the energy
    specular x L x (area of the disc's image in px^2), splatted bilinearly at the sample images (a sub-pixel
    spot, which the lens PSF then spreads)."""

    center_mm: tuple[float, float, float]
    radius_mm: float
    specular: tuple[float, float, float] = (0.62, 0.60, 0.58)
    diffuse_albedo: float = 0.05
    extinction_ratio: float = 1.0 / 500.0
    led_radius_mm: float = 6.0
    supersample: int = 3
    disc_rings: int = 3
    kind = "mirror_ball"

    def _disc(self, led: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Sample points (S, M, 3) on each LED disc (facing the ball) and boundary points (S, B, 3)."""
        c = np.asarray(self.center_mm, float)
        n = c - led
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        helper = np.where(np.abs(n[:, 2:3]) < 0.9, np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
        e1 = np.cross(n, helper)
        e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
        e2 = np.cross(n, e1)
        pts = [np.zeros(2)]
        for k in range(1, self.disc_rings + 1):
            rr = k / (self.disc_rings + 0.5)
            m = 6 * k
            a = 2 * np.pi * (np.arange(m) + 0.5 * (k % 2)) / m
            pts += list(rr * np.stack([np.cos(a), np.sin(a)], axis=-1))
        uv = np.asarray(pts) * self.led_radius_mm                                   # (M, 2)
        a = 2 * np.pi * np.arange(24) / 24
        bd = np.stack([np.cos(a), np.sin(a)], axis=-1) * self.led_radius_mm         # (B, 2)
        mk = lambda q: led[:, None, :] + q[None, :, 0:1] * e1[:, None, :] + q[None, :, 1:2] * e2[:, None, :]
        return mk(uv), mk(bd)

    def highlight_energy(self, camera: LensCamera, led_positions_mm: FloatArray, emission: FloatArray
                         ) -> tuple[FloatArray, FloatArray, npt.NDArray[np.bool_]]:
        """Per lit LED: sample image positions (S, M, 2), energy per sample (S, 3) in radiance x px^2, and
        the LEDs' indices (S,) among ``led_positions_mm``; unpolarized specular (before the analyzer)."""
        lit = np.flatnonzero(np.any(emission > 0, axis=1))
        if len(lit) == 0:
            return np.zeros((0, 1, 2)), np.zeros((0, 3)), lit
        c = np.asarray(self.center_mm, float)
        leds = led_positions_mm[lit]
        samples, boundary = self._disc(leds)
        S, M, _ = samples.shape
        C = camera.pinhole.C
        p_s, ok_s = _reflection_points(C, c, self.radius_mm, samples.reshape(-1, 3))
        p_b, ok_b = _reflection_points(C, c, self.radius_mm, boundary.reshape(-1, 3))
        uv_s = camera.project(p_s)[0].reshape(S, M, 2)
        uv_b = camera.project(p_b)[0].reshape(S, -1, 2)
        x, y = uv_b[..., 0], uv_b[..., 1]
        area = 0.5 * np.abs(np.sum(x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y, axis=1))
        ok = ok_s.reshape(S, M).all(axis=1) & ok_b.reshape(S, -1).all(axis=1)
        radiance = emission[lit] / (np.pi * self.led_radius_mm ** 2)                # (S, 3)
        energy = np.asarray(self.specular) * radiance * area[:, None] / M
        energy[~ok] = 0.0
        return uv_s, energy, lit

    def true_highlights(self, camera: LensCamera, led_positions_mm: FloatArray) -> FloatArray:
        """Distorted pixel positions (N, 2) of the reflection of every LED's centre (diagnostics)."""
        p, ok = _reflection_points(camera.pinhole.C, np.asarray(self.center_mm, float), self.radius_mm,
                                   np.asarray(led_positions_mm, float))
        uv = camera.project(p)[0]
        uv[~ok] = np.nan
        return uv

    def render(self, camera: LensCamera, led_positions_mm: FloatArray, emission: FloatArray,
               polarization: Polarization) -> FloatArray:
        c = np.asarray(self.center_mm, float)
        kd, ks = polarization_factors(polarization, self.extinction_ratio)
        pts, hit, _ = _sphere_samples(camera, c, self.radius_mm, self.supersample)
        out = np.zeros(hit.shape + (3,))
        e = _sphere_irradiance(c, self.radius_mm, pts[hit], led_positions_mm, emission)
        out[hit] = kd * self.diffuse_albedo / np.pi * e
        img = out.mean(axis=2)
        uv, energy, _ = self.highlight_energy(camera, led_positions_mm, emission)
        if len(energy):
            H, W = img.shape[:2]
            u = uv[..., 0].ravel()
            v = uv[..., 1].ravel()
            en = np.repeat(energy * ks, uv.shape[1], axis=0)
            i0, j0 = np.floor(v).astype(int), np.floor(u).astype(int)
            fy, fx = v - i0, u - j0
            for di, dj, w in ((0, 0, (1 - fy) * (1 - fx)), (0, 1, (1 - fy) * fx), (1, 0, fy * (1 - fx)),
                              (1, 1, fy * fx)):
                ii, jj = i0 + di, j0 + dj
                keep = (ii >= 0) & (jj >= 0) & (ii < H) & (jj < W) & np.isfinite(w)
                np.add.at(img, (ii[keep], jj[keep]), en[keep] * w[keep, None])
        return img


@dataclass
class TileTarget(_Target):
    """A flat square Lambertian reference (Spectralon tile, ColorChecker patch) of ``size_mm``."""

    center_mm: tuple[float, float, float]
    normal: tuple[float, float, float]
    size_mm: float = 50.0
    albedo: tuple[float, float, float] = (0.99, 0.99, 0.99)
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    supersample: int = 2
    kind = "tile"

    def render(self, camera: LensCamera, led_positions_mm: FloatArray, emission: FloatArray,
               polarization: Polarization) -> FloatArray:
        x, y, n = MarkerPlate(0, self.center_mm, self.normal, self.up).axes()
        c = np.asarray(self.center_mm, float)
        dirs = camera.sample_directions(self.supersample)
        t, hit = _plane_hits(camera.pinhole.C, dirs, c, n)
        lu, lv = (hit - c) @ x, (hit - c) @ y
        half = self.size_mm / 2.0
        on = np.isfinite(t) & (np.abs(lu) <= half) & (np.abs(lv) <= half)
        e = _plane_irradiance(c, x, y, n, half, half, led_positions_mm, emission, lu, lv)
        kd, _ = polarization_factors(polarization, 0.0)
        rad = np.where(on[..., None], kd * np.asarray(self.albedo) / np.pi * e, 0.0)
        return rad.mean(axis=2)


@dataclass
class TranslucentSphereTarget(_Target):
    """A sphere of known translucent material (``simulators.scene.SphereObject``), rendered by
    ``simulators.scene.render`` through the undistorted pinhole and resampled through the lens distortion."""

    obj: Any                      # simulators.scene.SphereObject
    kind = "translucent_sphere"

    def render(self, camera: LensCamera, led_positions_mm: FloatArray, emission: FloatArray,
               polarization: Polarization) -> FloatArray:
        from .scene import render

        img = render(self.obj, camera.pinhole, led_positions_mm, emission, polarization).radiance
        if not np.any(camera.distortion):
            return img
        return resample_through_distortion(img, camera)


def resample_through_distortion(pinhole_image: FloatArray, camera: LensCamera) -> FloatArray:
    """The image a distorted lens records of a scene whose ideal pinhole image is ``pinhole_image``
    (bilinear resampling at the undistorted position of every pixel centre)."""
    from scipy.ndimage import map_coordinates

    c = camera.pinhole
    v, u = np.mgrid[0:c.height_px, 0:c.width_px].astype(float)
    xd = np.stack([(u - c.cx_px) / c.fx_px, (v - c.cy_px) / c.fy_px], axis=-1)
    xy = undistort_normalized(xd, camera.distortion)
    coords = [xy[..., 1] * c.fy_px + c.cy_px, xy[..., 0] * c.fx_px + c.cx_px]
    return np.stack([map_coordinates(pinhole_image[..., k], coords, order=1, mode="constant", cval=0.0)
                     for k in range(pinhole_image.shape[2])], axis=-1)


# ----------------------------------------------------------------------------------------------- sensor
def expose_raw(radiance: FloatArray, exposure_s: float, sensor: Any, rng: np.random.Generator, *,
               black_offset_dn: float = 0.0, nonlinearity: float = 0.0) -> npt.NDArray[np.uint16]:
    """Radiance (H, W, 3) -> RGGB mosaic (2H, 2W) uint16 like :func:`simulators.camera.expose`, plus a
    pedestal ``black_offset_dn`` above the declared black level and a quadratic response
    s' = s (1 - nonlinearity s / span) (span = white - black) applied to the photo signal before noise."""
    from .sensor import signal_mosaic

    span = float(sensor.white_level_dn - sensor.black_level_dn)
    signal_dn = np.maximum(signal_mosaic(radiance) * sensor.gain_dn_per_unit * exposure_s, 0.0)
    if nonlinearity:
        signal_dn = signal_dn * (1.0 - nonlinearity * np.minimum(signal_dn, span) / span)
    electrons = rng.poisson(signal_dn * sensor.electrons_per_dn)
    dn = electrons / sensor.electrons_per_dn + rng.normal(0.0, sensor.read_noise_dn, signal_dn.shape)
    dn = np.round(dn + sensor.black_level_dn + black_offset_dn)
    return np.clip(dn, 0, sensor.white_level_dn).astype(np.uint16)


# ----------------------------------------------------------------------------------------------- truth
@dataclass
class CalibrationTruth:
    """What the simulated rig really is, next to what the design file says.

    ``led_gains`` (N, 3): true radiant intensity / design intensity per LED and channel.
    ``targets_mm``: every reflector the total station can measure (true rig-frame positions).
    """

    camera: LensCamera
    led_positions_mm: FloatArray
    led_gains: FloatArray
    led_transform: dict[str, Any]
    extinction_ratio: float = 1.0 / 500.0
    psf_sigma_px: float = 0.7
    black_offset_dn: float = 0.0
    nonlinearity: float = 0.0
    led_radius_mm: float = 6.0
    targets_mm: dict[str, tuple[float, float, float]] = field(default_factory=dict)

    @classmethod
    def perturbed(cls, design_camera: PinholeCamera, design_led_positions_mm: npt.ArrayLike, *, seed: int = 0,
                  focal_scale: tuple[float, float] = (1.012, 1.016), principal_offset_px: tuple[float, float] = (
                      3.2, -2.1), distortion: Distortion = (-0.18, 0.22, 6e-4, -4e-4, 0.0),
                  camera_offset_mm: tuple[float, float, float] = (1.6, -2.2, 1.1), camera_rotation_deg: float = 0.45,
                  led_rotation_deg: float = 0.15, led_translation_mm: tuple[float, float, float] = (0.8, -0.6, 1.0),
                  led_scatter_mm: float = 0.6, gain_sigma: float = 0.06,
                  channel_gain: tuple[float, float, float] = (0.96, 1.0, 1.05), **kw: Any) -> "CalibrationTruth":
        """A seeded true rig near the design: intrinsics scaled/shifted, distortion added, camera moved and
        turned, LEDs moved by a rigid transform plus isotropic scatter, lognormal per-LED gains."""
        rng = np.random.default_rng(seed)
        c = design_camera
        axis = rng.normal(size=3)
        Rc = rotation_about(axis, math.radians(camera_rotation_deg)) @ c.R
        pin = PinholeCamera(c.width_px, c.height_px, c.fx_px * focal_scale[0], c.fy_px * focal_scale[1],
                            c.cx_px + principal_offset_px[0], c.cy_px + principal_offset_px[1],
                            tuple(map(tuple, Rc.tolist())), tuple((c.C + np.asarray(camera_offset_mm)).tolist()))
        design = np.asarray(design_led_positions_mm, float)
        Rl = rotation_about(rng.normal(size=3), math.radians(led_rotation_deg))
        tl = np.asarray(led_translation_mm, float)
        leds = design @ Rl.T + tl + rng.normal(0.0, led_scatter_mm, design.shape)
        gains = np.exp(rng.normal(0.0, gain_sigma, design.shape)) * np.asarray(channel_gain)
        return cls(LensCamera(pin, tuple(float(x) for x in distortion)), leds, gains,
                   {"rotation": Rl.tolist(), "translation_mm": tl.tolist(), "scatter_mm": led_scatter_mm}, **kw)

    def led_directions(self) -> FloatArray:
        return self.led_positions_mm / np.linalg.norm(self.led_positions_mm, axis=1, keepdims=True)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able summary (session manifests' ``truth``)."""
        c = self.camera.pinhole
        return {"camera": {"fx_px": c.fx_px, "fy_px": c.fy_px, "cx_px": c.cx_px, "cy_px": c.cy_px,
                           "distortion": list(self.camera.distortion), "rotation": [list(r) for r in c.rotation],
                           "center_mm": list(c.center_mm)},
                "led_positions_mm": self.led_positions_mm.tolist(), "led_gains": self.led_gains.tolist(),
                "led_transform": self.led_transform, "extinction_ratio": self.extinction_ratio,
                "black_offset_dn": self.black_offset_dn, "nonlinearity": self.nonlinearity,
                "psf_sigma_px": self.psf_sigma_px, "targets_mm": {k: list(v) for k, v in self.targets_mm.items()}}


class TargetWorld:
    """The simulated world's current calibration target, rendered under the sphere's true LEDs.

    ``emission`` handed to :meth:`render` is what the simulated camera computes from the sphere's state:
    drive level x *design* intensity (N, 3); the world multiplies it by the true gains and uses the true
    LED positions and the true (distorted) camera. The operator changes ``target`` (and a board's
    ``pose_index``) between frames."""

    def __init__(self, truth: CalibrationTruth, target: _Target | None = None) -> None:
        self.truth = truth
        self.target: _Target = target or DarkTarget()
        self.renders = 0

    def render(self, emission: npt.ArrayLike, polarization: Polarization) -> FloatArray:
        from scipy.ndimage import gaussian_filter

        em = np.asarray(emission, float) * self.truth.led_gains
        img = self.target.render(self.truth.camera, self.truth.led_positions_mm, em, Polarization(polarization))
        self.renders += 1
        if self.truth.psf_sigma_px > 0:
            img = np.stack([gaussian_filter(img[..., k], self.truth.psf_sigma_px, mode="constant")
                            for k in range(3)], axis=-1)
        return img

    def expose(self, radiance: FloatArray, exposure_s: float, sensor: Any, rng: np.random.Generator
               ) -> npt.NDArray[np.uint16]:
        return expose_raw(radiance, exposure_s, sensor, rng, black_offset_dn=self.truth.black_offset_dn,
                          nonlinearity=self.truth.nonlinearity)

    def attach(self, simcam: Any) -> None:
        """Make a running :class:`simulators.camera.SimulatedCamera` render this world's target (its
        ``render_raw`` is replaced on the instance; sphere and trigger couplings are untouched)."""
        world = self

        def render_raw(emission: npt.ArrayLike, polarization: Polarization, exposure_s: float
                       ) -> npt.NDArray[np.uint16]:
            rad = world.render(emission, polarization)
            return world.expose(rad, exposure_s, simcam.sensor, simcam.rng)

        simcam.render_raw = render_raw
        if simcam.camera.width_px != self.truth.camera.width_px or \
                simcam.camera.height_px != self.truth.camera.height_px:
            raise ValueError("the true camera's image size differs from the simulated camera's")


def charuco_poses(camera: PinholeCamera, board_w_mm: float, board_h_mm: float, count: int, *, seed: int = 0,
                  distance_range: tuple[float, float] = (0.5, 1.0), max_tilt_deg: float = 55.0,
                  coverage: float = 0.95) -> list[tuple[FloatArray, FloatArray]]:
    """``count`` board poses (R, t) that a careful operator would take: the board's centre at varied depth and
    spread over the field of view (corners included), tilted up to ``max_tilt_deg`` about varied axes,
    always facing the camera (Zhang 2000 needs non-parallel views)."""
    rng = np.random.default_rng(seed)
    R = camera.R
    dist0 = float(np.linalg.norm(camera.C))
    out = []
    grid = [(0.0, 0.0)] + [(coverage * math.cos(a), coverage * math.sin(a))
                           for a in np.linspace(0, 2 * np.pi, count, endpoint=False)]
    for k in range(count):
        gx, gy = grid[k % len(grid)]
        d = dist0 * rng.uniform(*distance_range)
        half_w = (camera.width_px / 2) / camera.fx_px * d
        half_h = (camera.height_px / 2) / camera.fy_px * d
        cx = gx * max(half_w - board_w_mm * 0.35, 0.0)
        cy = gy * max(half_h - board_h_mm * 0.35, 0.0)
        center = camera.C + R.T @ np.array([cx, cy, d])
        tilt_axis = np.array([math.cos(2.4 * k + 0.3), math.sin(2.4 * k + 0.3), 0.0])
        tilt = math.radians(max_tilt_deg) * (0.45 + 0.55 * ((k * 0.618) % 1.0))
        Rb = R.T @ rotation_about(tilt_axis, tilt) @ rotation_about((0, 0, 1), math.radians(rng.uniform(-8, 8)))
        t = center - Rb @ np.array([board_w_mm / 2, board_h_mm / 2, 0.0])
        out.append((Rb, t))
    return out
