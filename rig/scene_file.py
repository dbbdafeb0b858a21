"""Scene files: the single-image method on a capture a user brings from elsewhere (docs/scene-file.md).

A scene file (TOML) names a mesh, a calibrated camera, the illumination, eta and one linear image. This
module validates it (:func:`load_scene`), runs :func:`estimation.single_image.estimate_single_image` on it
(:func:`estimate_scene`) and implements ``rig estimate single-image SCENE`` (:func:`run_cli`).

Every input error raises :class:`SceneFileError` (a :class:`drivers.errors.ConfigError`, hence a ``RigError``)
whose message names the scene file, the key and what was expected, e.g.
``scene.toml: field 'camera.fx_px': expected a number > 0, got -3.0``.

From image to observations the project's own helpers are reused (``rig.estimate``): the mesh is rasterized into
a face-ID buffer with OpenCV (object pixels), and each visible patch centre is sampled from the image by
``sample_at_points`` (mean over a ``window_px`` square, bilinear between window centres).
"""
from __future__ import annotations

import json
import math
import os
import platform
import sys
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from drivers.atomic import atomic_write
from drivers.errors import ConfigError
from estimation.camera import PinholeCamera, look_at_rotation

from .config import _REQUIRED, _Reader
from .imageio import ImageFileError, RAW_SUFFIXES, read_image
from .provenance import jsonable, sha256_file
from .session import software_version

__all__ = ["SceneFileError", "Scene", "MeshSpec", "CameraSpec", "DistortedCamera", "ImageSpec", "PointLightSpec",
           "DirectionalLightSpec", "EnvironmentSpec", "MaterialSpec", "EstimationSpec", "NoiseSpec",
           "MESH_UNITS_MM", "SCENE_FORMAT_VERSION", "load_scene", "estimate_scene", "format_table", "run_cli",
           "environment_directions"]

SCENE_FORMAT_VERSION = 1
RESULT_FORMAT = "sssrig-single-image-estimate"
#: millimetres per mesh unit
MESH_UNITS_MM: dict[str, float] = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}
MESH_SUFFIXES = (".ply", ".obj", ".stl")
MASK_SUFFIXES = (".png", ".tif", ".tiff", ".bmp", ".exr")
ENV_SUFFIXES = (".exr", ".hdr", ".tif", ".tiff", ".png")
METHODS = ("direct", "tikhonov", "pinv")
MODELS = ("dipole-jensen", "dipole-better", "mc-table", "mc-table+reference")
REFERENCE_MODEL = "mc-table+reference"  # the Monte Carlo table corrected by reference renders (rig.scene_reference)
INTEGER_SATURATION = 0.98  # default saturation level of integer images (16-bit PNG/TIFF, RAW), white = 1
_AXES = {"+x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0), "+y": (0.0, 1.0, 0.0), "-y": (0.0, -1.0, 0.0),
         "+z": (0.0, 0.0, 1.0), "-z": (0.0, 0.0, -1.0)}

Array = NDArray[np.float64]
Vec3 = tuple[float, float, float]


class SceneFileError(ConfigError):
    """A scene file is invalid: the message names the file, the key and what was expected."""

    @classmethod
    def from_config_error(cls, exc: ConfigError) -> "SceneFileError":
        """The same message as a :class:`ConfigError` raised by the shared reader of ``rig.config``."""
        err = cls.__new__(cls)
        Exception.__init__(err, str(exc))
        err.file, err.field, err.expected = exc.file, exc.field, exc.expected
        return err


# ---------------------------------------------------------------------------------------------- specs
@dataclass(frozen=True)
class MeshSpec:
    """The object's surface: a triangle mesh scaled to mm (``units``) and translated by ``translation_mm``."""

    path: Path
    units: str
    mm_per_unit: float
    translation_mm: Vec3
    max_edge_mm: float | None
    sha256: str
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class DistortedCamera:
    """A :class:`PinholeCamera` with OpenCV lens distortion (k1, k2, p1, p2, k3) applied to its projections.

    ``project`` maps world points to *distorted* pixel coordinates (those of the image as recorded), so the
    image is sampled where each point really appears and is never resampled. Beyond the calibrated field
    (``max_radius``: normalized radius of the image's corners + 10 %), where the polynomial can fold back, the
    mapping is continued radially at the distortion factor of ``max_radius`` (such points land outside the
    frame). Duck-types the attributes of :class:`PinholeCamera` that the estimators use.
    """

    pinhole: PinholeCamera
    distortion: tuple[float, float, float, float, float]
    max_radius: float

    @property
    def width_px(self) -> int:
        return self.pinhole.width_px

    @property
    def height_px(self) -> int:
        return self.pinhole.height_px

    @property
    def center_mm(self) -> tuple[float, float, float]:
        return self.pinhole.center_mm

    @property
    def C(self) -> Array:
        return self.pinhole.C

    @property
    def R(self) -> Array:
        return self.pinhole.R

    @property
    def K(self) -> Array:
        return self.pinhole.K

    def project(self, points_mm: Any) -> tuple[Array, Array]:
        """Project (..., 3) world points to distorted pixel coordinates (..., 2) and depth (...) in mm."""
        cam = self.pinhole
        p = np.asarray(points_mm, float)
        xc = (p - cam.C) @ cam.R.T
        z = xc[..., 2]
        k1, k2, p1, p2, k3 = self.distortion
        with np.errstate(divide="ignore", invalid="ignore"):
            x = xc[..., 0] / z
            y = xc[..., 1] / z
            r = np.sqrt(x * x + y * y)
            # beyond the calibrated field the polynomial may fold back: continue it radially (linear in r)
            s = np.where(r > self.max_radius, self.max_radius / np.where(r > 0, r, 1.0), 1.0)
            xs, ys = x * s, y * s
            r2 = xs * xs + ys * ys
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            xd = (xs * radial + 2 * p1 * xs * ys + p2 * (r2 + 2 * xs * xs)) / s
            yd = (ys * radial + p1 * (r2 + 2 * ys * ys) + 2 * p2 * xs * ys) / s
            u = cam.fx_px * xd + cam.cx_px
            v = cam.fy_px * yd + cam.cy_px
        behind = ~(z > 0)
        u = np.where(behind, np.nan, u)
        v = np.where(behind, np.nan, v)
        return np.stack([u, v], axis=-1), z

    def view_directions(self, points_mm: Any) -> Array:
        return self.pinhole.view_directions(points_mm)

    def pixel_rays(self) -> tuple[Array, Array]:
        """Origins (H, W, 3) and unit directions (H, W, 3) of the rays that the lens maps onto every pixel centre
        (for renderers): OpenCV's iterative undistortion of the pixel centres, checked by reprojecting with
        :meth:`project`; raises ValueError when some pixel does not come back within 1e-3 px."""
        import cv2

        cam = self.pinhole
        h, w = cam.height_px, cam.width_px
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        pix = np.stack([u, v], axis=-1)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
        und = cv2.undistortPoints(pix.reshape(-1, 1, 2), cam.K, np.asarray(self.distortion, float), None, None,
                                  criteria=crit).reshape(h, w, 2)
        d = np.concatenate([und, np.ones((h, w, 1))], axis=-1) @ cam.R
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        back, _ = self.project(cam.C + d)
        gap = np.linalg.norm(back - pix, axis=-1)
        err = float(np.max(gap)) if np.all(np.isfinite(gap)) else np.inf
        if not err <= 1e-3:
            raise ValueError(f"undistorted pixel rays reproject up to {err:.3g} px from their pixel centres")
        return np.broadcast_to(cam.C, d.shape).copy(), d


@dataclass(frozen=True)
class CameraSpec:
    """Intrinsics and pose as given, and the camera model used (pinhole, or pinhole + distortion)."""

    camera: PinholeCamera  # intrinsics of the image as read (RAW: converted from the sensor when needed)
    distortion: tuple[float, float, float, float, float] | None
    pose_from: str  # "look_at", "rotation", "quaternion_wxyz" or "rodrigues"
    intrinsics_of: str  # "image" or "sensor" (RAW files given with full-sensor intrinsics)

    @property
    def model(self) -> PinholeCamera | DistortedCamera:
        """The projection used for visibility, rasterization and sampling."""
        if self.distortion is None or not any(self.distortion):
            return self.camera
        return DistortedCamera(self.camera, self.distortion, _max_normalized_radius(self.camera, self.distortion))


