"""Calibration settings: the targets the operator owns and how each step captures them.

Read from an optional ``[calibration]`` table of the rig config TOML (``docs/calibration.md`` lists every key);
anything left out takes the default here. Errors name the file and the dotted field (``ConfigError``).
"""
from __future__ import annotations

import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from drivers.errors import ConfigError

from ..data import default_config_text

if TYPE_CHECKING:  # annotations only: rig.config imports this module to check [calibration]
    from ..config import RigConfig

Vec3 = tuple[float, float, float]

__all__ = ["resolve_sizes", "BoardSettings", "PoseTargetSettings", "LedSurveySettings", "MirrorBallSettings",
           "DiffuseSphereSettings", "ExtinctionSettings", "RadiometrySettings", "SeedKSettings",
           "CalibrationSettings", "load_settings", "aruco_dictionary"]


def aruco_dictionary(name: str) -> int:
    """OpenCV predefined ArUco dictionary id for a name such as ``"DICT_4X4_50"``."""
    import cv2

    value = getattr(cv2.aruco, name, None) if name.startswith("DICT_") else None
    if not isinstance(value, int):
        raise ValueError(f"unknown ArUco dictionary {name!r} (e.g. DICT_4X4_50, DICT_5X5_100)")
    return value


@dataclass(frozen=True)
class BoardSettings:
    """ChArUco board (OpenCV ``CharucoBoard``) for the intrinsics."""

    squares_x: int = 9
    squares_y: int = 7
    square_mm: float = 0.0            # 0 = auto: the board spans 75% of the field of view's width at the look-at
    marker_mm: float = 0.0            # 0 = auto: 0.73 x square_mm
    dictionary: str = "DICT_4X4_50"
    views: int = 20                   # board poses the operator takes
    min_corners: int = 8              # a view with fewer detected corners is dropped
    fix_k3: bool = True               # narrow lenses cannot separate k3 from k1, k2
    white_fraction: float = 0.6       # exposure: the white squares at this fraction of full scale (design)


@dataclass(frozen=True)
class PoseTargetSettings:
    """Survey plates: a black-and-white quadrant target over a reflector, named by the ArUco marker above it
    (``[[targets]]`` named ``aruco_<id>`` in the rig config give the reflectors' design positions; without any,
    ``count`` plates are laid out around the camera's look-at point)."""

    dictionary: str = "DICT_4X4_50"
    marker_mm: float = 0.0            # 0 = auto: 5.5% of the field of view's width at the look-at
    target_mm: float = 0.0            # quadrant target over the reflector; 0 = marker_mm
    margin_mm: float = 0.0            # white around and between marker and target; 0 = 0.3 x marker_mm
    count: int = 12
    first_id: int = 32                # generated layout: marker ids first_id.. (the board uses 0..)
    depth_mm: float = 150.0           # generated layout: plates at look-at depth -depth..+depth
    fill: float = 0.8                 # generated layout: fraction of the half field of view used
    white_fraction: float = 0.6


@dataclass(frozen=True)
class LedSurveySettings:
    """LEDs carrying a reflector for the total station (targets ``led_<index>``)."""

    leds: tuple[int, ...] = ()        # () = ``count`` LEDs spread over the sphere (farthest-point order)
    count: int = 12
    fit: str = "rigid"                # "rigid" | "similarity" (design -> surveyed)
    min_distance_mm: float = 1000.0   # automatic choice: only LEDs this far from the total station (focus, ATR)


@dataclass(frozen=True)
class MirrorBallSettings:
    radius_mm: float = 0.0             # 0 = auto: 18% of the field of view's height at the look-at
    center_mm: Vec3 = (0.0, 0.0, 0.0)  # nominal (the fit finds it)
    leds: tuple[int, ...] = ()         # () = ``count`` LEDs among those the ball shows well
    count: int = 0                     # 0 = every LED whose highlight normal is within max_normal_deg
    max_normal_deg: float = 62.0
    highlight_fraction: float = 0.4    # exposure: highlight peak at this fraction of full scale (design)
    silhouette_fraction: float = 0.5
    specular_reflectance: float = 0.6  # design guess for the exposure
    diffuse_albedo: float = 0.05       # design guess for the silhouette exposure


