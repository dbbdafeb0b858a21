"""Scene files, the reading: the single-image method on a capture a user brings from elsewhere (docs/scene-file.md).

A scene file (TOML) names a mesh, a calibrated camera, the illumination, eta and one linear image. This module
validates it (:func:`load_scene`) into the types of :mod:`rig.files.scene_spec`; :mod:`rig.estimate.scenes` runs
:func:`estimation.single_image.estimate_single_image` on it and implements ``rig estimate single-image SCENE``.

Every input error raises :class:`SceneFileError` (a :class:`drivers.errors.ConfigError`, hence a ``RigError``)
whose message names the scene file, the key and what was expected, e.g.
``scene.toml: field 'camera.fx_px': expected a number > 0, got -3.0``.
"""
from __future__ import annotations

import math
import os
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from drivers.errors import ConfigError
from estimation.camera import PinholeCamera, look_at_rotation

from rig.config import _REQUIRED, _Reader
from rig.files.imageio import ImageFileError, RAW_SUFFIXES, read_image
from rig.files.provenance import sha256_file
from rig.files.scene_spec import (_AXES, ENV_SUFFIXES, INTEGER_SATURATION, MASK_SUFFIXES, MESH_SUFFIXES, MESH_UNITS_MM,
                         METHODS, MODELS, SCENE_FORMAT_VERSION, Array, CameraSpec, DirectionalLightSpec,
                         EnvironmentSpec, EstimationSpec, ImageSpec, MaterialSpec, MeshFileError, MeshSpec, NoiseSpec,
                         load_triangle_mesh,
                         PointLightSpec, Scene, SceneFileError, Vec3, _max_normalized_radius, patches_error)

__all__ = ["load_scene", "parse_scene"]


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



# ---------------------------------------------------------------------------------------------- sections
def _read_mesh(r: _SceneReader, base: Path) -> tuple[MeshSpec, Any]:
    r.only(("path", "units", "translation_mm", "max_edge_mm"))
    path = r.path("path", base, MESH_SUFFIXES, "a mesh file (PLY, OBJ or STL)")
    assert path is not None
    units = r.str("units", "mm", choices=tuple(MESH_UNITS_MM))
    translation = r.vec3("translation_mm", (0.0, 0.0, 0.0))
    max_edge = r.opt_num("max_edge_mm", positive=True)
    try:
        mesh = load_triangle_mesh(path)
    except MeshFileError as exc:
        raise r.fail("path", f"{exc.expected}; {exc.found}", path.name) from None
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
             "max_patches", "reference_spp", "reference_iterations", "reference_seed", "shadows", "patches"))
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
        reference_seed=es.int("reference_seed", 1, lo=0, hi=2 ** 31 - 1), shadows=shadows,
        patches=es.data.get("patches", "auto"))
    n_faces = len(mesh.faces)
    render_mesh = mesh
    if mesh_spec.max_edge_mm is not None:
        import trimesh
        v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=mesh_spec.max_edge_mm)
        mesh = trimesh.Trimesh(v, f, process=False)
        n_faces = len(f)
    bad = patches_error(estimation.patches, n_faces, estimation.max_patches, mesh_spec.max_edge_mm)
    if bad is not None:
        raise es.fail("patches", bad, estimation.patches)
    if n_faces > estimation.max_patches and mesh_spec.max_edge_mm is not None:   # (otherwise: decimated)
        raise es.fail("max_patches", f"at least the mesh's face count ({n_faces} faces after max_edge_mm); use a "
                      "larger max_edge_mm, or drop it (patches = auto then decimates a mesh of more than "
                      "max_patches faces), or raise max_patches (cost grows with faces x visible faces)",
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