@dataclass(frozen=True)
class ImageSpec:
    """The observed image and how its values become diffuse radiance."""

    path: Path
    radiance_scale: tuple[float, ...]  # image value per unit radiance, per channel
    cross_polarized: bool
    specular_free: bool
    specular_cone_deg: float
    saturation: float | None  # values >= this are masked (None: no saturation mask)
    mask_path: Path | None
    sha256: str
    mask_sha256: str | None
    format: str
    shape: tuple[int, ...]


@dataclass(frozen=True)
class PointLightSpec:
    """An isotropic point light: position in mm, radiant intensity per channel."""

    position_mm: Vec3
    intensity: tuple[float, ...]


@dataclass(frozen=True)
class DirectionalLightSpec:
    """A distant light: unit direction towards the light, irradiance at normal incidence per channel."""

    direction: Vec3
    irradiance: tuple[float, ...]


@dataclass(frozen=True)
class EnvironmentSpec:
    """A distant lat-long environment map and its orientation in the world frame."""

    path: Path
    radiance_scale: tuple[float, ...]  # map value per unit radiance
    up: Vec3
    phi0: Vec3
    azimuth: str  # "counterclockwise" or "clockwise" seen from above (from +up)
    rotation_deg: float
    max_size: int
    sha256: str

    @property
    def rotation(self) -> Array:
        """3x3 matrix taking a direction in the native map frame (EnvironmentMap: +z up, phi = 0 along +x,
        phi growing towards +y) to the world frame."""
        up = np.asarray(self.up, float)
        up /= np.linalg.norm(up)
        a = np.asarray(self.phi0, float)
        a = a - (a @ up) * up
        a /= np.linalg.norm(a)
        b = np.cross(up, a)
        if self.azimuth == "clockwise":
            b = -b
        t = math.radians(self.rotation_deg)
        rz = np.array([[math.cos(t), -math.sin(t), 0.0], [math.sin(t), math.cos(t), 0.0], [0.0, 0.0, 1.0]])
        # native (x, y, z) -> world a, b, up; then rotate by rotation_deg about up (right-handed)
        frame = np.stack([a, b, up], axis=1)
        return frame @ rz


@dataclass(frozen=True)
class MaterialSpec:
    eta: float
    model: str


@dataclass(frozen=True)
class EstimationSpec:
    method: str
    bin_mm: float
    window_px: int
    max_view_angle_deg: float
    occlusion: str | bool
    cutoff_mm: float | None
    model_error: float
    max_patches: int
    reference_spp: int = 128  # model mc-table+reference: paths per pixel of each Monte Carlo reference render
    reference_iterations: int = 4  # at most this many reference renders
    reference_seed: int = 1  # the seed of every reference render (common random numbers)
    shadows: str | bool = "auto"  # cast shadows of the lights: "auto" = for non-convex meshes (docs/visibility.md)


@dataclass(frozen=True)
class NoiseSpec:
    """Per-pixel noise in image values: constant ``sigma``, shot + read noise, or a standard-error image."""

    sigma: tuple[float, ...] | None
    electrons_per_value: float | None
    read_noise: tuple[float, ...] | None
    stderr_path: Path | None = None
    stderr_sha256: str | None = None


@dataclass(frozen=True)
class Scene:
    """A validated scene file with its mesh, image, mask and environment map loaded."""

    path: Path
    name: str
    sha256: str
    mesh: MeshSpec
    camera: CameraSpec
    image: ImageSpec
    point_lights: tuple[PointLightSpec, ...]
    directional_lights: tuple[DirectionalLightSpec, ...]
    environment: EnvironmentSpec | None
    material: MaterialSpec
    estimation: EstimationSpec
    noise: NoiseSpec | None
    mesh_data: Any = field(repr=False, compare=False, default=None)  # trimesh.Trimesh in mm (world frame)
    image_data: Array = field(repr=False, compare=False, default=None)  # (H, W, C) float64 image values
    image_meta: dict[str, Any] = field(repr=False, compare=False, default_factory=dict)
    mask_data: NDArray[np.bool_] | None = field(repr=False, compare=False, default=None)  # (H, W) True = use
    environment_data: Array | None = field(repr=False, compare=False, default=None)  # (h, w, C) radiance
    # the mesh as read (mm, world frame) before max_edge_mm subdivision: the surface of the Monte Carlo reference
    render_mesh_data: Any = field(repr=False, compare=False, default=None)
    # [noise].stderr_path loaded: (H, W, C) standard error per pixel in image values (NaN = unusable pixel)
    stderr_data: Array | None = field(repr=False, compare=False, default=None)

    @property
    def channels(self) -> int:
        return int(self.image_data.shape[2])


# ---------------------------------------------------------------------------------------------- reading
class _SceneReader(_Reader):
    """The config reader of ``rig.config`` plus the value types of scene files; unknown keys are refused."""

    def section(self, key: str) -> "_SceneReader":
        value = self.data.get(key)
        if not isinstance(value, dict):
            raise SceneFileError(self.file, self._name(key), "a table [" + self._name(key) + "]",
                                 None if value is None else type(value).__name__)
        return _SceneReader(self.file, value, self._name(key) + ".")

    def has(self, key: str) -> bool:
        return key in self.data

    def fail(self, key: str, expected: str, got: Any = None) -> SceneFileError:
        return SceneFileError(self.file, self._name(key), expected, got)

    def only(self, allowed: tuple[str, ...]) -> None:
        extra = sorted(set(self.data) - set(allowed))
        if extra:
            raise self.fail(extra[0], "a known key (one of " + ", ".join(allowed) + "); check the spelling",
                            "unknown key")

    def bool(self, key: str, default: bool) -> bool:
        v = self.data.get(key, default)
        if not isinstance(v, bool):
            raise self.fail(key, "true or false", v)
        return v

    def opt_num(self, key: str, **kw: Any) -> float | None:
        return self.num(key, **kw) if key in self.data else None

    def numbers(self, key: str, n: int | tuple[int, ...], *, positive: bool = False, nonneg: bool = False,
                default: Any = None) -> tuple[float, ...]:
        """A number or a list of numbers; lengths in ``n`` are accepted, a scalar is broadcast to max(n)."""
        sizes = (n,) if isinstance(n, int) else n
        v = self._get(key, default if default is not None else _REQUIRED)
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            v = [v] * max(sizes)
        words = " or ".join(str(s) for s in sizes)
        if not (isinstance(v, list) and len(v) in sizes and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)):
            raise self.fail(key, f"a number or a list of {words} numbers", v)
        out = tuple(float(x) for x in v)
        if not all(math.isfinite(x) for x in out):
            raise self.fail(key, "finite numbers", v)
        if positive and any(x <= 0 for x in out):
            raise self.fail(key, "numbers > 0", v)
        if nonneg and any(x < 0 for x in out):
            raise self.fail(key, "numbers >= 0", v)
        return out

    def vector(self, key: str, n: int, default: Any = None) -> tuple[float, ...]:
        v = self._get(key, default if default is not None else _REQUIRED)
        if not (isinstance(v, list) and len(v) == n and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)):
            raise self.fail(key, f"a list of {n} finite numbers", v)
        return tuple(float(x) for x in v)

    def direction(self, key: str, default: Any = None) -> Vec3:
        """A non-zero 3-vector or an axis name ("+x" ... "-z")."""
        v = self._get(key, default if default is not None else _REQUIRED)
        if isinstance(v, str):
            if v not in _AXES:
                raise self.fail(key, "a list of 3 numbers or one of " + ", ".join(_AXES), v)
            return _AXES[v]
        vec = self.vector(key, 3, default)
        if np.linalg.norm(vec) < 1e-12:
            raise self.fail(key, "a non-zero direction", list(vec))
        return (vec[0], vec[1], vec[2])

    def matrix3(self, key: str) -> Array:
        v = self.data[key]
        ok = (isinstance(v, list) and len(v) == 3 and all(
            isinstance(r, list) and len(r) == 3 and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in r) for r in v))
        if not ok:
            raise self.fail(key, "a 3x3 matrix [[r00, r01, r02], [r10, r11, r12], [r20, r21, r22]]", v)
        return np.asarray(v, float)

    def path(self, key: str, base: Path, suffixes: tuple[str, ...], what: str, *, required: bool = True
             ) -> Path | None:
        if key not in self.data and not required:
            return None
        v = self._get(key, _REQUIRED)
        if not isinstance(v, str) or not v:
            raise self.fail(key, f"a path to {what} (relative to the scene file)", v)
        p = Path(os.path.expanduser(v))
        p = p if p.is_absolute() else base / p
        if p.suffix.lower() not in suffixes:
            raise self.fail(key, f"{what} with a suffix among {', '.join(suffixes)}", v)
        if not p.is_file():
            raise self.fail(key, f"an existing file ({what}); no such file: {p}", v)
        return p