@dataclass(frozen=True)
class DiffuseSphereSettings:
    radius_mm: float = 0.0             # 0 = auto: 18% of the field of view's height at the look-at
    center_mm: Vec3 = (0.0, 0.0, 0.0)
    albedo: Vec3 = (0.99, 0.99, 0.99)  # hemispherical reflectance of the sphere's coating
    leds: tuple[int, ...] = ()         # () = ``count`` LEDs that light the camera-facing side, spread
    count: int = 0                     # 0 = all of them
    min_cos: float = 0.25              # pixels where n.w_led is below this are not used (terminator)
    erode_px: int = 3
    fraction: float = 0.5              # exposure: brightest pixel at this fraction of full scale (design)


@dataclass(frozen=True)
class ExtinctionSettings:
    leds: tuple[int, ...] = ()         # () = ``count`` LEDs with central highlights
    count: int = 3
    exposure_ratio: float = 50.0       # cross-polarized exposure / parallel exposure
    max_ratio: float = 0.01            # the check fails above this
    aperture_px: float = 4.0


@dataclass(frozen=True)
class RadiometrySettings:
    tile_mm: float = 0.0                     # 0 = auto: 60% of the field of view's width at the look-at
    tile_center_mm: Vec3 = (0.0, 0.0, 0.0)
    tile_normal: Vec3 = (0.0, -1.0, 0.0)
    reflectance: Vec3 = (0.99, 0.99, 0.99)   # 99% Spectralon; a ColorChecker patch: its measured reflectance
    dark_frames: int = 3
    series: int = 7                          # exposure series length (geometric, factor 1.6)
    series_factor: float = 1.6
    series_top_fraction: float = 1.3         # the longest exposure reaches this fraction of full scale (design)
    roi_px: int = 11


@dataclass(frozen=True)
class SeedKSettings:
    material: str = ""                 # a row of the material table; "" = the config's [scene] material
    sigma_s_prime_per_mm: Vec3 | None = None
    sigma_a_per_mm: Vec3 | None = None
    eta: float = 0.0                   # 0 = [estimation] eta
    radius_mm: float = 0.0             # 0 = [object] radius_mm (the reference sits where objects sit)
    erode_px: int = 3
    lut_size: int = 65                 # gradient maps' response table (as the estimator; smaller is faster)


@dataclass(frozen=True)
class CalibrationSettings:
    board: BoardSettings = field(default_factory=BoardSettings)
    pose_targets: PoseTargetSettings = field(default_factory=PoseTargetSettings)
    led_survey: LedSurveySettings = field(default_factory=LedSurveySettings)
    mirror_ball: MirrorBallSettings = field(default_factory=MirrorBallSettings)
    diffuse_sphere: DiffuseSphereSettings = field(default_factory=DiffuseSphereSettings)
    extinction: ExtinctionSettings = field(default_factory=ExtinctionSettings)
    radiometry: RadiometrySettings = field(default_factory=RadiometrySettings)
    seed_k: SeedKSettings = field(default_factory=SeedKSettings)

    def with_(self, **sections: Any) -> "CalibrationSettings":
        """A copy with some sections' fields replaced: ``with_(board={"views": 8})``."""
        out = self
        for name, changes in sections.items():
            out = replace(out, **{name: replace(getattr(out, name), **changes)})
        return out


def _model() -> Any:
    global _MODEL
    if _MODEL is None:
        from ..schema import model_from_dataclass

        _MODEL = model_from_dataclass(CalibrationSettings, name="CalibrationTable")
    return _MODEL


_MODEL: Any = None


def _parse(file: str, table: Any, config: RigConfig | None = None) -> CalibrationSettings:
    """Check ``table`` against the schema built from these dataclasses (unknown keys refused with a "did you
    mean", strict types), then the rules across keys (:func:`_check`)."""
    from ..schema import validate

    model = validate(table, file, _model(), prefix=("calibration",))
    s = CalibrationSettings()
    for name, changes in model.model_dump(exclude_unset=True).items():
        section = getattr(s, name)
        for key, value in list(changes.items()):
            where = f"calibration.{name}.{key}"
            if key == "leds" and any(v < 0 for v in value):
                raise ConfigError(file, where, "a list of LED indices (integers >= 0)", list(value))
            if isinstance(value, tuple) and key != "leds":
                changes[key] = tuple(float(v) for v in value)
        s = replace(s, **{name: replace(section, **changes)})
    if config is not None:
        s = resolve_sizes(config, s)
    _check(file, s)
    return s


