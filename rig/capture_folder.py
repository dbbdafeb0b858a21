"""Capture folders a user brings from elsewhere -> gradient maps and diffusion (``rig estimate gradients FOLDER``).

A capture folder holds the frames (EXR, float TIFF, 16-bit PNG or camera RAW/DNG) and ``capture.toml`` naming each
frame's pattern, polarization and exposure, the LED calibration (or an ideal-gradient flag), the camera
(orthographic or pinhole), the radiometric scale and optionally an object mask, the object's geometry (a sphere,
for the grounded diffusion estimator) and a seed calibration. The format is documented key by key in
``docs/capture-folder.md``; this module validates it (:func:`load_capture`: every error names the file, the key
and what was expected, as ``rig.config`` does), runs :func:`estimation.gradients.compute_maps` and the diffusion
estimators (:func:`estimate_capture`) and writes the maps with :func:`rig.maps_io.write_maps`.

The session path (``rig.estimate.run_gradients``) and this one call the same estimators with the same conventions:
frames ambient-subtracted and divided by their exposure, ``albedo_scale`` from radiometry
(:func:`estimation.gradients.albedo_scale_from_radiometry`) or from a Lambertian reference
(:func:`estimation.gradients.albedo_scale_from_lambertian`), the LED near field modelled at the sphere, the
grounded sphere estimator (:func:`estimation.diffusion.estimate_sphere`).

References: Ma et al. 2007 (polarized spherical gradients); Zhu, Peers, Debevec, Ghosh, "Estimating diffusion
parameters from polarized spherical gradient illumination" (the seed); Jensen et al. 2001 (dipole);
``docs/gradients.md``; ``shared/reference/science.md`` sec. 3-4, 6.
"""
from __future__ import annotations

import csv
import json
import math
import sys
import tempfile
import time
import tomllib
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from numpy.typing import NDArray

from drivers.errors import ConfigError, RigError
from estimation.camera import OrthographicCamera, PinholeCamera, look_at_rotation
from estimation.gradients import PATTERNS, POLARIZATIONS, LedRig

from .imageio import ImageFileError, read_image
from .provenance import jsonable, sha256_file
from .session import software_version

__all__ = ["CAPTURE_FILE", "CAPTURE_FORMAT", "CAPTURE_FORMAT_VERSION", "CaptureError", "FrameEntry",
           "LedCalibration", "OrthographicCamera", "ReferenceTarget", "Radiometry", "SphereGeometry", "SeedSpec",
           "Capture", "load_capture", "missing_frames", "estimate_capture", "run_cli", "format_summary"]

CAPTURE_FILE = "capture.toml"
CAPTURE_FORMAT = "sssrig-capture"
CAPTURE_FORMAT_VERSION = 1
LED_COLUMNS = ("x_mm", "y_mm", "z_mm", "intensity_r", "intensity_g", "intensity_b")
_AXES = ("x", "y", "z")
FrameKey = tuple[str, str]


class CaptureError(RigError, ValueError):
    """The estimate on a capture folder failed for a reason that is not a malformed ``capture.toml``."""


# ------------------------------------------------------------------------------------------------ reading TOML
_REQ = object()


class _Table:
    """Typed, strict access to one TOML table; errors are :class:`ConfigError` naming file and dotted key."""

    def __init__(self, file: str, data: Mapping[str, Any], prefix: str, allowed: tuple[str, ...]) -> None:
        self.file, self.data, self.prefix = file, data, prefix
        unknown = sorted(set(data) - set(allowed))
        if unknown:
            from .schema import did_you_mean
            raise ConfigError(file, self.key(unknown[0]), "one of the documented keys"
                              + did_you_mean(unknown[0], allowed) + ": " + ", ".join(allowed), unknown[0])

    def key(self, k: str) -> str:
        return f"{self.prefix}{k}"

    def has(self, k: str) -> bool:
        return k in self.data

    def err(self, k: str, expected: str, got: Any = None) -> ConfigError:
        return ConfigError(self.file, self.key(k), expected, got)

    def _get(self, k: str, default: Any) -> Any:
        if k in self.data:
            return self.data[k]
        if default is _REQ:
            raise self.err(k, "a value (key is missing)")
        return default

    def str(self, k: str, default: Any = _REQ, choices: tuple[str, ...] | None = None) -> str:
        v = self._get(k, default)
        if not isinstance(v, str):
            raise self.err(k, "a string", v)
        if choices is not None and v not in choices:
            raise self.err(k, "one of " + ", ".join(choices), v)
        return v

    def bool(self, k: str, default: Any = _REQ) -> bool:
        v = self._get(k, default)
        if not isinstance(v, bool):
            raise self.err(k, "true or false", v)
        return v

    def num(self, k: str, default: Any = _REQ, *, lo: float | None = None, hi: float | None = None,
            positive: bool = False, allow_inf: bool = False) -> float:
        v = self._get(k, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.err(k, "a number", v)
        v = float(v)
        if math.isnan(v) or (math.isinf(v) and not allow_inf):
            raise self.err(k, "a finite number", v)
        if positive and not v > 0:
            raise self.err(k, "a number > 0", v)
        if lo is not None and v < lo:
            raise self.err(k, f"a number >= {lo}", v)
        if hi is not None and v > hi:
            raise self.err(k, f"a number <= {hi}", v)
        return v

    def rgb(self, k: str, default: Any = _REQ, *, positive: bool = False, nonneg: bool = False
            ) -> NDArray[np.float64]:
        """A number (grey) or a list of 3 numbers (R, G, B)."""
        v = self._get(k, default)
        vals = [v] * 3 if isinstance(v, (int, float)) and not isinstance(v, bool) else v
        if not (isinstance(vals, list) and len(vals) == 3
                and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in vals)):
            raise self.err(k, "a number or a list of 3 numbers (R, G, B)", v)
        a = np.asarray(vals, dtype=np.float64)
        if not np.all(np.isfinite(a)):
            raise self.err(k, "finite numbers", v)
        if positive and np.any(a <= 0):
            raise self.err(k, "numbers > 0", v)
        if nonneg and np.any(a < 0):
            raise self.err(k, "numbers >= 0", v)
        return a

    def vec(self, k: str, n: int, default: Any = _REQ) -> NDArray[np.float64]:
        v = self._get(k, default)
        ok = (isinstance(v, list) and len(v) == n
              and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v))
        if not ok or not np.all(np.isfinite(np.asarray(v, dtype=np.float64))):
            raise self.err(k, f"a list of {n} finite numbers", v)
        return np.asarray(v, dtype=np.float64)

    def matrix(self, k: str, cols: int, rows: int | None = None) -> NDArray[np.float64]:
        v = self._get(k, _REQ)
        shape = f"{rows} x {cols}" if rows else f"N x {cols}"
        try:
            a = np.asarray(v, dtype=np.float64)
        except (TypeError, ValueError):
            raise self.err(k, f"a {shape} array of numbers (list of lists)", v) from None
        if (a.ndim != 2 or a.shape[1] != cols or (rows is not None and a.shape[0] != rows) or a.shape[0] == 0
                or isinstance(v, bool) or not np.all(np.isfinite(a))):
            raise self.err(k, f"a {shape} array of finite numbers (list of lists)", f"shape {a.shape}")
        return a

    def table(self, k: str, allowed: tuple[str, ...], required: bool = True) -> "_Table | None":
        v = self.data.get(k)
        if v is None and not required:
            return None
        if not isinstance(v, dict):
            raise self.err(k, f"a table [{self.key(k)}]", None if v is None else type(v).__name__)
        return _Table(self.file, v, self.key(k) + ".", allowed)

    def path(self, k: str, folder: Path, what: str) -> Path:
        """A file path relative to the capture folder (absolute paths are taken as they are); must exist."""
        v = self.str(k)
        p = Path(v)
        p = p if p.is_absolute() else folder / p
        if not p.is_file():
            raise self.err(k, f"an existing {what} file (relative to {folder})", v)
        return p