def _max_normalized_radius(cam: PinholeCamera, dist: tuple[float, float, float, float, float]) -> float:
    """Largest undistorted normalized radius inside the image (its corners and edge midpoints) + 10 %."""
    import cv2

    w, h = cam.width_px, cam.height_px
    pts = np.array([[x, y] for x in (-0.5, (w - 1) / 2, w - 0.5) for y in (-0.5, (h - 1) / 2, h - 0.5)],
                   dtype=np.float64).reshape(-1, 1, 2)
    und = cv2.undistortPoints(pts, cam.K, np.asarray(dist, float)).reshape(-1, 2)
    return float(np.max(np.linalg.norm(und, axis=1)) * 1.1)


# ---------------------------------------------------------------------------------------------- sections
def _read_mesh(r: _SceneReader, base: Path) -> tuple[MeshSpec, Any]:
    import trimesh

    r.only(("path", "units", "translation_mm", "max_edge_mm"))
    path = r.path("path", base, MESH_SUFFIXES, "a mesh file (PLY, OBJ or STL)")
    assert path is not None
    units = r.str("units", "mm", choices=tuple(MESH_UNITS_MM))
    translation = r.vec3("translation_mm", (0.0, 0.0, 0.0))
    max_edge = r.opt_num("max_edge_mm", positive=True)
    try:
        loaded = trimesh.load(str(path))
    except Exception as exc:  # trimesh raises assorted exceptions on bad files
        raise r.fail("path", f"a readable triangle mesh; {path}: {exc}", path.name) from None
    if isinstance(loaded, trimesh.Scene):
        geoms = [g for g in loaded.geometry.values() if isinstance(g, trimesh.Trimesh)]
        if len(geoms) != 1 or len(loaded.geometry) != 1:
            raise r.fail("path", f"a single triangle mesh; {path} holds {len(loaded.geometry)} geometries "
                         "(merge them into one object or export one)", path.name)
        loaded = loaded.to_geometry()
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise r.fail("path", f"a triangle mesh with faces; {path} holds a {type(loaded).__name__} "
                     f"({len(getattr(loaded, 'faces', []))} faces)", path.name)
    mesh = loaded.copy()
    if not np.all(np.isfinite(mesh.vertices)):
        raise r.fail("path", f"finite vertex coordinates; {path} has NaN/inf vertices", path.name)
    notes: list[str] = []
    mm = MESH_UNITS_MM[units]
    mesh.apply_scale(mm)
    mesh.apply_translation(translation)
    areas = mesh.area_faces
    degenerate = ~(areas > 1e-12 * max(float(areas.max()), 1e-300))
    if degenerate.any():
        mesh.update_faces(~degenerate)
        notes.append(f"{int(degenerate.sum())} degenerate (zero-area) faces dropped")
    if len(mesh.faces) == 0:
        raise r.fail("path", f"a triangle mesh with non-degenerate faces; {path}", path.name)
    if mesh.is_watertight and mesh.volume < 0:
        mesh.invert()
        notes.append("face winding was inward (negative volume): normals flipped to point outward")
    spec = MeshSpec(path, units, mm, translation, max_edge, sha256_file(path), tuple(notes))
    return spec, mesh


def _read_camera(r: _SceneReader) -> tuple[dict[str, Any], tuple[float, ...] | None, str]:
    r.only(("width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px", "distortion", "position_mm",
            "look_at_mm", "up", "rotation", "quaternion_wxyz", "rodrigues", "translation_mm"))
    width = r.int("width_px", lo=1, hi=100_000)
    height = r.int("height_px", lo=1, hi=100_000)
    fx = r.num("fx_px", positive=True)
    fy = r.num("fy_px", fx, positive=True)
    cx = r.num("cx_px", (width - 1) / 2.0)
    cy = r.num("cy_px", (height - 1) / 2.0)
    dist = None
    if r.has("distortion"):
        v = r.data["distortion"]
        if not (isinstance(v, list) and len(v) in (4, 5) and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)):
            raise r.fail("distortion", "a list [k1, k2, p1, p2] or [k1, k2, p1, p2, k3] of finite numbers "
                         "(OpenCV model)", v)
        d5 = [float(x) for x in v] + [0.0] * (5 - len(v))
        dist = (d5[0], d5[1], d5[2], d5[3], d5[4])
    kinds = [k for k in ("look_at_mm", "rotation", "quaternion_wxyz", "rodrigues") if r.has(k)]
    if len(kinds) != 1:
        raise r.fail("look_at_mm" if not kinds else kinds[1],
                     "exactly one of look_at_mm (with position_mm, up), rotation, quaternion_wxyz or rodrigues "
                     "(each with position_mm or translation_mm)", kinds or None)
    kind = kinds[0]
    if kind == "look_at_mm":
        if r.has("translation_mm"):
            raise r.fail("translation_mm", "position_mm with look_at_mm (translation_mm goes with a rotation)",
                         r.data["translation_mm"])
        pos = np.asarray(r.vec3("position_mm"))
        target = np.asarray(r.vec3("look_at_mm"))
        up = np.asarray(r.direction("up", [0.0, 0.0, 1.0]))
        if np.linalg.norm(target - pos) < 1e-9:
            raise r.fail("look_at_mm", "a point different from position_mm", list(target))
        if np.linalg.norm(np.cross(target - pos, up)) < 1e-9 * np.linalg.norm(target - pos) * np.linalg.norm(up):
            raise r.fail("up", "a direction not parallel to the viewing direction", list(up))
        rot = look_at_rotation(pos, target, up)
    else:
        if r.has("up"):
            raise r.fail("up", "no 'up' with an explicit rotation (only with look_at_mm)", r.data["up"])
        if kind == "rotation":
            rot = r.matrix3("rotation")
            err = float(np.max(np.abs(rot @ rot.T - np.eye(3))))
            if err > 1e-5:
                raise r.fail("rotation", "an orthonormal matrix (R R^T = I within 1e-5; rows = camera x, y, z "
                             f"axes in world coordinates); max |R R^T - I| = {err:.3g}", rot.tolist())
            if np.linalg.det(rot) < 0:
                raise r.fail("rotation", "a proper rotation (determinant +1, not a reflection)", rot.tolist())
            u, _, vt = np.linalg.svd(rot)
            rot = u @ vt  # re-orthonormalize the rounding of the file
        elif kind == "quaternion_wxyz":
            q = np.asarray(r.vector("quaternion_wxyz", 4))
            if np.linalg.norm(q) < 1e-9:
                raise r.fail("quaternion_wxyz", "a non-zero quaternion [w, x, y, z]", q.tolist())
            from scipy.spatial.transform import Rotation
            rot = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
        else:
            import cv2
            rvec = np.asarray(r.vector("rodrigues", 3))
            rot = cv2.Rodrigues(rvec.reshape(3, 1))[0]
        have = [k for k in ("position_mm", "translation_mm") if r.has(k)]
        if len(have) != 1:
            raise r.fail("position_mm", f"exactly one of position_mm (camera centre C) or translation_mm "
                         f"(OpenCV tvec t, C = -R^T t) with {kind}", have or None)
        if have[0] == "position_mm":
            pos = np.asarray(r.vec3("position_mm"))
        else:
            pos = -rot.T @ np.asarray(r.vec3("translation_mm"))
    cam = dict(width_px=width, height_px=height, fx_px=fx, fy_px=fy, cx_px=cx, cy_px=cy,
               rotation=tuple(map(tuple, np.asarray(rot, float).tolist())),
               center_mm=tuple(float(x) for x in pos))
    return cam, dist, kind


