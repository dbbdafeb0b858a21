"""A capture folder's record types (``capture.toml``, docs/capture-folder.md): frames, LED calibration, reference
target, radiometry, sphere geometry, the seed's k, and the TOML reader with errors naming the field.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from numpy.typing import NDArray

from drivers.errors import ConfigError, RigError
from estimation.camera import OrthographicCamera, PinholeCamera
from estimation.gradients import PATTERNS, LedRig


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
            from rig.config.schema import did_you_mean
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
    relief: Any = None          # rig.estimate.folder_diffusion.ReliefGeometry ([object] shape = "relief") or None
    regions: Any = None         # rig.estimate.folder_regions.RegionLabels ([object] regions) or None
    noise: Any = None           # rig.estimate.capture_folder.noise.NoiseSpec ([noise] / frames' stderr_file) or None

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