def _rel(path: Path, folder: Path) -> str:
    try:
        return str(path.relative_to(folder))
    except ValueError:
        return str(path)


# ------------------------------------------------------------------------------------------------ data types
@dataclass(frozen=True)
class FrameEntry:
    """One ``[[frames]]`` entry, validated; ``shape`` is (H, W) of the decoded RGB image."""

    index: int
    file: Path
    pattern: str
    polarization: str
    exposure_s: float
    sha256: str
    source_format: str
    shape: tuple[int, int]

    @property
    def key(self) -> FrameKey:
        return (self.pattern, self.polarization)


@dataclass(frozen=True)
class LedCalibration:
    """``[leds]``: ideal continuous gradients, or point LEDs (positions in the rig frame, radiant intensity per
    channel) with optional displayed drive values per pattern (else the ideal gradients times ``drive_peak``)."""

    ideal: bool
    positions_mm: NDArray[np.float64] | None = None
    intensity: NDArray[np.float64] | None = None
    drive: Mapping[str, NDArray[np.float64]] = field(default_factory=dict)
    drive_peak: float = 1.0
    source: str = "ideal"
    sha256: str | None = None

    def rig(self, patterns: tuple[str, ...]) -> LedRig | None:
        """The :class:`estimation.gradients.LedRig` (None when ideal) for the gradient patterns in use."""
        if self.ideal:
            return None
        assert self.positions_mm is not None and self.intensity is not None
        drive = dict(self.drive)
        if self.drive_peak != 1.0:
            probe = LedRig.from_positions(self.positions_mm, self.intensity)
            for p in patterns:
                drive.setdefault(p, probe.pattern_values(p) * self.drive_peak)
        return LedRig.from_positions(self.positions_mm, self.intensity, patterns=drive or None)

    def provenance(self) -> dict[str, Any]:
        if self.ideal:
            return {"ideal": True}
        assert self.positions_mm is not None
        return {"ideal": False, "source": self.source, "sha256": self.sha256, "count": int(len(self.positions_mm)),
                "drive_patterns": sorted(self.drive), "drive_peak": self.drive_peak}


@dataclass(frozen=True)
class ReferenceTarget:
    """A Lambertian reference (Spectralon-like) of known ``reflectance`` seen in the frames at ``region_px``
    = (x0, y0, x1, y1) (half-open pixel ranges), facing the camera near the rig origin."""

    region_px: tuple[int, int, int, int]
    reflectance: NDArray[np.float64]


@dataclass(frozen=True)
class Radiometry:
    """``[radiometry]``: eta and exactly one source of the albedo scale, plus the clipping / dark levels."""

    eta: float
    albedo_scale: NDArray[np.float64] | None
    value_per_radiance_per_s: NDArray[np.float64] | None
    reference: ReferenceTarget | None
    saturation_level: float
    dark_level: float


@dataclass(frozen=True)
class SphereGeometry:
    center_mm: NDArray[np.float64]
    radius_mm: float


@dataclass(frozen=True)
class SeedSpec:
    """``[seed]``: the seed estimator's calibrated length k (mm, per channel) and where it came from."""

    k_mm: NDArray[np.float64]
    provenance: dict[str, Any]


@dataclass(frozen=True)
class Capture:
    """A validated capture folder with its decoded frames (float32 (H, W, 3) linear RGB, by (pattern, pol))."""

    folder: Path
    file: Path
    sha256: str
    name: str
    frames: tuple[FrameEntry, ...]
    images: Mapping[FrameKey, NDArray[np.float32]]
    leds: LedCalibration
    camera: PinholeCamera | OrthographicCamera
    camera_spec: dict[str, Any]
    radiometry: Radiometry
    mask: NDArray[np.bool_] | None
    mask_file: Path | None
    geometry: SphereGeometry | None
    seed: SeedSpec | None
    specular: bool
    notes: tuple[str, ...] = ()
    relief: Any = None          # rig.folder_diffusion.ReliefGeometry ([object] shape = "relief") or None
    regions: Any = None         # rig.folder_regions.RegionLabels ([object] regions) or None

    @property
    def shape(self) -> tuple[int, int]:
        return self.frames[0].shape

    @property
    def gradient_patterns(self) -> tuple[str, ...]:
        return tuple(p for p in PATTERNS[1:] if (p, "cross") in self.images)


# ------------------------------------------------------------------------------------------------ frame sets
def _axis_ok(have: set[FrameKey], axis: str, pol: str) -> bool:
    g, gc, full = (axis, pol) in have, (axis + "_c", pol) in have, ("full", pol) in have
    return (g and gc) or ((g or gc) and full)


def missing_frames(keys: Any) -> list[str]:
    """What a set of (pattern, polarization) keys lacks for the diffuse maps (empty list = sufficient).

    Sufficient: a cross-polarized ``ambient`` frame and, for each axis a in x, y, z, the cross-polarized
    gradient ``a`` with its complement ``a_c``, or either of them with ``full``.
    """
    have = set(keys)
    out = []
    if ("ambient", "cross") not in have:
        out.append("ambient (cross)")
    for a in _AXES:
        if not _axis_ok(have, a, "cross"):
            present = [p for p in (a, a + "_c", "full") if (p, "cross") in have]
            out.append(f"axis {a}: {a} + {a}_c, or {a} + full, or {a}_c + full (cross); have "
                       + (", ".join(present) if present else "none of them"))
    return out


def _specular_possible(have: set[FrameKey]) -> tuple[bool, str]:
    """Mirrors compute_maps: specular maps need, for the patterns present in *both* polarizations, a solvable
    set per axis (parallel minus cross isolates the specular reflection)."""
    par = {p for p, pol in have if pol == "parallel" and p != "ambient"}
    if not par:
        return False, ""
    both = {(p, "parallel") for p in par if (p, "cross") in have}
    lacking = [a for a in _AXES if not _axis_ok(both, a, "parallel")]
    if lacking:
        return False, ("parallel-polarized frames are present but not enough for specular maps (axes "
                       + ", ".join(lacking) + " need the same patterns as the cross set: gradient + complement "
                       "or gradient + full, in both polarizations)")
    return True, ""