def _read_env_image(r: _SceneReader, path: Path) -> Array:
    if path.suffix.lower() == ".hdr":
        import cv2
        a = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if a is None or a.ndim != 3:
            raise r.fail("path", f"a readable Radiance .hdr file; {path} could not be read", path.name)
        a = a[..., ::-1].astype(np.float64)
    else:
        try:
            arr, _meta = read_image(path)
        except ImageFileError as exc:
            raise r.fail("path", f"a linear lat-long image ({exc})", path.name) from None
        a = np.asarray(arr, np.float64)
    if a.ndim == 2:
        a = a[..., None]
    if not np.all(np.isfinite(a)) or np.any(a < 0):
        raise r.fail("path", f"finite, non-negative radiance values; {path} has negative or non-finite pixels",
                     path.name)
    h, w = a.shape[:2]
    if w != 2 * h:
        raise r.fail("path", f"a lat-long map twice as wide as high; {path} is {w} x {h} px", path.name)
    return a


def _read_stderr(r: _SceneReader, path: Path, image_shape: tuple[int, ...]) -> Array:
    """The per-pixel standard-error image of ``[noise].stderr_path``: the image's size, 1 or its channel count,
    values >= 0 (NaN / inf pixels are left out of the fit, like the image's)."""
    try:
        a, _meta = read_image(path, allow_nonfinite=True)
    except ImageFileError as exc:
        raise r.fail("stderr_path", f"a readable standard-error image ({exc})", path.name) from None
    a = np.asarray(a, np.float64)
    if a.ndim == 2:
        a = a[..., None]
    h, w, c = image_shape
    if a.shape[:2] != (h, w) or a.shape[2] not in (1, c):
        raise r.fail("stderr_path", f"an image of the image's size {w} x {h} px with 1 or {c} channels",
                     f"{path.name}: {a.shape[1]} x {a.shape[0]} px, {a.shape[2]} channels")
    if np.any(a[np.isfinite(a)] < 0):
        raise r.fail("stderr_path", "standard errors >= 0", f"{path.name}: min {float(np.nanmin(a)):.3g}")
    return np.array(np.broadcast_to(a, (h, w, c)))


def _read_mask(r: _SceneReader, path: Path) -> NDArray[np.bool_]:
    if path.suffix.lower() == ".exr":
        try:
            a, _ = read_image(path)
        except ImageFileError as exc:
            raise r.fail("mask", f"a readable mask image ({exc})", path.name) from None
        a = np.asarray(a)
    else:
        import cv2
        a = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if a is None:
            raise r.fail("mask", f"a readable mask image; OpenCV cannot read {path}", path.name)
    a = np.asarray(a)
    return (a != 0).any(axis=2) if a.ndim == 3 else a != 0


def _intrinsics_for_image(cam: dict[str, Any], image_shape: tuple[int, int], raw_shape: tuple[int, int] | None,
                          file: str) -> tuple[dict[str, Any], str]:
    """Check the image size against the intrinsics; convert full-sensor intrinsics of a RAW file to the
    half-resolution superpixel image (column j covers sensor columns 2j, 2j+1: u_image = (u_sensor - 0.5)/2)."""
    h, w = image_shape
    if (cam["height_px"], cam["width_px"]) == (h, w):
        return cam, "image"
    if raw_shape is not None and (cam["height_px"], cam["width_px"]) == tuple(raw_shape):
        out = dict(cam, width_px=w, height_px=h, fx_px=cam["fx_px"] / 2.0, fy_px=cam["fy_px"] / 2.0,
                   cx_px=(cam["cx_px"] - 0.5) / 2.0, cy_px=(cam["cy_px"] - 0.5) / 2.0)
        return out, "sensor"
    also = (f" or the RAW sensor size {raw_shape[1]} x {raw_shape[0]}" if raw_shape is not None else "")
    raise SceneFileError(file, "camera.width_px", f"the image size {w} x {h} px (width x height){also}; "
                         "the intrinsics must be those of the image file",
                         f"{cam['width_px']} x {cam['height_px']}")


def _channels(r: _SceneReader, key: str, n_ch: int, **kw: Any) -> tuple[float, ...]:
    """A per-channel quantity: a number, or one number per image channel."""
    return r.numbers(key, n_ch, **kw)


