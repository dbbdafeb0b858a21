"""Scene files, the data: what a scene file describes (docs/scene-file.md) once :func:`rig.files.scene_file.load_scene`
has validated it — mesh, camera (with its lens distortion), image, lights, environment map, material, estimation
options, noise — and :class:`SceneFileError`, whose message names the file, the key and what was expected.

Read by :mod:`rig.files.scene_file`, estimated by :mod:`rig.estimate.scenes`, rendered by :mod:`rig.estimate.reference.scene_reference`
(the Monte Carlo reference): the types live here so that none of those imports another in a circle.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from drivers.errors import ConfigError
from estimation.camera import PinholeCamera

SCENE_FORMAT_VERSION = 1
RESULT_FORMAT = "sssrig-single-image-estimate"
#: millimetres per mesh unit
MESH_UNITS_MM: dict[str, float] = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}
MESH_SUFFIXES = (".ply", ".obj", ".stl")


class MeshFileError(ValueError):
    """A mesh file that is not one readable triangle mesh: ``expected`` (what was wanted), ``found`` (what the file
    holds); the caller names its file and key."""

    def __init__(self, expected: str, found: str) -> None:
        super().__init__(f"expected {expected}; found {found}")
        self.expected, self.found = expected, found


def load_triangle_mesh(path: Path) -> Any:
    """One ``trimesh.Trimesh`` (a copy) with faces and finite vertices from a PLY / OBJ / STL file (a scene holding
    exactly one geometry is unwrapped); else :class:`MeshFileError`. The one mesh reader of scene files
    (``[object] path``) and capture folders (``[object] mesh_file``)."""
    import trimesh

    try:
        loaded = trimesh.load(str(path))
    except Exception as exc:  # trimesh raises assorted exceptions on bad files
        raise MeshFileError("a readable triangle mesh", f"{path}: {exc}") from None
    if isinstance(loaded, trimesh.Scene):
        geoms = [g for g in loaded.geometry.values() if isinstance(g, trimesh.Trimesh)]
        if len(geoms) != 1 or len(loaded.geometry) != 1:
            raise MeshFileError("a single triangle mesh", f"{path} holds {len(loaded.geometry)} geometries (merge "
                                "them into one object or export one)")
        loaded = loaded.to_geometry()
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise MeshFileError("a triangle mesh with faces", f"{path} holds a {type(loaded).__name__} "
                            f"({len(getattr(loaded, 'faces', []))} faces)")
    if not np.all(np.isfinite(loaded.vertices)):
        raise MeshFileError("finite vertex coordinates", f"{path} has NaN/inf vertices")
    return loaded.copy()
MASK_SUFFIXES = (".png", ".tif", ".tiff", ".bmp", ".exr")
ENV_SUFFIXES = (".exr", ".hdr", ".tif", ".tiff", ".png")
METHODS = ("direct", "tikhonov", "pinv")
MODELS = ("dipole-jensen", "dipole-better", "mc-table", "mc-table+reference")
REFERENCE_MODEL = "mc-table+reference"  # the Monte Carlo table corrected by reference renders (rig.estimate.reference.scene_reference)
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
    patches: str | int = "auto"  # patch budget: "auto" or a face count of a decimated copy (resolve_patches)


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


# ---------------------------------------------------------------------------------------------- patch budget
#: ``patches = "auto"`` decimates a mesh of more than ``max_patches`` faces to this many patches
AUTO_PATCHES = 10_000
#: the fewest patches a scene file may ask for
MIN_PATCHES = 10


def patches_error(requested: object, n_faces: int, max_patches: int, max_edge_mm: float | None) -> str | None:
    """What is wrong with a ``patches`` value ("auto" or an integer) for a mesh of ``n_faces`` faces, or None."""
    if requested == "auto":
        return None
    if isinstance(requested, bool) or not isinstance(requested, int):
        return "\"auto\" or an integer number of patches"
    if max_edge_mm is not None:
        return "\"auto\" when [mesh].max_edge_mm is set (max_edge_mm refines the mesh, patches coarsens it)"
    if requested < MIN_PATCHES:
        return f"an integer >= {MIN_PATCHES} (patches of a decimated copy of the mesh)"
    if requested > n_faces:
        return (f"at most the mesh's face count ({n_faces} faces): patches come from a decimated copy of the mesh, "
                "decimation only removes faces")
    if requested > max_patches:
        return f"at most max_patches ({max_patches}); raise max_patches to allow more (cost grows with patches)"
    return None


def resolve_patches(requested: str | int, n_faces: int, max_patches: int) -> tuple[int | None, str]:
    """The number of patches to decimate to (None: one patch per face) and why, for a valid ``patches`` value:
    an integer below the face count decimates to it; "auto" decimates to min(AUTO_PATCHES, max_patches) a mesh
    of more than ``max_patches`` faces and leaves smaller ones alone."""
    if requested == "auto":
        if n_faces > max_patches:
            target = min(AUTO_PATCHES, max_patches)
            return target, (f"patches = auto: the mesh's {n_faces} faces exceed max_patches ({max_patches}): "
                            f"decimated to {target} patches")
        return None, f"patches = auto: one patch per face ({n_faces} faces <= max_patches {max_patches})"
    assert isinstance(requested, int)
    if requested >= n_faces:
        return None, f"patches = {requested}: one patch per face ({n_faces} faces)"
    return requested, f"patches = {requested}: decimated from {n_faces} faces"


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


def _max_normalized_radius(cam: PinholeCamera, dist: tuple[float, float, float, float, float]) -> float:
    """Largest undistorted normalized radius inside the image (its corners and edge midpoints) + 10 %."""
    import cv2

    w, h = cam.width_px, cam.height_px
    pts = np.array([[x, y] for x in (-0.5, (w - 1) / 2, w - 0.5) for y in (-0.5, (h - 1) / 2, h - 0.5)],
                   dtype=np.float64).reshape(-1, 1, 2)
    und = cv2.undistortPoints(pts, cam.K, np.asarray(dist, float)).reshape(-1, 2)
    return float(np.max(np.linalg.norm(und, axis=1)) * 1.1)