# ------------------------------------------------------------------------------------------------ sections
def _read_frames(file: str, folder: Path, data: dict[str, Any]
                 ) -> tuple[tuple[FrameEntry, ...], dict[FrameKey, NDArray[np.float32]]]:
    raw = data.get("frames")
    if not isinstance(raw, list) or not raw:
        raise ConfigError(file, "frames", "an array of tables [[frames]] (one per frame file)",
                          None if raw is None else type(raw).__name__)
    entries: list[FrameEntry] = []
    images: dict[FrameKey, NDArray[np.float32]] = {}
    seen: dict[FrameKey, int] = {}
    for i, item in enumerate(raw):
        if not isinstance(item, dict):
            raise ConfigError(file, f"frames[{i}]", "a table with file, pattern, polarization, exposure_s",
                              type(item).__name__)
        t = _Table(file, item, f"frames[{i}].", ("file", "pattern", "polarization", "exposure_s"))
        pattern = t.str("pattern", choices=PATTERNS)
        pol = t.str("polarization", choices=POLARIZATIONS)
        exposure = t.num("exposure_s", positive=True)
        key = (pattern, pol)
        if key in seen:
            raise ConfigError(file, f"frames[{i}]", f"a unique (pattern, polarization); frames[{seen[key]}] "
                              f"already is ({pattern}, {pol})", f"({pattern}, {pol})")
        seen[key] = i
        path = t.path("file", folder, "image")
        try:
            img, meta = read_image(path)
        except ImageFileError as exc:
            raise ConfigError(file, f"frames[{i}].file", f"a readable linear image ({exc.reason})",
                              _rel(path, folder)) from None
        recorded = meta.get("exposure_s")
        if isinstance(recorded, (int, float)) and recorded > 0 and abs(recorded / exposure - 1) > 0.02:
            raise ConfigError(file, f"frames[{i}].exposure_s", f"the exposure recorded in {path.name} "
                              f"({recorded:.6g} s) within 2 %", exposure)
        if img.ndim == 2:  # monochrome camera: the same value in R, G, B
            img = np.repeat(img[..., None], 3, axis=-1)
        shape = (int(img.shape[0]), int(img.shape[1]))
        if entries and shape != entries[0].shape:
            f0 = entries[0]
            raise ConfigError(file, f"frames[{i}].file", f"an image of {f0.shape[1]} x {f0.shape[0]} px (W x H) "
                              f"like frames[0] ({_rel(f0.file, folder)})",
                              f"{_rel(path, folder)}: {shape[1]} x {shape[0]} px")
        entries.append(FrameEntry(i, path, pattern, pol, exposure, sha256_file(path), str(meta.get("format")), shape))
        images[key] = img
    miss = missing_frames(images)
    if miss:
        raise ConfigError(file, "frames", "a sufficient frame set: ambient and, per axis, the gradient with its "
                          "complement or with full (all cross-polarized); missing: " + "; ".join(miss),
                          sorted(f"{p}/{pol}" for p, pol in images))
    return tuple(entries), images


def _led_file(t: _Table, folder: Path) -> tuple[NDArray[np.float64], Path]:
    p = t.path("file", folder, "LED calibration (.csv or .npy)")
    if p.suffix.lower() == ".npy":
        try:
            a = np.load(p, allow_pickle=False)
        except Exception as exc:
            raise t.err("file", f"a readable .npy array of shape (N, 6): {', '.join(LED_COLUMNS)}",
                        f"{p.name} ({exc})") from None
        a = np.asarray(a, dtype=np.float64) if np.issubdtype(np.asarray(a).dtype, np.number) else a
        if not (isinstance(a, np.ndarray) and a.ndim == 2 and a.shape[1] == 6 and a.shape[0] > 0):
            raise t.err("file", f"an .npy array of shape (N, 6): {', '.join(LED_COLUMNS)}",
                        f"{p.name}: shape {getattr(a, 'shape', None)}")
        return a, p
    if p.suffix.lower() != ".csv":
        raise t.err("file", "a .csv or .npy file", p.name)
    rows: list[list[float]] = []
    header: list[str] | None = None
    idx: list[int] = []
    with open(p, newline="") as fh:
        for line_no, line in enumerate(fh, start=1):
            if not line.strip() or line.lstrip().startswith("#"):
                continue
            row = next(csv.reader([line]))
            if header is None:
                header = [h.strip() for h in row]
                if sorted(header) != sorted(LED_COLUMNS):
                    raise t.err("file", f"a CSV whose header names the columns {','.join(LED_COLUMNS)}",
                                f"{p.name} line {line_no}: {row}")
                idx = [header.index(c) for c in LED_COLUMNS]
                continue
            try:
                rows.append([float(row[j]) for j in idx])
            except (ValueError, IndexError):
                raise t.err("file", "6 numbers per CSV row", f"{p.name} line {line_no}: {row}") from None
    if not rows:
        raise t.err("file", "at least one LED row", p.name)
    return np.asarray(rows, dtype=np.float64), p


def _read_leds(file: str, folder: Path, data: dict[str, Any]) -> LedCalibration:
    if not isinstance(data.get("leds"), dict):
        raise ConfigError(file, "leds", "a table [leds] with ideal = true or an LED calibration",
                          None if data.get("leds") is None else type(data.get("leds")).__name__)
    t = _Table(file, data["leds"], "leds.", ("ideal", "file", "positions_mm", "intensity", "drive_file", "drive_peak"))
    ideal = t.bool("ideal", False)
    if ideal:
        for k in ("file", "positions_mm", "intensity", "drive_file", "drive_peak"):
            if t.has(k):
                raise t.err(k, "nothing: ideal = true uses the continuous gradients and no LED calibration", k)
        return LedCalibration(ideal=True)
    if t.has("file") == t.has("positions_mm"):
        raise t.err("file", "either file = \"leds.csv\" (or .npy) or positions_mm + intensity inline "
                    "(or ideal = true)", "both" if t.has("file") else "neither")
    sha = None
    if t.has("file"):
        if t.has("intensity"):
            raise t.err("intensity", "nothing: the LED file holds the intensities", "intensity")
        a, p = _led_file(t, folder)
        pos, inten, source, sha = a[:, :3], a[:, 3:], _rel(p, folder), sha256_file(p)
        where = f"{p.name}"
    else:
        pos = t.matrix("positions_mm", 3)
        v = t._get("intensity", _REQ)
        if isinstance(v, list) and v and isinstance(v[0], list):
            inten = t.matrix("intensity", 3, rows=len(pos))
        else:
            inten = np.broadcast_to(t.rgb("intensity", nonneg=True), pos.shape).copy()
        source, where = "inline", "leds.positions_mm"
    if not np.all(np.isfinite(pos)) or np.any(np.linalg.norm(pos, axis=1) <= 0):
        raise t.err("file" if t.has("file") else "positions_mm",
                    "finite LED positions away from the rig origin (mm)", where)
    if not np.all(np.isfinite(inten)) or np.any(inten < 0) or not np.any(inten > 0):
        raise t.err("file" if t.has("file") else "intensity", "finite intensities >= 0, not all zero", where)
    drive: dict[str, NDArray[np.float64]] = {}
    if t.has("drive_file"):
        dp = t.path("drive_file", folder, "drive values (.npz)")
        try:
            with np.load(dp, allow_pickle=False) as z:
                for name in z.files:
                    if name not in PATTERNS[1:]:
                        raise t.err("drive_file", "arrays named after gradient patterns (full, x, y, z, x_c, y_c, "
                                    "z_c)", f"{dp.name}: {name}")
                    arr = np.asarray(z[name], dtype=np.float64)
                    if arr.shape not in ((len(pos),), (len(pos), 3)) or not np.all(np.isfinite(arr)) \
                            or np.any(arr < 0):
                        raise t.err("drive_file", f"per pattern (N,) or (N, 3) finite values >= 0, N = {len(pos)}",
                                    f"{dp.name}: {name} of shape {arr.shape}")
                    drive[name] = arr
        except ConfigError:
            raise
        except Exception as exc:
            raise t.err("drive_file", "a readable .npz file", f"{dp.name} ({exc})") from None
    peak = t.num("drive_peak", 1.0, positive=True, hi=1.0)
    return LedCalibration(False, pos, inten, drive, peak, source, sha)


def _rotation(t: _Table, k: str) -> NDArray[np.float64]:
    R = t.matrix(k, 3, rows=3)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise t.err(k, "a proper rotation (orthonormal rows: camera right, down, forward in the rig frame; "
                    "det +1)", R.tolist())
    return R


def _default_up(direction: NDArray[np.float64]) -> NDArray[np.float64]:
    """The ``up`` a user did not write: +z, or +y when the camera looks (nearly) along z (docs/capture-folder.md)."""
    n = float(np.linalg.norm(direction))
    if n > 0 and abs(float(direction[2])) / n > 0.99:
        return np.array([0.0, 1.0, 0.0])
    return np.array([0.0, 0.0, 1.0])