def parse_scene(data: dict[str, Any], path: Path, file: str | None = None) -> Scene:
    """Validate a parsed scene document (``path``: the scene file, for relative paths and messages)."""
    file = file or str(path)
    base = path.parent
    top = _SceneReader(file, data)
    top.only(("version", "name", "mesh", "camera", "image", "point_lights", "directional_lights", "environment",
              "material", "estimation", "noise"))
    version = top.int("version", SCENE_FORMAT_VERSION)
    if version != SCENE_FORMAT_VERSION:
        raise top.fail("version", f"scene format version {SCENE_FORMAT_VERSION}", version)
    name = top.str("name", path.stem)

    # image first: its channel count sizes every per-channel value
    im = top.section("image")
    im.only(("path", "radiance_scale", "cross_polarized", "specular_free", "specular_cone_deg", "saturation",
             "mask"))
    img_path = im.path("path", base, tuple(sorted(set((".exr", ".tif", ".tiff", ".png") + RAW_SUFFIXES))),
                       "an image file (EXR, float/16-bit TIFF, 16-bit PNG or camera RAW/DNG)")
    assert img_path is not None
    try:
        img, meta = read_image(img_path, allow_nonfinite=True)  # NaN / inf pixels are excluded, and counted
    except ImageFileError as exc:
        raise im.fail("path", f"a linear image file ({exc})", str(img_path.name)) from None
    image = np.asarray(img, np.float64)
    if image.ndim == 2:
        image = image[..., None]
    n_ch = image.shape[2]
    fmt = str(meta.get("format", "?"))
    integer_source = fmt in ("png16", "raw") or (fmt == "tiff" and "int" in str(meta.get("source_dtype", "")))
    radiance_scale = _channels(im, "radiance_scale", n_ch, positive=True, default=1.0)
    cross = im.bool("cross_polarized", False)
    specular_free = im.bool("specular_free", cross)
    if cross and not specular_free:
        raise im.fail("specular_free", "true (or absent) for a cross-polarized image, which holds no specular "
                      "reflection", False)
    cone = im.num("specular_cone_deg", 20.0, lo=0.0, hi=90.0)
    if im.has("saturation"):
        sat: float | None = im.num("saturation", positive=True)
    else:
        sat = INTEGER_SATURATION if integer_source else None
    mask_path = im.path("mask", base, MASK_SUFFIXES, "a mask image (nonzero = use)", required=False)
    mask = None
    if mask_path is not None:
        mask = _read_mask(im, mask_path)
        if mask.shape != image.shape[:2]:
            raise im.fail("mask", f"a mask of the image's size {image.shape[1]} x {image.shape[0]} px; "
                          f"{mask_path.name} is {mask.shape[1]} x {mask.shape[0]}", mask_path.name)
        if not mask.any():
            raise im.fail("mask", "a mask with some nonzero (used) pixels", mask_path.name)
    image_spec = ImageSpec(img_path, radiance_scale, cross, specular_free, cone, sat, mask_path, sha256_file(img_path),
                           None if mask_path is None else sha256_file(mask_path), fmt, tuple(image.shape))

    # camera (after the image: its size is checked against the intrinsics)
    cam_dict, dist, pose_from = _read_camera(top.section("camera"))
    raw_shape = tuple(meta["raw_shape"][:2]) if fmt == "raw" and "raw_shape" in meta else None
    cam_dict, intrinsics_of = _intrinsics_for_image(cam_dict, image.shape[:2], raw_shape, file)
    camera = CameraSpec(PinholeCamera(**cam_dict), dist, pose_from, intrinsics_of)
    if dist is not None and any(dist):
        r_max = _max_normalized_radius(camera.camera, dist)
        rr = np.linspace(0.0, r_max, 512) ** 2
        slope = 1 + rr * (3 * dist[0] + rr * (5 * dist[1] + rr * 7 * dist[4]))
        if not (math.isfinite(r_max) and np.all(slope > 0)):
            raise SceneFileError(file, "camera.distortion", "a distortion whose radial mapping increases over the "
                                 "whole image (d r_d/d r > 0 up to the corners); check the coefficients' order "
                                 "[k1, k2, p1, p2, k3]", list(dist))

    mesh_spec, mesh = _read_mesh(top.section("mesh"), base)

    # lights
    points: list[PointLightSpec] = []
    raw_points = data.get("point_lights", [])
    if not isinstance(raw_points, list):
        raise top.fail("point_lights", "an array of tables [[point_lights]]", type(raw_points).__name__)
    for i, item in enumerate(raw_points):
        if not isinstance(item, dict):
            raise top.fail(f"point_lights[{i}]", "a table with position_mm and intensity", item)
        lr = _SceneReader(file, item, f"point_lights[{i}].")
        lr.only(("position_mm", "intensity"))
        points.append(PointLightSpec(lr.vec3("position_mm"), _channels(lr, "intensity", n_ch, nonneg=True)))
    dirs: list[DirectionalLightSpec] = []
    raw_dirs = data.get("directional_lights", [])
    if not isinstance(raw_dirs, list):
        raise top.fail("directional_lights", "an array of tables [[directional_lights]]", type(raw_dirs).__name__)
    for i, item in enumerate(raw_dirs):
        if not isinstance(item, dict):
            raise top.fail(f"directional_lights[{i}]", "a table with direction and irradiance", item)
        lr = _SceneReader(file, item, f"directional_lights[{i}].")
        lr.only(("direction", "irradiance"))
        d = np.asarray(lr.direction("direction"))
        d = d / np.linalg.norm(d)
        dirs.append(DirectionalLightSpec((float(d[0]), float(d[1]), float(d[2])),
                                         _channels(lr, "irradiance", n_ch, nonneg=True)))
    env = None
    env_data = None
    if top.has("environment"):
        er = top.section("environment")
        er.only(("path", "radiance_scale", "up", "phi0", "azimuth", "rotation_deg", "max_size"))
        env_path = er.path("path", base, ENV_SUFFIXES, "a lat-long environment map (EXR, HDR, TIFF, 16-bit PNG)")
        assert env_path is not None
        env_img = _read_env_image(er, env_path)
        if env_img.shape[2] not in (1, n_ch):
            raise er.fail("path", f"a map with 1 or {n_ch} channels (like the image); {env_path.name} has "
                          f"{env_img.shape[2]}", env_path.name)
        up = er.direction("up", "+z")
        phi0 = er.direction("phi0", "+x")
        u = np.asarray(up) / np.linalg.norm(up)
        a = np.asarray(phi0) / np.linalg.norm(phi0)
        if np.linalg.norm(a - (a @ u) * u) < 1e-3:
            raise er.fail("phi0", "a direction not parallel to 'up'", list(phi0))
        env = EnvironmentSpec(env_path, _channels(er, "radiance_scale", n_ch, positive=True, default=1.0), up,
                              phi0, er.str("azimuth", "counterclockwise", choices=("counterclockwise", "clockwise")),
                              er.num("rotation_deg", 0.0), er.int("max_size", 64, lo=4, hi=2048), sha256_file(env_path))
        env_data = np.broadcast_to(env_img, env_img.shape[:2] + (n_ch,)) / np.asarray(env.radiance_scale)
    if not points and not dirs and env is None:
        raise top.fail("point_lights", "at least one light: [[point_lights]], [[directional_lights]] or "
                       "[environment]", None)
    if env is not None and not specular_free:
        raise im.fail("specular_free", "true when the lighting includes an environment map (specular reflection "
                      "of an environment covers the whole object and cannot be masked geometrically): if the image "
                      "holds no specular reflection (a diffuse-only render, a separated diffuse pass), set "
                      "specular_free = true; set cross_polarized = true only for a photograph through crossed "
                      "polarizers (it doubles the image's radiance)", False)

    mr = top.section("material") if top.has("material") else _SceneReader(file, {}, "material.")
    mr.only(("eta", "model"))
    material = MaterialSpec(mr.num("eta", 1.3, lo=1.0, hi=3.0), mr.str("model", "dipole-jensen", choices=MODELS))

    es = top.section("estimation") if top.has("estimation") else _SceneReader(file, {}, "estimation.")
    es.only(("method", "bin_mm", "window_px", "max_view_angle_deg", "occlusion", "cutoff_mm", "model_error",
             "max_patches", "reference_spp", "reference_iterations", "reference_seed", "shadows"))
    window = es.int("window_px", 1, lo=1, hi=15)
    if window % 2 == 0:
        raise es.fail("window_px", "an odd number of pixels (1, 3, 5, ...)", window)
    occl = es.data.get("occlusion", "auto")
    if not (occl == "auto" or isinstance(occl, bool)):
        raise es.fail("occlusion", "\"auto\", true or false", occl)
    shadows = es.data.get("shadows", "auto")
    if not (shadows == "auto" or isinstance(shadows, bool)):
        raise es.fail("shadows", "\"auto\", true or false", shadows)
    estimation = EstimationSpec(
        method=es.str("method", "direct", choices=METHODS), bin_mm=es.num("bin_mm", 0.35, positive=True),
        window_px=window, max_view_angle_deg=es.num("max_view_angle_deg", 70.0, lo=1.0, hi=89.0),
        occlusion=occl, cutoff_mm=es.opt_num("cutoff_mm", positive=True),
        model_error=es.num("model_error", 0.02, lo=0.0, hi=1.0), max_patches=es.int("max_patches", 20000, lo=10),
        reference_spp=es.int("reference_spp", 128, lo=2, hi=1_000_000),
        reference_iterations=es.int("reference_iterations", 4, lo=1, hi=100),
        reference_seed=es.int("reference_seed", 1, lo=0, hi=2 ** 31 - 1), shadows=shadows)
    n_faces = len(mesh.faces)
    render_mesh = mesh
    if mesh_spec.max_edge_mm is not None:
        import trimesh
        v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=mesh_spec.max_edge_mm)
        mesh = trimesh.Trimesh(v, f, process=False)
        n_faces = len(f)
    if n_faces > estimation.max_patches:
        raise es.fail("max_patches", f"at least the mesh's face count ({n_faces} faces"
                      f"{' after max_edge_mm' if mesh_spec.max_edge_mm else ''}); decimate the mesh (faces ~ patch "
                      "spacing well below l_d) or raise max_patches (cost grows with faces x visible faces)",
                      estimation.max_patches)

    noise = None
    stderr_img = None
    if top.has("noise"):
        nr = top.section("noise")
        nr.only(("sigma", "electrons_per_value", "read_noise", "stderr_path"))
        kinds = [nr.has("sigma"), nr.has("electrons_per_value") or nr.has("read_noise"), nr.has("stderr_path")]
        if sum(kinds) != 1:
            raise nr.fail("sigma", "exactly one of: sigma, electrons_per_value (+ read_noise), stderr_path",
                          sorted(nr.data))
        if nr.has("sigma"):
            noise = NoiseSpec(_channels(nr, "sigma", n_ch, positive=True), None, None)
        elif nr.has("stderr_path"):
            se_path = nr.path("stderr_path", base, (".exr", ".tif", ".tiff"),
                              "a per-pixel standard-error image (EXR or float TIFF, image value units)")
            assert se_path is not None
            stderr_img = _read_stderr(nr, se_path, image.shape)
            noise = NoiseSpec(None, None, None, se_path, sha256_file(se_path))
        else:
            noise = NoiseSpec(None, nr.num("electrons_per_value", positive=True),
                              _channels(nr, "read_noise", n_ch, nonneg=True, default=0.0))

    try:
        scene_hash = sha256_file(path)
    except OSError:
        scene_hash = ""
    return Scene(path=path, name=name, sha256=scene_hash, mesh=mesh_spec, camera=camera, image=image_spec,
                 point_lights=tuple(points), directional_lights=tuple(dirs), environment=env, material=material,
                 estimation=estimation, noise=noise, mesh_data=mesh, image_data=image, image_meta=dict(meta),
                 mask_data=mask, environment_data=env_data, render_mesh_data=render_mesh, stderr_data=stderr_img)


def load_scene(path: str | os.PathLike[str]) -> Scene:
    """Read and validate a scene file (docs/scene-file.md); load its mesh, image, mask and environment map.

    Raises :class:`SceneFileError` naming the file, the key and what was expected (including missing or
    unreadable mesh/image/mask/map files and an image whose size does not match the intrinsics).
    """
    p = Path(path)
    file = str(p)
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneFileError(file, "<file>", "a readable UTF-8 TOML scene file", str(exc)) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SceneFileError(file, "<syntax>", "valid TOML", str(exc)) from None
    try:
        return parse_scene(data, p.resolve(), file)
    except SceneFileError:
        raise
    except ConfigError as exc:  # raised by the shared reader of rig.config: same message, scene-file type
        raise SceneFileError.from_config_error(exc) from None