def resolve_sizes(config: RigConfig, s: CalibrationSettings) -> CalibrationSettings:
    """Replace the ``0 = auto`` target sizes by sizes fitted to the camera's field of view at its look-at point
    (convenient in simulation; a real rig's targets have the sizes written in ``[calibration]``)."""
    c = config.camera
    d = float(np.linalg.norm(np.asarray(c.look_at_mm, float) - np.asarray(c.position_mm, float)))
    fw, fh = c.width_px / c.fx_px * d, c.height_px / c.fx_px * d
    b, p = s.board, s.pose_targets
    square = b.square_mm or round(0.75 * fw / b.squares_x, 2)
    marker = p.marker_mm or round(0.055 * fw, 2)
    return s.with_(board={"square_mm": square, "marker_mm": b.marker_mm or round(0.73 * square, 2)},
                   pose_targets={"marker_mm": marker, "target_mm": p.target_mm or marker,
                                 "margin_mm": p.margin_mm or round(0.3 * marker, 2)},
                   mirror_ball={"radius_mm": s.mirror_ball.radius_mm or round(0.18 * fh, 1)},
                   diffuse_sphere={"radius_mm": s.diffuse_sphere.radius_mm or round(0.18 * fh, 1)},
                   radiometry={"tile_mm": s.radiometry.tile_mm or round(0.6 * fw, 1)})


def _check(file: str, s: CalibrationSettings) -> None:
    b = s.board
    if b.squares_x < 3 or b.squares_y < 3:
        raise ConfigError(file, "calibration.board.squares_x", "at least 3 x 3 squares", (b.squares_x, b.squares_y))
    if not 0 < b.marker_mm < b.square_mm:
        raise ConfigError(file, "calibration.board.marker_mm", f"a size in (0, square_mm={b.square_mm})",
                          b.marker_mm)
    if b.views < 3:
        raise ConfigError(file, "calibration.board.views", "at least 3 views (Zhang 2000)", b.views)
    for where, name in (("calibration.board.dictionary", b.dictionary),
                        ("calibration.pose_targets.dictionary", s.pose_targets.dictionary)):
        try:
            aruco_dictionary(name)
        except ValueError as exc:
            raise ConfigError(file, where, "an OpenCV ArUco dictionary name (DICT_4X4_50...)", name) from exc
    if s.led_survey.fit not in ("rigid", "similarity"):
        raise ConfigError(file, "calibration.led_survey.fit", "rigid or similarity", s.led_survey.fit)
    for where, v in (("calibration.mirror_ball.radius_mm", s.mirror_ball.radius_mm),
                     ("calibration.diffuse_sphere.radius_mm", s.diffuse_sphere.radius_mm),
                     ("calibration.radiometry.tile_mm", s.radiometry.tile_mm),
                     ("calibration.extinction.exposure_ratio", s.extinction.exposure_ratio)):
        if not v > 0:
            raise ConfigError(file, where, "a number > 0", v)
    import cv2

    p = s.pose_targets
    size = cv2.aruco.getPredefinedDictionary(aruco_dictionary(p.dictionary)).bytesList.shape[0]
    if p.first_id < 0 or p.first_id + p.count > size:
        raise ConfigError(file, "calibration.pose_targets.first_id", f"marker ids first_id..first_id+count-1 within "
                          f"{p.dictionary} (0..{size - 1})", p.first_id)
    board_ids = b.squares_x * b.squares_y // 2
    if p.dictionary == b.dictionary and p.first_id < board_ids:
        raise ConfigError(file, "calibration.pose_targets.first_id", f">= {board_ids} (the board's markers use ids "
                          f"0..{board_ids - 1} of the same dictionary)", p.first_id)
    if s.pose_targets.count < 4:
        raise ConfigError(file, "calibration.pose_targets.count", "at least 4 targets (solvePnP)",
                          s.pose_targets.count)
    if s.led_survey.count < 3 and not s.led_survey.leds:
        raise ConfigError(file, "calibration.led_survey.count", "at least 3 LEDs (rigid fit)", s.led_survey.count)


def load_settings(config: RigConfig, table: dict[str, Any] | None = None) -> CalibrationSettings:
    """The ``[calibration]`` table of ``config``'s TOML file (or ``table``), validated; defaults if absent, and
    ``0 = auto`` sizes resolved for the config's camera (:func:`resolve_sizes`)."""
    if table is not None:
        return _parse(config.source, table, config)
    src = config.source
    text = None
    if src.startswith("<package>"):
        text = default_config_text()
    elif not src.startswith("<") and Path(src).is_file():
        text = Path(src).read_text()
    data = tomllib.loads(text) if text is not None else {}
    return _parse(src, data.get("calibration", {}), config)