def _read_camera(file: str, data: dict[str, Any], shape: tuple[int, int]
                 ) -> tuple[PinholeCamera | OrthographicCamera, dict[str, Any]]:
    H, W = shape
    if not isinstance(data.get("camera"), dict):
        raise ConfigError(file, "camera", "a table [camera] with model = \"pinhole\" or \"orthographic\"",
                          None if data.get("camera") is None else type(data.get("camera")).__name__)
    model = data["camera"].get("model")
    common = ("model", "width_px", "height_px", "cx_px", "cy_px", "rotation", "up")
    if model == "pinhole":
        allowed = common + ("fx_px", "fy_px", "position_mm", "look_at_mm", "translation_mm")
    elif model == "orthographic":
        allowed = common + ("pixel_size_mm", "look_direction", "target_mm")
    else:
        raise ConfigError(file, "camera.model", "one of pinhole, orthographic", model)
    t = _Table(file, data["camera"], "camera.", allowed)
    for k, n in (("width_px", W), ("height_px", H)):
        if t.has(k) and t.num(k) != n:
            raise t.err(k, f"the frames' size ({W} x {H} px), or leave it out", t.data[k])
    cx, cy = t.num("cx_px", (W - 1) / 2.0), t.num("cy_px", (H - 1) / 2.0)
    spec: dict[str, Any] = {"model": model, "width_px": W, "height_px": H, "cx_px": cx, "cy_px": cy}
    if model == "pinhole":
        fx = t.num("fx_px", positive=True)
        fy = t.num("fy_px", fx, positive=True)
        if t.has("rotation"):
            for k in ("position_mm", "look_at_mm", "up"):
                if t.has(k):
                    raise t.err(k, "nothing: give the pose as rotation + translation_mm or as position_mm + "
                                "look_at_mm (+ up), not both", k)
            R = _rotation(t, "rotation")
            tvec = t.vec("translation_mm", 3)
            C = -R.T @ tvec                       # OpenCV: X_cam = R X_rig + t  =>  centre C = -R^T t
        else:
            if t.has("translation_mm"):
                raise t.err("translation_mm", "only with rotation (OpenCV extrinsics R, t)", "translation_mm")
            C = t.vec("position_mm", 3)
            target = t.vec("look_at_mm", 3)
            up = t.vec("up", 3) if t.has("up") else _default_up(target - C)
            try:
                R = look_at_rotation(C, target, up)
            except ValueError:
                raise t.err("look_at_mm", "a target away from position_mm, in a direction not parallel to up "
                            f"{up.tolist()}", target.tolist()) from None
        if np.linalg.norm(C) == 0:
            raise t.err("position_mm" if not t.has("rotation") else "translation_mm",
                        "a camera centre away from the rig origin (the object sits there)", C.tolist())
        cam: PinholeCamera | OrthographicCamera = PinholeCamera(
            W, H, fx, fy, cx, cy, tuple(map(tuple, R.tolist())), tuple(map(float, C)))
        spec.update({"fx_px": fx, "fy_px": fy, "rotation": R.tolist(), "center_mm": C.tolist(),
                     "convention": "OpenCV: X_cam = R (X_rig - center_mm); rows of R = right, down, forward"})
        return cam, spec
    px = t.num("pixel_size_mm", positive=True)
    if t.has("rotation"):
        for k in ("look_direction", "up"):
            if t.has(k):
                raise t.err(k, "nothing: give rotation or look_direction (+ up), not both", k)
        R = _rotation(t, "rotation")
    else:
        d = t.vec("look_direction", 3)
        up = t.vec("up", 3) if t.has("up") else _default_up(d)
        if np.linalg.norm(d) == 0:
            raise t.err("look_direction", "a non-zero direction (from the camera towards the object)", d.tolist())
        try:
            R = look_at_rotation(np.zeros(3), d, up)
        except ValueError:
            raise t.err("up", f"a direction not parallel to look_direction {d.tolist()}", up.tolist()) from None
    target = t.vec("target_mm", 3, [0.0, 0.0, 0.0])
    cam = OrthographicCamera(W, H, px, tuple(map(tuple, R.tolist())), tuple(map(float, target)), cx, cy)
    spec.update({"pixel_size_mm": px, "rotation": R.tolist(), "target_mm": target.tolist(),
                 "convention": "X_cam = R (X_rig - target_mm); (u, v) = X_cam[:2] / pixel_size_mm + (cx, cy)"})
    return cam, spec


def _read_radiometry(file: str, data: dict[str, Any], shape: tuple[int, int]) -> Radiometry:
    if not isinstance(data.get("radiometry"), dict):
        raise ConfigError(file, "radiometry", "a table [radiometry] with albedo_scale, value_per_radiance_per_s "
                          "or [radiometry.reference]", None)
    t = _Table(file, data["radiometry"], "radiometry.",
               ("eta", "albedo_scale", "value_per_radiance_per_s", "reference", "saturation_level", "dark_level"))
    eta = t.num("eta", 1.3, lo=1.0, hi=3.0)
    sources = [k for k in ("albedo_scale", "value_per_radiance_per_s", "reference") if t.has(k)]
    if len(sources) != 1:
        raise t.err("albedo_scale", "exactly one of albedo_scale, value_per_radiance_per_s, [radiometry.reference]",
                    sources or "none")
    scale = t.rgb("albedo_scale", positive=True) if t.has("albedo_scale") else None
    vpr = t.rgb("value_per_radiance_per_s", positive=True) if t.has("value_per_radiance_per_s") else None
    ref = None
    if t.has("reference"):
        r = t.table("reference", ("region_px", "reflectance"))
        assert r is not None
        reg = r.vec("region_px", 4)
        H, W = shape
        x0, y0, x1, y1 = (int(v) for v in reg)
        if not (np.all(reg == np.round(reg)) and 0 <= x0 < x1 <= W and 0 <= y0 < y1 <= H):
            raise r.err("region_px", f"integers [x0, y0, x1, y1] with 0 <= x0 < x1 <= {W} and 0 <= y0 < y1 <= {H} "
                        "(half-open pixel ranges)", reg.tolist())
        ref = ReferenceTarget((x0, y0, x1, y1), r.rgb("reflectance", positive=True))
    return Radiometry(eta, scale, vpr, ref, t.num("saturation_level", 0.98, positive=True, allow_inf=True),
                      t.num("dark_level", 0.01, lo=0.0))


def _read_mask(t: _Table, folder: Path, shape: tuple[int, int]) -> tuple[NDArray[np.bool_], Path]:
    p = t.path("mask", folder, "mask image (.png, .tif, .exr)")
    suffix = p.suffix.lower()
    try:
        if suffix == ".png":
            import cv2
            a = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            if a is None:
                raise ValueError("not a readable PNG")
        elif suffix in (".tif", ".tiff"):
            import tifffile
            a = tifffile.imread(str(p))
        elif suffix == ".exr":
            a, _ = read_image(p)
        else:
            raise ValueError(f"unknown suffix {suffix!r}")
    except (ValueError, ImageFileError, OSError) as exc:
        raise t.err("mask", "a PNG (8/16-bit), TIFF or EXR image, non-zero = object", f"{p.name} ({exc})") from None
    a = np.asarray(a)
    if a.ndim == 3:
        a = np.any(a[..., :3] != 0, axis=-1)
    if a.shape != shape:
        raise t.err("mask", f"an image of the frames' size {shape[1]} x {shape[0]} px",
                    f"{p.name}: {a.shape[1] if a.ndim > 1 else '?'} x {a.shape[0]} px")
    return a != 0, p