# ---------------------------------------------------------------------------------------------- illumination
def environment_directions(env: EnvironmentSpec, radiance: Array) -> tuple[Array, Array]:
    """World directions (N, 3) towards the environment and radiance x solid-angle weights (N, C) of a map
    given in the scene's orientation (``up``, ``phi0``, ``azimuth``, ``rotation_deg``)."""
    from estimation.single_image import EnvironmentMap

    d, w = EnvironmentMap(radiance, max_size=env.max_size).directions_and_weights()
    return d @ env.rotation.T, w


def environment_grid_shape(env: EnvironmentSpec, radiance: Array) -> tuple[int, int]:
    """(rows, columns) of the lat-long grid :func:`environment_directions` returns (after downsampling)."""
    from estimation.single_image import EnvironmentMap

    return EnvironmentMap(radiance, max_size=env.max_size).grid_shape()


def _irradiance(scene: Scene, patches: Any) -> Array:
    """Fresnel-transmitted irradiance E_t (K, C) of all the scene's lights on the patches."""
    from estimation.single_image import DirectionalLights, PointLights, patch_irradiance

    eta = scene.material.eta
    n_ch = scene.channels
    e = np.zeros((patches.centers_mm.shape[0], n_ch))
    if scene.point_lights:
        pl = PointLights(np.array([p.position_mm for p in scene.point_lights]),
                         np.array([p.intensity for p in scene.point_lights]))
        e += patch_irradiance(patches, pl, eta)
    if scene.directional_lights:
        dl = DirectionalLights(np.array([d.direction for d in scene.directional_lights]),
                               np.array([d.irradiance for d in scene.directional_lights]))
        e += patch_irradiance(patches, dl, eta)
    if scene.environment is not None and scene.environment_data is not None:
        d, w = environment_directions(scene.environment, scene.environment_data)
        grid = environment_grid_shape(scene.environment, scene.environment_data)   # per-cell cast shadows
        e += patch_irradiance(patches, DirectionalLights(d, np.broadcast_to(w, (w.shape[0], n_ch)), grid), eta)
    return e


def _specular_patches(scene: Scene, patches: Any) -> NDArray[np.bool_]:
    """Patches whose normal lies within ``specular_cone_deg`` of the half vector of any point/directional light
    and the camera: where a mirror-like highlight of that light can appear."""
    c = patches.centers_mm
    v = scene.camera.camera.C[None, :] - c
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    to_lights = [np.asarray(p.position_mm)[None, :] - c for p in scene.point_lights]
    to_lights += [np.broadcast_to(np.asarray(d.direction), c.shape) for d in scene.directional_lights]
    cos_cone = math.cos(math.radians(scene.image.specular_cone_deg))
    spec = np.zeros(c.shape[0], dtype=bool)
    for lvec in to_lights:
        lv = lvec / np.linalg.norm(lvec, axis=1, keepdims=True)
        h = lv + v
        h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)
        spec |= np.einsum("kc,kc->k", h, patches.normals) >= cos_cone
    return spec


# ---------------------------------------------------------------------------------------------- estimation
def _pixel_variance(scene: Scene, usable: NDArray[np.bool_]) -> tuple[Array, dict[str, Any]]:
    """Per-pixel variance of the image values (H, W, C) and a description of the noise model: the scene's
    ``[noise]``, or without one a signal-dependent fit var = a value + b to the usable pixels
    (:func:`estimation.noise.estimate_signal_dependent_noise`)."""
    from estimation.noise import estimate_signal_dependent_noise

    img = scene.image_data
    nz = scene.noise
    if nz is None:
        fit = estimate_signal_dependent_noise(img, usable)
        return fit.variance(img), {"source": "estimated from the image", "model": "var = a value + b",
                                   **fit.as_dict()}
    if nz.stderr_path is not None:
        assert scene.stderr_data is not None
        return np.square(scene.stderr_data), {"source": "given", "model": "standard-error image",
                                              "path": str(nz.stderr_path)}
    if nz.sigma is not None:
        return (np.broadcast_to(np.square(np.asarray(nz.sigma))[None, None, :], img.shape).copy(),
                {"source": "given", "model": "constant sigma", "sigma": list(nz.sigma)})
    assert nz.electrons_per_value is not None and nz.read_noise is not None
    var = np.maximum(img, 0.0) / nz.electrons_per_value + np.square(np.asarray(nz.read_noise))[None, None, :]
    if scene.image.format == "raw" and img.shape[2] == 3:
        var = var / np.array([1.0, 2.0, 1.0])  # G of a RAW superpixel is the mean of two photosites
    return var, {"source": "given", "model": "shot + read noise", "electrons_per_value": nz.electrons_per_value,
                 "read_noise": list(nz.read_noise)}




def _scene_summary(scene: Scene) -> dict[str, Any]:
    cam = scene.camera.camera
    out: dict[str, Any] = {
        "name": scene.name,
        "mesh": {"path": scene.mesh.path, "units": scene.mesh.units, "mm_per_unit": scene.mesh.mm_per_unit,
                 "translation_mm": scene.mesh.translation_mm, "faces": int(len(scene.mesh_data.faces)),
                 "notes": list(scene.mesh.notes)},
        "camera": {"width_px": cam.width_px, "height_px": cam.height_px, "fx_px": cam.fx_px, "fy_px": cam.fy_px,
                   "cx_px": cam.cx_px, "cy_px": cam.cy_px, "rotation": cam.rotation, "center_mm": cam.center_mm,
                   "distortion": scene.camera.distortion, "pose_from": scene.camera.pose_from,
                   "intrinsics_of": scene.camera.intrinsics_of},
        "image": {"path": scene.image.path, "format": scene.image.format, "shape": scene.image.shape,
                  "radiance_scale": scene.image.radiance_scale, "cross_polarized": scene.image.cross_polarized,
                  "specular_free": scene.image.specular_free, "saturation": scene.image.saturation,
                  "mask": scene.image.mask_path},
        "lights": {"point": [{"position_mm": p.position_mm, "intensity": p.intensity} for p in scene.point_lights],
                   "directional": [{"direction": d.direction, "irradiance": d.irradiance}
                                   for d in scene.directional_lights],
                   "environment": None if scene.environment is None else {
                       "path": scene.environment.path, "radiance_scale": scene.environment.radiance_scale,
                       "up": scene.environment.up, "phi0": scene.environment.phi0,
                       "azimuth": scene.environment.azimuth, "rotation_deg": scene.environment.rotation_deg,
                       "max_size": scene.environment.max_size}},
        "material": {"eta": scene.material.eta, "model": scene.material.model},
        "estimation": {"method": scene.estimation.method, "bin_mm": scene.estimation.bin_mm,
                       "window_px": scene.estimation.window_px,
                       "reference_spp": scene.estimation.reference_spp,
                       "reference_iterations": scene.estimation.reference_iterations,
                       "reference_seed": scene.estimation.reference_seed,
                       "max_view_angle_deg": scene.estimation.max_view_angle_deg,
                       "occlusion": scene.estimation.occlusion, "shadows": scene.estimation.shadows,
                       "cutoff_mm": scene.estimation.cutoff_mm,
                       "model_error": scene.estimation.model_error},
        "noise": None if scene.noise is None else {"sigma": scene.noise.sigma,
                                                   "electrons_per_value": scene.noise.electrons_per_value,
                                                   "read_noise": scene.noise.read_noise,
                                                   "stderr_path": None if scene.noise.stderr_path is None
                                                   else str(scene.noise.stderr_path)},
    }
    return out


def estimate_scene(scene: Scene, *, method: str | None = None, model: str | None = None,
                   reference_spp: int | None = None, reference_iterations: int | None = None,
                   reference_seed: int | None = None, shadows: bool | str | None = None) -> dict[str, Any]:
    """Run the single-image method on a loaded scene; return a JSON-able result (docs/scene-file.md, "Output").

    ``method`` overrides the scene's ``[estimation].method``, ``model`` its ``[material].model``, and the
    ``reference_*`` arguments its ``[estimation].reference_*`` keys (used by ``model = "mc-table+reference"``:
    the Monte Carlo table fit corrected by Monte Carlo renders of the scene, :mod:`rig.scene_reference`). A failed
    estimate returns ``success: false`` with the reason in ``message`` (never raises for that); input errors were
    raised by :func:`load_scene`, or are raised here as :class:`SceneFileError` when only the reference cannot
    handle them (e.g. point lights through a non-convex refracting mesh). ``shadows`` ("auto", True/"on",
    False/"off") overrides ``[estimation].shadows``: cast shadows of the lights on the mesh (docs/visibility.md).
    """
    from estimation.single_image import SingleImageResult, estimate_single_image, patches_from_mesh

    from .estimate import pixel_faces, sample_at_points

    t0 = time.perf_counter()
    meth = method or scene.estimation.method
    if meth not in METHODS:
        raise SceneFileError(str(scene.path), "estimation.method", "one of " + ", ".join(METHODS), meth)
    model_name = model or scene.material.model
    if model_name not in MODELS:
        raise SceneFileError(str(scene.path), "material.model", "one of " + ", ".join(MODELS), model_name)
    spp = scene.estimation.reference_spp if reference_spp is None else int(reference_spp)
    iterations = scene.estimation.reference_iterations if reference_iterations is None else int(reference_iterations)
    ref_seed = scene.estimation.reference_seed if reference_seed is None else int(reference_seed)
    if spp < 2 or iterations < 1 or ref_seed < 0:
        raise ValueError(f"reference_spp must be >= 2, reference_iterations >= 1, reference_seed >= 0; got {spp}, "
                         f"{iterations}, {ref_seed}")
    cam = scene.camera.model
    mesh = scene.mesh_data
    est = scene.estimation
    cos_min = math.cos(math.radians(est.max_view_angle_deg))
    sh = est.shadows if shadows is None else {"on": True, "off": False}.get(shadows, shadows)  # type: ignore[call-overload]
    if not (sh == "auto" or isinstance(sh, bool)):
        raise ValueError(f"shadows must be 'auto', 'on', 'off', True or False; got {shadows!r}")
    patches = patches_from_mesh(mesh, cam, cos_min=cos_min, occlusion=est.occlusion, shadows=sh)
    img = scene.image_data
    n_ch = img.shape[2]
    h, w = img.shape[:2]
    faces = pixel_faces(mesh, cam)
    on_object = faces >= 0
    user_ok = np.ones((h, w), bool) if scene.mask_data is None else scene.mask_data
    sat_ok = np.ones((h, w), bool) if scene.image.saturation is None else ~np.any(
        img >= scene.image.saturation, axis=2)
    valid = (on_object & user_ok & sat_ok)[..., None] & np.isfinite(img)
    if scene.stderr_data is not None:
        valid &= np.isfinite(scene.stderr_data)
    var, noise_info = _pixel_variance(scene, np.all(valid, axis=2))
    obs, sigma = sample_at_points(img, var, valid, cam, patches.centers_mm, window_px=est.window_px)
    obs[~patches.visible] = np.nan

    # what excluded the visible patches (a patch can be counted under several reasons)
    ones = np.ones((h, w, 1))
    vis_centers = patches.centers_mm[patches.visible]
    base, _ = sample_at_points(ones, ones * 0, on_object[..., None], cam, vis_centers, window_px=est.window_px)

    def lost(extra_ok: NDArray[np.bool_]) -> int:
        cut, _ = sample_at_points(ones, ones * 0, (on_object & extra_ok)[..., None], cam, vis_centers,
                                   window_px=est.window_px)
        return int(np.sum(np.isfinite(base[:, 0]) & ~np.isfinite(cut[:, 0])))

    excluded: dict[str, int] = {
        "off_object_or_frame": int(np.sum(~np.isfinite(base[:, 0]))),
        "mask": lost(user_ok) if scene.mask_data is not None else 0,
        "saturated": lost(sat_ok) if scene.image.saturation is not None else 0,
    }
    spec = np.zeros(len(patches.areas_mm2), bool)
    if not scene.image.specular_free:
        spec = _specular_patches(scene, patches) & patches.visible
        obs[spec] = np.nan
    excluded["specular_cone"] = int(spec.sum())

    k = np.asarray(scene.image.radiance_scale, float)[None, :]
    factor = 2.0 if scene.image.cross_polarized else 1.0  # the analyzer passes half the depolarized diffuse light
    obs = obs / k * factor
    sigma = sigma / k * factor
    e_t = _irradiance(scene, patches)
    n_obs = np.isfinite(obs[patches.visible]).sum(axis=0)
    fit_kw: dict[str, Any] = dict(method=meth, bin_mm=est.bin_mm, cutoff_mm=est.cutoff_mm,
                                  noise_sigma=sigma,
                                  model_error=est.model_error)
    reference_out: dict[str, Any] | None = None
    if model_name == REFERENCE_MODEL:
        from estimation.model_correction import estimate_with_reference

        from .scene_reference import scene_reference

        valid_px = np.all(valid, axis=2)
        ref, ref_info = scene_reference(scene, patches, valid_px, spp=spp)  # SceneFileError before any fit
        try:
            res = estimate_with_reference(obs, patches, e_t, scene.material.eta, ref, base_model="mc-table",
                                          max_iterations=iterations, seed=ref_seed, **fit_kw)
        except ValueError as exc:  # e.g. the reference has no value at any observed patch
            res = SingleImageResult(False, f"Monte Carlo reference: {exc}", meth, model_name, scene.material.eta)
        reference_out = {**ref_info, "base_model": "mc-table", "max_iterations": iterations, "seed": ref_seed,
                         "steps": res.extra.get("reference", []), "converged": res.extra.get("converged"),
                         "interval_propagation": res.extra.get("interval_propagation"),
                         "renders": list(ref.renders),
                         "render_seconds_total": float(sum(r["seconds"] for r in ref.renders)),
                         "seconds_total": res.extra.get("seconds_total")}
    else:
        res = estimate_single_image(obs, patches, e_t, scene.material.eta, model=model_name, **fit_kw)
    seconds = time.perf_counter() - t0
    channels = ["R", "G", "B"] if n_ch == 3 else ["Y"]
    out: dict[str, Any] = {
        "format": RESULT_FORMAT, "format_version": 1, "estimator": "single-image",
        "success": bool(res), "message": res.message if patches.visible.any() else
        res.message + " (check the camera pose and that the mesh's face normals point outward)",
        "method": res.method, "model": model_name, "eta": scene.material.eta, "channels": channels,
        "seconds": seconds,
        "observations": {"patches": int(len(patches.areas_mm2)), "visible": int(patches.visible.sum()),
                         "observed_per_channel": n_obs.tolist(), "excluded_patches": excluded,
                         "object_pixels": int(on_object.sum()), "patch_spacing_mm": patches.spacing_mm,
                         "cast_shadows": patches.shadows,
                         "nonfinite_pixels": int(scene.image_meta.get("nonfinite", 0))},
        "radiometry": {"radiance_scale": list(scene.image.radiance_scale), "cross_polarized_factor": factor,
                       "noise_model": noise_info},
    }
    if res:
        ssp, sa = res.sigma_s_prime_per_mm, res.sigma_a_per_mm
        out["parameters"] = {
            "sigma_s_prime_per_mm": {"value": ssp, "ci95": res.sigma_s_prime_ci_per_mm},
            "sigma_a_per_mm": {"value": sa, "ci95": res.sigma_a_ci_per_mm,
                               "ci95_wald": res.sigma_a_ci_jacobian_per_mm},
            "R_d": {"value": res.R_d, "ci95": res.R_d_ci},
            "l_d_mm": {"value": res.l_d_mm, "ci95": res.l_d_ci_mm},
            "D_mm": {"value": res.D_mm},
            "albedo": {"value": ssp / (ssp + sa)},
            "transport_mean_free_path_mm": {"value": 1.0 / (ssp + sa)},
        }
        out["correlation_log"] = res.correlation_log
        out["sigma_a_identifiable"] = list(res.sigma_a_identifiable_per_channel)
        out["identifiability_reason"] = res.identifiability_reason
    out["model_bias"] = res.extra.get("model_bias")
    if res:
        out["status"] = res.extra.get("status")
        out["status_reasons"] = res.extra.get("status_reasons")
    else:  # a failed estimate is no measurement of anything
        out["status"] = {"sigma_s_prime_per_mm": ["unknown"] * n_ch, "sigma_a_per_mm": ["unknown"] * n_ch}
        out["status_reasons"] = [f"channel {c}: the estimate failed: {res.message}" for c in range(n_ch)]
    if reference_out is not None:
        out["reference"] = reference_out
        out["converged"] = reference_out["converged"]
    d = res.diagnostics
    if d is not None:
        out["diagnostics"] = {"condition_number": d.condition_number, "n_bins": d.n_bins,
                              "empty_bins": d.empty_bins, "residual_rms": d.residual_rms,
                              "relative_residual_rms": d.relative_residual_rms, "n_observations": d.n_observations,
                              "n_patches": d.n_patches, "nfev": d.nfev, "solver_seconds": d.seconds,
                              "regularization": d.regularization, "notes": list(d.notes)}
    out["scene"] = _scene_summary(scene)
    out["provenance"] = {
        "scene": str(scene.path), "scene_sha256": scene.sha256,
        "image": str(scene.image.path), "image_sha256": scene.image.sha256,
        "mesh": str(scene.mesh.path), "mesh_sha256": scene.mesh.sha256,
        "mask": None if scene.image.mask_path is None else str(scene.image.mask_path),
        "mask_sha256": scene.image.mask_sha256,
        "environment": None if scene.environment is None else str(scene.environment.path),
        "environment_sha256": None if scene.environment is None else scene.environment.sha256,
        "method": res.method, "software": "sssrig", "software_version": software_version(),
        "python": platform.python_version(), "numpy": np.__version__,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    return jsonable(out)


# ---------------------------------------------------------------------------------------------- CLI
def _fmt(v: Any) -> str:
    return "-" if v is None else f"{v:.4g}"


def _cells(values: Any) -> str:
    return "[" + ", ".join(_fmt(v) for v in (values or [])) + "]"


def _reference_lines(result: dict[str, Any]) -> list[str]:
    """The reference iteration of model mc-table+reference: parameters and render seconds per step, converged,
    and the bias of the flat mc-table model in this scene."""
    ref = result.get("reference")
    if not ref:
        return []
    lines = [f"  Monte Carlo reference ({ref.get('spp')} spp per render, seed {ref.get('seed')}, at most "
             f"{ref.get('max_iterations')} renders, window {ref.get('window_px')} px): converged "
             f"{'yes' if ref.get('converged') else 'NO'}, {len(ref.get('renders', []))} renders, "
             f"{ref.get('render_seconds_total', 0.0):.1f} s rendering",
             f"    {'step':<10}{'sigma_s_prime [1/mm]':<28}{'sigma_a [1/mm]':<28}{'render s':<10}"
             f"{'kappa median (reference / mc-table)'}"]
    for st in ref.get("steps", []):
        it = st.get("iteration")
        label = "0 mc-table" if it == 0 else f"{it}"
        lines.append(f"    {label:<10}{_cells(st.get('sigma_s_prime_per_mm')):<28}{_cells(st.get('sigma_a_per_mm')):<28}"
                     f"{st.get('render_seconds', 0.0):<10.1f}{_cells(st.get('kappa_median'))}")
    bias = result.get("model_bias") or {}
    if "radiance_ratio_median" in bias:
        lines.append(f"  model bias in this scene (mc-table / reference radiance per patch): median "
                     f"{_cells(bias.get('radiance_ratio_median'))}, 5-95 % {_cells(bias.get('radiance_ratio_p05'))}"
                     f"-{_cells(bias.get('radiance_ratio_p95'))}, rms log {_cells(bias.get('rms_log_ratio'))}")
    for n in ref.get("notes", []):
        lines.append(f"  reference: {n}")
    return lines


def format_table(result: dict[str, Any]) -> str:
    """A readable table of the parameters with their 95 % intervals."""
    prov = result.get("provenance", {})
    obs = result.get("observations", {})
    lines = [f"single-image estimate of {prov.get('scene', '?')}",
             f"  method {result.get('method')}, model {result.get('model')}, eta {result.get('eta')}, "
             f"{obs.get('visible', 0)} visible of {obs.get('patches', 0)} patches, observed per channel "
             f"{obs.get('observed_per_channel')}, {result.get('seconds', 0.0):.1f} s"]
    if not result.get("success"):
        lines.append(f"  FAILED: {result.get('message')}")
        lines += _reference_lines(result)
        return "\n".join(lines)
    chans = result["channels"]
    lines.append("  " + f"{'quantity':<26}" + "".join(f"{c:<28}" for c in chans))
    labels = [("sigma_s_prime_per_mm", "sigma_s' [1/mm]"), ("sigma_a_per_mm", "sigma_a [1/mm]"),
              ("R_d", "R_d"), ("l_d_mm", "l_d = 1/sigma_tr [mm]"), ("D_mm", "D [mm]"),
              ("albedo", "albedo alpha'"), ("transport_mean_free_path_mm", "1/sigma_t' [mm]")]
    for key, label in labels:
        p = result["parameters"][key]
        cells = []
        for c in range(len(chans)):
            v = p["value"][c]
            ci = p.get("ci95")
            cell = _fmt(v) + (f" ({_fmt(ci[c][0])}-{_fmt(ci[c][1])})" if ci is not None else "")
            cells.append(f"{cell:<28}")
        lines.append("  " + f"{label:<26}" + "".join(cells))
    ident = result.get("sigma_a_identifiable", [])
    lines.append("  " + f"{'sigma_a identifiable':<26}" + "".join(f"{('yes' if i else 'NO'):<28}" for i in ident))
    status = result.get("status") or {}
    for key, label in (("sigma_s_prime_per_mm", "status sigma_s'"), ("sigma_a_per_mm", "status sigma_a")):
        if key in status:
            lines.append("  " + f"{label:<26}" + "".join(f"{v.upper() if v != 'ok' else 'ok':<28}" for v in status[key]))
    lines.append("  (95 % intervals in parentheses; sigma_a: profile likelihood, lower bound 0 when one-sided)")
    if not all(ident):
        lines.append(f"  {result.get('identifiability_reason', '')}")
    if any(v != "ok" for vals in status.values() for v in vals):
        lines.append("  WEAK = not a measurement to quote without its interval: " +
                     "; ".join(result.get("status_reasons") or []))
    lines += _reference_lines(result)
    notes = result.get("diagnostics", {}).get("notes", [])
    for n in notes:
        lines.append(f"  note: {n}")
    if result.get("message") not in (None, "ok"):
        lines.append(f"  message: {result['message']}")
    return "\n".join(lines)


def run_cli(args: Any) -> int:
    """``rig estimate single-image SCENE [--method M] [--model MODEL] [--reference-spp N]
    [--reference-iterations K] [--reference-seed S] [--shadows auto|on|off] [--out FILE] [--json]``.

    Prints a table (or the JSON with ``--json``) and writes the JSON atomically to ``--out`` or
    ``<scene>.estimate.json`` beside the scene file. Returns 0 on success, 1 if the estimate failed (the reason
    is printed); input errors raise :class:`SceneFileError` (the CLI prints them and returns 2).
    """
    scene = load_scene(args.scene)
    result = estimate_scene(scene, method=getattr(args, "method", None), model=getattr(args, "model", None),
                            reference_spp=getattr(args, "reference_spp", None),
                            reference_iterations=getattr(args, "reference_iterations", None),
                            reference_seed=getattr(args, "reference_seed", None),
                            shadows=getattr(args, "shadows", None))
    out = getattr(args, "out", None)
    out_path = Path(out) if out is not None else Path(args.scene).with_suffix(".estimate.json")
    text = json.dumps(result, indent=2, allow_nan=False) + "\n"

    def write(tmp: Path) -> None:
        tmp.write_text(text, encoding="utf-8")

    atomic_write(out_path, write)
    if getattr(args, "json", False):
        print(text, end="")
        print(f"wrote {out_path}", file=sys.stderr)
    else:
        print(format_table(result))
        print(f"wrote {out_path}")
    if not result["success"]:
        print(f"rig estimate single-image: estimation failed: {result['message']}", file=sys.stderr)
        return 1
    return 0