def _read_object(file: str, folder: Path, data: dict[str, Any], shape: tuple[int, int], camera: Any = None
                 ) -> tuple[NDArray[np.bool_] | None, Path | None, SphereGeometry | None, Any, Any]:
    if "object" not in data:
        return None, None, None, None, None
    if not isinstance(data["object"], dict):
        raise ConfigError(file, "object", "a table [object]", type(data["object"]).__name__)
    t = _Table(file, data["object"], "object.", ("mask", "shape", "center_mm", "radius_mm", "normals_file",
                                                 "height_file", "regions", "region_names"))
    mask, mask_file = _read_mask(t, folder, shape) if t.has("mask") else (None, None)
    shape_kind = t.str("shape", "unknown", choices=("unknown", "sphere", "relief"))
    geo = None
    relief = None
    if shape_kind == "sphere":
        geo = SphereGeometry(t.vec("center_mm", 3), t.num("radius_mm", positive=True))
    else:
        for k in ("center_mm", "radius_mm"):
            if t.has(k):
                raise t.err(k, "nothing unless shape = \"sphere\"", k)
    if shape_kind == "relief":
        from .folder_diffusion import read_relief_geometry
        relief = read_relief_geometry(t, folder, shape, camera)
    else:
        for k in ("normals_file", "height_file"):
            if t.has(k):
                raise t.err(k, "nothing unless shape = \"relief\"", k)
    from .folder_regions import read_regions
    return mask, mask_file, geo, relief, read_regions(t, folder, shape)


def _read_seed(file: str, data: dict[str, Any]) -> SeedSpec | None:
    if "seed" not in data:
        return None
    if not isinstance(data["seed"], dict):
        raise ConfigError(file, "seed", "a table [seed] with k_mm and provenance", type(data["seed"]).__name__)
    t = _Table(file, data["seed"], "seed.", ("k_mm", "provenance"))
    k = t.rgb("k_mm", positive=True)
    prov = t._get("provenance", _REQ)
    if isinstance(prov, str) and prov.strip():
        prov_d: dict[str, Any] = {"note": prov}
    elif isinstance(prov, dict) and prov:
        prov_d = dict(prov)
    else:
        raise t.err("provenance", "a non-empty string or table: the reference material, its D, the geometry and "
                    "rig it was calibrated on, the date (k is an empirical length, not a constant)", prov)
    return SeedSpec(k, prov_d)


def load_capture(folder: str | Path) -> Capture:
    """Read and validate ``FOLDER/capture.toml`` and decode its frames (``docs/capture-folder.md``).

    Raises :class:`drivers.errors.ConfigError` naming the file, the key and what was expected (missing frame file,
    unknown pattern or polarization, duplicate (pattern, polarization), frames of different sizes, an insufficient
    frame set listing what is missing, an unreadable frame with the reader's reason, a RAW frame whose recorded
    exposure differs from ``exposure_s``, bad calibration / camera / radiometry / object / seed values).
    """
    root = Path(folder)
    cfile = root / CAPTURE_FILE
    file = str(cfile)
    if not root.is_dir():
        raise ConfigError(str(root), "<folder>", "a capture folder holding capture.toml", "no such folder")
    try:
        text = cfile.read_text()
    except OSError as exc:
        raise ConfigError(file, "<file>", "a readable capture.toml", str(exc)) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(file, "<syntax>", "valid TOML", str(exc)) from None
    top = _Table(file, data, "", ("format", "format_version", "name", "description", "frames", "leds", "camera",
                                  "radiometry", "object", "seed"))
    if top.str("format") != CAPTURE_FORMAT:
        raise top.err("format", repr(CAPTURE_FORMAT), data.get("format"))
    v = data.get("format_version")
    if v != CAPTURE_FORMAT_VERSION or isinstance(v, bool):
        raise top.err("format_version", str(CAPTURE_FORMAT_VERSION), v)
    name = top.str("name", root.resolve().name)
    top.str("description", "")
    frames, images = _read_frames(file, root, data)
    shape = frames[0].shape
    leds = _read_leds(file, root, data)
    camera, cam_spec = _read_camera(file, data, shape)
    radiometry = _read_radiometry(file, data, shape)
    if radiometry.value_per_radiance_per_s is not None and leds.ideal:
        raise ConfigError(file, "radiometry.value_per_radiance_per_s", "an LED calibration ([leds] file or "
                          "positions_mm + intensity): the irradiance comes from it; with ideal = true give "
                          "albedo_scale or [radiometry.reference]", "leds.ideal = true")
    if radiometry.reference is not None:
        if ("full", "cross") not in images and not any((a, "cross") in images and (a + "_c", "cross") in images
                                                        for a in _AXES):
            raise ConfigError(file, "radiometry.reference", "a cross-polarized full frame, or a gradient with its "
                              "complement (their sum is the full pattern), to measure the reference", None)
    mask, mask_file, geo, relief, regions = _read_object(file, root, data, shape, camera)
    seed = _read_seed(file, data)
    spec_ok, spec_note = _specular_possible(set(images))
    notes = tuple(n for n in (spec_note,) if n)
    return Capture(root, cfile, sha256_file(cfile), name, frames, images, leds, camera, cam_spec, radiometry, mask,
                   mask_file, geo, seed, spec_ok, notes, relief, regions)


# ------------------------------------------------------------------------------------------------ estimate
def _view_dirs(camera: PinholeCamera | OrthographicCamera) -> NDArray[np.float64]:
    _, d = camera.pixel_rays()
    return -d


def _reference_normal(camera: PinholeCamera | OrthographicCamera) -> NDArray[np.float64]:
    """Unit vector from the rig origin towards the camera: the albedo convention's n_ref (docs/gradients.md)."""
    if isinstance(camera, OrthographicCamera):
        return -camera.R[2]
    c = camera.C
    return c / np.linalg.norm(c)


def _reference_signal(cap: Capture, ref: ReferenceTarget) -> NDArray[np.float64]:
    """Median over the reference region of the ambient-subtracted cross full-on value per second."""
    x0, y0, x1, y1 = ref.region_px
    exp = {f.key: f.exposure_s for f in cap.frames}
    sat = cap.radiometry.saturation_level

    def per_s(key: FrameKey) -> NDArray[np.float64]:
        a = cap.images[key][y0:y1, x0:x1].astype(np.float64)
        if np.any(a >= sat):
            raise ConfigError(str(cap.file), "radiometry.reference.region_px", "a reference region without saturated "
                              f"pixels in frame {key[0]}/{key[1]}", list(ref.region_px))
        return a / exp[key]

    amb = per_s(("ambient", "cross"))
    if ("full", "cross") in cap.images:
        sig = per_s(("full", "cross")) - amb
    else:
        a = next(a for a in _AXES if (a, "cross") in cap.images and (a + "_c", "cross") in cap.images)
        sig = per_s((a, "cross")) + per_s((a + "_c", "cross")) - 2 * amb
    med = np.median(sig.reshape(-1, 3), axis=0)
    if np.any(~(med > 0)):
        raise ConfigError(str(cap.file), "radiometry.reference.region_px", "a region showing the lit reference "
                          "(ambient-subtracted full-on signal > 0 in every channel)", med.tolist())
    return med


def _albedo_scale(cap: Capture, leds: LedRig | None, n_ref: NDArray[np.float64]) -> tuple[NDArray[np.float64], dict]:
    from estimation.gradients import albedo_scale_from_lambertian, albedo_scale_from_radiometry

    rad = cap.radiometry
    if rad.albedo_scale is not None:
        return rad.albedo_scale, {"source": "albedo_scale (given)"}
    if rad.value_per_radiance_per_s is not None:
        assert leds is not None
        return (albedo_scale_from_radiometry(rad.value_per_radiance_per_s, leds, eta=rad.eta, reference_normal=n_ref),
                {"source": "value_per_radiance_per_s + LED calibration (albedo_scale_from_radiometry)",
                 "value_per_radiance_per_s": rad.value_per_radiance_per_s})
    assert rad.reference is not None
    sig = _reference_signal(cap, rad.reference)
    return (albedo_scale_from_lambertian(sig, rad.reference.reflectance, eta=rad.eta, leds=leds,
                                         reference_normal=n_ref),
            {"source": "Lambertian reference region (albedo_scale_from_lambertian)",
             "region_px": list(rad.reference.region_px), "reflectance": rad.reference.reflectance,
             "signal_per_s": sig})



def _strip_gradients(prov: Mapping[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in prov.items() if k not in ("gradients", "maps")}


def _check_reference(cap: Capture, reference: Mapping[str, Any]) -> None:
    """--reference needs a known sphere (it renders it); refuse clearly otherwise. Ideal gradients are rendered with
    a dense synthetic LED set (:func:`rig.folder_diffusion.ideal_reference_leds`)."""
    if cap.geometry is None:
        raise ConfigError(str(cap.file), "object.shape", "shape = \"sphere\" with center_mm and radius_mm: "
                          "--reference renders the known sphere by Monte Carlo, and corrects only a sphere's "
                          "estimate", "no sphere ([object] missing or shape = \"unknown\")")
    for k, lo in (("spp", 2), ("iterations", 1), ("seed", 0)):
        v = reference.get(k)
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < lo):
            raise ConfigError(f"--reference-{k}", k, f"an integer >= {lo}", v)


def _reference_summary(cap: Capture, reference: Mapping[str, Any], leds: LedRig | None, scale: Any, eta: float,
                       n_ref: NDArray[np.float64], normals: Any, obj: Any, maps: Any, folder_maps: Any,
                       tile_rows: int) -> dict[str, Any]:
    """The reference-corrected sphere summary (:func:`rig.folder_reference.reference_corrected_sphere`)."""
    from .folder_reference import (REFERENCE_ITERATIONS, REFERENCE_SEED, REFERENCE_SPP,
                                   reference_corrected_sphere)

    assert cap.geometry is not None
    led_pos, led_int = cap.leds.positions_mm, cap.leds.intensity
    if cap.leds.ideal:      # continuous gradients: the renderer sees LEDs as a distant map anyway
        from .folder_diffusion import ideal_reference_leds
        led_pos, led_int = ideal_reference_leds()
        leds = LedRig.from_positions(led_pos, led_int)
    assert leds is not None and led_pos is not None and led_int is not None
    region = np.asarray(obj, dtype=bool) & ~np.asarray(maps.masks.saturated).any(axis=-1)
    try:
        out, _ = reference_corrected_sphere(
            camera=cap.camera, leds=leds, led_positions_mm=led_pos,
            led_intensity=led_int, frame_keys=[f.key for f in cap.frames],
            exposure_s={f.key: f.exposure_s for f in cap.frames}, albedo_scale=scale, eta=eta,
            reference_normal=n_ref, center_mm=cap.geometry.center_mm, radius_mm=cap.geometry.radius_mm,
            true_normals=normals, region=region, folder_maps=folder_maps, observed_maps=maps,
            spp=int(reference.get("spp") or REFERENCE_SPP),
            iterations=int(reference.get("iterations") or REFERENCE_ITERATIONS),
            seed=int(REFERENCE_SEED if reference.get("seed") is None else reference["seed"]), tile_rows=tile_rows,
            render_mode=str(reference.get("render_mode", "mc")))
    except ValueError as exc:
        raise CaptureError(f"{cap.file}: the reference-corrected sphere estimate failed: {exc}") from exc
    return out


MEMMAP_MIN_PX = 4_000_000
"""Frames of at least this many pixels get their full-size intermediate maps as memory maps in a scratch folder
inside the output folder (deleted afterwards) instead of RAM: a 24 MP capture's maps are ~4 frame sets."""


def estimate_capture(capture: Capture, out_dir: str | Path, fmt: str = "exr", tile_rows: int | None = None, *,
                     preview: str = "auto", memmap_min_px: int = MEMMAP_MIN_PX,
                     model: str = "dipole-jensen", maps: Any = None, half: bool = False,
                     reference: Mapping[str, Any] | None = None, relief_window_px: int | None = None
                     ) -> dict[str, Any]:
    """Gradient maps (Ma et al. 2007), the grounded diffusion estimate (with a sphere) and the seed's D (with a
    seed calibration) for a loaded capture; writes the maps into ``out_dir`` (:func:`rig.maps_io.write_maps`) and
    returns a JSON-ready summary (per-channel medians, the diffusion summary with intervals, files, notes).

    ``fmt``: "exr" or "tiff"; ``tile_rows``: rows per processing tile of ``compute_maps`` (None: its default);
    ``memmap_min_px``: see :data:`MEMMAP_MIN_PX`. ``model``: profile model of the grounded estimate
    (:data:`estimation.diffusion.MODELS_GROUNDED`): "dipole-jensen" (default) uses the exact sphere integrals
    (method "sphere"); "dipole-better" and "mc-table" use the first-order method "small_blur" with that model's
    half-space R_d and <r^2>. The summary and sidecar record the model and its bias against the Monte Carlo table
    at the fitted parameters (``diffusion.model_bias``). ``maps``: names of the map files to write (None: all;
    :func:`rig.maps_io.select_maps`), ``half``: normals and albedos as EXR HALF (:data:`rig.maps_io.HALF_OK`);
    the sidecar lists what was written and how the left-out maps are derived.

    ``reference``: None, or {"spp": N, "iterations": K, "seed": S} (missing keys: the defaults of
    :mod:`rig.folder_reference`): with a sphere and an LED calibration, the sphere summary is also corrected by
    Monte Carlo renders of the same capture (:func:`rig.folder_reference.reference_corrected_sphere`) and reported
    as ``diffusion_reference_corrected`` beside the uncorrected ``diffusion``; the per-pixel maps stay uncorrected.

    Without a sphere: with ``[object] shape = "relief"`` (a normals or height file) or with specular normals
    (parallel-polarized frames), the relief-blur fit per window of ``relief_window_px`` pixels (default
    :data:`rig.folder_diffusion.RELIEF_WINDOW_PX`) and its region summary (:func:`rig.folder_diffusion.
    relief_estimate`) are the ``diffusion`` summary; otherwise D, sigma_s', sigma_a are unknown.
    """
    from estimation.diffusion import check_grounded_model

    try:
        check_grounded_model(model, "sphere" if model == "dipole-jensen" else "small_blur", capture.radiometry.eta)
    except ValueError as exc:
        raise ConfigError("--model", "model", str(exc), model) from None
    if reference is not None:
        _check_reference(capture, reference)
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    scratch = (tempfile.TemporaryDirectory(prefix=".scratch-", dir=out_dir)
               if capture.shape[0] * capture.shape[1] >= memmap_min_px else None)
    try:
        return _estimate_capture(capture, out_dir, fmt, tile_rows, preview,
                                 None if scratch is None else Path(scratch.name), model, maps, half, reference,
                                 relief_window_px)
    finally:
        if scratch is not None:
            scratch.cleanup()


def _estimate_capture(capture: Capture, out_dir: str | Path, fmt: str, tile_rows: int | None, preview: str,
                      scratch: Path | None, model: str = "dipole-jensen", select: Any = None,
                      half: bool = False, reference: Mapping[str, Any] | None = None,
                      relief_window_px: int | None = None) -> dict[str, Any]:
    from estimation.diffusion import compare_estimates, diffusion_seed, estimate_sphere, sphere_geometry
    from estimation.gradients import compute_maps

    from .maps_io import write_maps

    t0 = time.perf_counter()
    cap = capture
    rad = cap.radiometry
    leds = cap.leds.rig(cap.gradient_patterns)
    n_ref = _reference_normal(cap.camera)
    H, W = cap.shape
    normals = None
    if cap.geometry is not None:
        normals, view, hit = sphere_geometry(cap.camera, cap.geometry.center_mm, cap.geometry.radius_mm)
        if not hit.any():
            raise ConfigError(str(cap.file), "object.center_mm", "a sphere that the camera sees (no pixel hits "
                              "the sphere at center_mm / radius_mm)", cap.geometry.center_mm.tolist())
        obj = hit if cap.mask is None else hit & cap.mask
        geo_normals = np.where(hit[..., None], np.nan_to_num(normals), 0.0)
        center, radius = cap.geometry.center_mm, cap.geometry.radius_mm
    else:
        view = _view_dirs(cap.camera)
        obj = cap.mask
        geo_normals = None
        center, radius = np.zeros(3), 0.0
    scale, scale_prov = _albedo_scale(cap, leds, n_ref)
    exposure = {f.key: f.exposure_s for f in cap.frames}

    lut_memo: dict[str, Any] = {}

    def folder_maps(images: Mapping[FrameKey, Any], out: Path | None = None) -> Any:
        """The folder's map computation (also applied to the reference renders, converted to frame units). The LED
        response LUT depends only on the LEDs, eta and the surface model: built once per capture (compute_maps'
        defaults), not once per reference render."""
        if not cap.leds.ideal and "lut" not in lut_memo:
            from estimation.gradients import build_response_lut
            lut_memo["lut"] = build_response_lut(leds, eta=rad.eta, reference_normal=n_ref, surface_center_mm=center,
                                                 surface_radius_mm=radius)
        return compute_maps(images, albedo_scale=scale, leds=leds, ideal=cap.leds.ideal, eta=rad.eta,
                            lut=lut_memo.get("lut"),
                            view_dirs=view, tile_rows=tile_rows or 256, white_level=1.0,
                            saturation=rad.saturation_level, dark_threshold=rad.dark_level, object_mask=obj,
                            geometry_normals=geo_normals, reference_normal=n_ref, surface_center_mm=center,
                            surface_radius_mm=radius, exposure_s=exposure, consistency=False, out_dir=out)

    try:
        maps = folder_maps(cap.images, None if scratch is None else scratch / "gradients")
    except ValueError as exc:
        raise CaptureError(f"{cap.file}: gradient maps failed: {exc}") from exc
    t_maps = time.perf_counter() - t0
    notes = list(cap.notes)
    from .folder_diffusion import apply_dark_channels, relief_branch, write_albedo_apparent
    from .folder_regions import channel_medians, grounded_summary, region_summaries
    apply_dark_channels(cap, maps, obj, exposure, notes)
    known = ~maps.unknown
    seed_est = None
    if cap.seed is not None:
        seed_est = diffusion_seed(maps, cap.seed.k_mm, cap.seed.provenance, true_normals=normals)
    diffusion = None
    diff_summary: dict[str, Any]
    relief_files: dict[str, Path] = {}
    relief_fit = None
    ref_summary: dict[str, Any] | None = None
    if cap.geometry is not None:
        assert normals is not None
        method = "sphere" if model == "dipole-jensen" else "small_blur"
        est = estimate_sphere(maps, radius_mm=cap.geometry.radius_mm, true_normals=normals, region=obj,
                              tile_rows=tile_rows or 256, out_dir=None if scratch is None else scratch / "diffusion",
                              method=method, model=model)
        diffusion = est.maps        # the dipole's measured shortening bias widens the intervals (issue 16)
        diff_summary = grounded_summary(est.summary, cap.geometry.radius_mm, rad.eta)
        if reference is not None:
            ref_summary = _reference_summary(cap, reference, leds, scale, rad.eta, n_ref, normals, obj, maps,
                                             folder_maps, tile_rows or 256)
            notes.append("diffusion_reference_corrected: the sphere summary corrected by Monte Carlo reference "
                         "renders; the per-pixel maps are uncorrected")
    elif cap.relief is not None or maps.specular_normals is not None:
        diff_summary, relief_files, relief_fit = relief_branch(
            cap, maps, obj, Path(out_dir), fmt, relief_window_px, notes,
            seed_D_mm=None if seed_est is None else seed_est.D_mm)
    else:
        diff_summary = {"estimator": "grounded", "status": ["unknown"] * 3,
                        "reason": "no geometry ([object] shape = \"sphere\" with center_mm, radius_mm): a region "
                                  "without curvature information carries no information about a length, so D, "
                                  "sigma_s' and sigma_a are unknown (docs/gradients.md sec. 5)"}
        notes.append("diffusion unknown: no object geometry in capture.toml and no specular normals")
    seed_summary = None
    if seed_est is not None:
        assert cap.seed is not None
        seed_summary = {"estimator": "seed D = k R_d/|n_z| (Zhu et al.)", "k_mm": cap.seed.k_mm,
                        "D_mm_median": channel_medians(seed_est.D_mm, ~seed_est.unknown),
                        "provenance": cap.seed.provenance,
                        "caveat": "k is an empirical length valid for the reference's geometry and material "
                                  "(docs/gradients.md sec. 6)"}
        if diffusion is not None:
            cmp = compare_estimates(seed_est, diffusion, region=obj)
            seed_summary["versus_grounded"] = {"median_ratio": cmp.median_ratio,
                                               "fraction_disagree": cmp.fraction_disagree, "rel_tol": cmp.rel_tol}
        elif "versus_seed" in diff_summary:
            seed_summary["versus_relief"] = diff_summary["versus_seed"]
    alb_app, app_write = write_albedo_apparent(cap, maps, geo_normals, leds, n_ref, Path(out_dir), fmt)
    summary: dict[str, Any] = {
        "capture": str(cap.folder), "name": cap.name, "out_dir": str(Path(out_dir)), "format": fmt,
        "mode": "ideal" if cap.leds.ideal else "leds", "eta": rad.eta, "image_px": [W, H],
        "albedo_scale": scale, "albedo_scale_source": scale_prov["source"],
        "maps": {"known_pixels": [int(known[..., c].sum()) for c in range(3)],
                 "albedo_median": channel_medians(maps.albedo, known),
                 "R_d_median": channel_medians(maps.albedo, known),
                 "albedo_apparent_median": channel_medians(alb_app, known),
                 "albedo_definitions": {
                     "R_d": "albedo_diffuse file: the dipole's total diffuse reflectance, exit Fresnel divided out: "
                            "I_full = F_t(eta, n.v) E_full(n)/E_full(n_ref) R_d / albedo_scale",
                     "albedo_apparent": "albedo_apparent file: pi L / E = R_d F_t(eta, n.v) E_t/E (Ma et al. "
                                        "2007's diffuse albedo; a renderer's diffuse texture)"},
                 "diffuse_length_median": channel_medians(maps.diffuse_length(), known),
                 "specular": maps.specular_normals is not None},
        "diffusion": diff_summary, "seed": seed_summary, "notes": notes,
    }
    if ref_summary is not None:
        summary["diffusion_reference_corrected"] = ref_summary
    if cap.regions is not None:     # rig.folder_regions: the same summaries restricted to each labelled region
        summary["regions"] = region_summaries(cap.regions, maps, alb_app, diffusion=diffusion, relief_fit=relief_fit,
                                              radius_mm=radius, eta=rad.eta, unknown_reason=diff_summary.get("reason"))
    prov: dict[str, Any] = {
        "name": cap.name,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "software": {"name": "sssrig", "version": software_version(),
                     "python": sys.version.split()[0], "numpy": np.__version__},
        "capture": {"folder": str(cap.folder.resolve()), "file": CAPTURE_FILE, "sha256": cap.sha256,
                    "format_version": CAPTURE_FORMAT_VERSION},
        "frames": [{"file": _rel(f.file, cap.folder), "pattern": f.pattern, "polarization": f.polarization,
                    "exposure_s": f.exposure_s, "sha256": f.sha256, "format": f.source_format} for f in cap.frames],
        "leds": cap.leds.provenance(),
        "camera": cap.camera_spec,
        "radiometry": {"eta": rad.eta, "albedo_scale_per_s": scale, **scale_prov,
                       "saturation_level": rad.saturation_level, "dark_level": rad.dark_level,
                       "reference_normal": n_ref},
        "object": {"mask": None if cap.mask_file is None else
                   {"file": _rel(cap.mask_file, cap.folder), "sha256": sha256_file(cap.mask_file)},
                   "shape": "sphere" if cap.geometry else ("relief" if cap.relief is not None else "unknown"),
                   **({"center_mm": cap.geometry.center_mm, "radius_mm": cap.geometry.radius_mm}
                      if cap.geometry else {}), "regions": cap.regions and cap.regions.provenance(cap.folder)},
        "seed": None if cap.seed is None else {"k_mm": cap.seed.k_mm, **cap.seed.provenance},
        "parameters": {"format": fmt, "tile_rows": tile_rows or 256, "model": model,
                       "maps": "all" if select is None else list(select), "half": bool(half),
                       "reference": None if ref_summary is None else ref_summary["reference"]},
        "gradients": maps.provenance,
        "diffusion": None if diffusion is None else _strip_gradients(diffusion.provenance),
    }
    try:
        files = write_maps(out_dir, maps, diffusion, fmt=fmt, provenance=prov, seed=seed_est, preview=preview,
                           extra_sidecar={"summary": jsonable(summary)}, select=select, half=half)
    except ValueError as exc:
        raise ConfigError("--maps/--half", "maps", str(exc), select) from None
    except OSError as exc:
        raise CaptureError(f"{out_dir}: cannot write the maps ({exc})") from exc
    try:
        app_path = app_write()
    except OSError as exc:
        raise CaptureError(f"{out_dir}: cannot write the maps ({exc})") from exc
    summary["files"] = {k: str(p) for k, p in {**files, **relief_files, "albedo_apparent": app_path}.items()}
    summary["seconds_maps"] = t_maps
    summary["seconds"] = time.perf_counter() - t0
    return jsonable(summary)


# ------------------------------------------------------------------------------------------------ CLI
def _fmt(v: Any, spec: str = ".4g") -> str:
    return "-" if v is None else format(v, spec)


def format_summary(s: Mapping[str, Any]) -> str:
    """A short human-readable table of :func:`estimate_capture`'s summary."""
    lines = [f"capture {s['name']} ({s['capture']}): {s['image_px'][0]} x {s['image_px'][1]} px, mode {s['mode']}, "
             f"eta {s['eta']}",
             f"maps -> {s['out_dir']} ({s['format']}), {s['seconds']:.1f} s"]
    d = s["diffusion"]
    head = f"{'ch':<3}{'known px':>10}{'albedo':>10}{'|v|/tau':>10}{'D [mm]':>11}{'sigma_s_prime':>15}" \
           f"{'sigma_a':>12}  status"
    lines.append(head)
    m = s["maps"]
    for c, ch in enumerate("RGB"):
        D = d.get("D_mm", {}).get("value", [None] * 3)[c] if "D_mm" in d else None
        ss = d.get("sigma_s_prime_per_mm", {}).get("value", [None] * 3)[c] if "D_mm" in d else None
        sa = d.get("sigma_a_per_mm", {}).get("value", [None] * 3)[c] if "D_mm" in d else None
        lines.append(f"{ch:<3}{m['known_pixels'][c]:>10}{_fmt(m['albedo_median'][c]):>10}"
                     f"{_fmt(m['diffuse_length_median'][c]):>10}{_fmt(D):>11}{_fmt(ss):>15}{_fmt(sa):>12}  "
                     f"{d['status'][c]}")
    r = s.get("diffusion_reference_corrected")
    if r:
        ref = r["reference"]
        lines.append(f"reference-corrected sphere summary ({r['iterations']} Monte Carlo renders at {ref['spp']} spp, "
                     f"seed {ref['seed']}, {r['seconds']:.1f} s; {r['message']}); per-pixel maps uncorrected:")
        lines.append(f"{'ch':<3}{'D [mm]':>11}{'95 % interval':>22}{'sigma_s_prime':>15}{'sigma_a':>12}"
                     f"{'kappa_alb':>11}{'kappa_blur':>11}{'D uncorr.':>11}")
        for c, ch in enumerate("RGB"):
            lo, hi = r["D_mm"]["interval"][c]
            lines.append(f"{ch:<3}{_fmt(r['D_mm']['value'][c]):>11}{'[' + _fmt(lo) + ', ' + _fmt(hi) + ']':>22}"
                         f"{_fmt(r['sigma_s_prime_per_mm']['value'][c]):>15}"
                         f"{_fmt(r['sigma_a_per_mm']['value'][c]):>12}{_fmt(r['kappa_albedo'][c], '.3f'):>11}"
                         f"{_fmt(r['kappa_blur'][c], '.3g'):>11}{_fmt(r['uncorrected']['D_mm'][c]):>11}")
    from .folder_regions import format_regions
    lines += format_regions(s.get("regions"))
    if s.get("seed"):
        lines.append("seed D [mm] (relative, k calibrated elsewhere): "
                     + " ".join(_fmt(v) for v in s["seed"]["D_mm_median"]))
    for n in s.get("notes", []):
        lines.append(f"note: {n}")
    return "\n".join(lines)


def run_cli(args: Any) -> int:
    """``rig estimate gradients FOLDER [--out DIR] [--format exr|tiff] [--tile-rows N] [--model M] [--json]
    [--reference [--reference-spp N] [--reference-iterations K] [--reference-seed S]]``."""
    folder = Path(args.folder)
    out = Path(args.out) if getattr(args, "out", None) else folder / "maps"
    tile_rows = getattr(args, "tile_rows", None)
    if tile_rows is not None and tile_rows < 1:
        raise ConfigError("--tile-rows", "tile_rows", "an integer >= 1", tile_rows)
    reference: dict[str, Any] | None = None
    ref_opts = {k: getattr(args, f"reference_{k}", None) for k in ("spp", "iterations", "seed")}
    if getattr(args, "reference", False):
        reference = ref_opts
    else:
        given = [k for k, v in ref_opts.items() if v is not None]
        if given:
            raise ConfigError(f"--reference-{given[0]}", given[0], "only together with --reference",
                              ref_opts[given[0]])
    cap = load_capture(folder)
    if reference is not None:
        _check_reference(cap, reference)      # before the maps: a missing sphere is a usage error, not a failure
    from .maps_io import select_maps

    try:
        sel = select_maps(getattr(args, "maps", None))
    except ValueError as exc:
        raise ConfigError("--maps", "maps", str(exc), getattr(args, "maps", None)) from None
    summary = estimate_capture(cap, out, getattr(args, "format", "exr") or "exr", tile_rows,
                               model=getattr(args, "model", None) or "dipole-jensen", maps=sel,
                               half=bool(getattr(args, "half", False)), reference=reference,
                               relief_window_px=getattr(args, "relief_window_px", None))
    if getattr(args, "json", False):
        print(json.dumps(summary, indent=2))
    else:
        print(format_summary(summary))
    return 0
