"""Rig configuration: TOML -> frozen dataclasses, validated on load.

The keys, types, ranges and enumerations are the pydantic schema of :mod:`rig.schema` (unknown keys refused with
a "did you mean"); the checks across keys (degenerate camera pose, exposures inside the trigger's range,
driver-specific rules, targets) are here; ``[calibration]`` is checked by :mod:`rig.calibration.settings`.
Every error names the file, the field, what was expected and the value (``drivers.errors.ConfigError``). The
default simulated rig ships in ``rig/data/default_rig.toml`` so that ``rig demo`` needs no user files.
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from drivers.errors import ConfigError

from . import schema
from .data import DEFAULT_RIG, default_config_text

# Jensen et al. 2001 Table 2 (pbrt's units: 1/mm, reduced sigma_s'); see shared science.md section 2.
MATERIALS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "apple": ((2.29, 2.39, 1.97), (0.0030, 0.0034, 0.046)),
    "chicken1": ((0.15, 0.21, 0.38), (0.015, 0.077, 0.19)),
    "chicken2": ((0.19, 0.25, 0.32), (0.018, 0.088, 0.20)),
    "cream": ((7.38, 5.47, 3.15), (0.0002, 0.0028, 0.0163)),
    "ketchup": ((0.18, 0.07, 0.03), (0.061, 0.97, 1.45)),
    "marble": ((2.19, 2.62, 3.00), (0.0021, 0.0041, 0.0071)),
    "potato": ((0.68, 0.70, 0.55), (0.0024, 0.0090, 0.12)),
    "skimmilk": ((0.70, 1.22, 1.90), (0.0014, 0.0025, 0.0142)),
    "skin1": ((0.74, 0.88, 1.01), (0.032, 0.17, 0.48)),
    "skin2": ((1.09, 1.59, 1.79), (0.013, 0.070, 0.145)),
    "wholemilk": ((2.55, 3.21, 3.77), (0.0011, 0.0024, 0.014)),
}

SPHERE_DRIVERS = ("serial", "modbus-tcp", "modbus-rtu")
TRIGGER_DRIVERS = ("esper", "hid", "serial-release")
CAMERA_DRIVERS = ("folder", "gphoto2")
GPHOTO2_CAPTURE_MODES = ("external", "capture")
STATION_DRIVERS = ("geocom",)
Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class SphereConfig:
    driver: str
    url: str
    radius_mm: float
    geodesic_frequency: int
    min_elevation_deg: float
    led_intensity: Vec3
    led_current_a_per_channel: float
    max_total_current_a: float
    max_mean_duty: float
    slots: int
    watchdog_s: float
    settle_s: float
    pattern_peak: float
    # first-order thermal model and LED forward voltage, for the plan's energy and thermal budget (`rig plan`)
    led_forward_voltage_v: float = 3.0
    ambient_c: float = 25.0
    thermal_c_per_a: float = 2.5
    thermal_tau_s: float = 30.0
    over_temperature_c: float = 70.0


@dataclass(frozen=True)
class TriggerConfig:
    """[trigger] (docs/protocols/trigger-boxes.md). ``url = "sim"`` runs the driver against its simulator:
    esper on a pty, hid with the fake box at the ``HidTransport`` seam, serial-release on pyserial ``loop://``."""

    driver: str                   # "esper" | "hid" | "serial-release"
    url: str = ""                 # esper, serial-release: device path, socket://host:port, loop:// or "sim";
    #                               hid: "" (find the box by vendor_id/product_id or path) or "sim"
    timeout_s: float = 1.0        # esper, hid: how long to wait for the box's answer
    min_exposure_s: float = 0.001
    max_exposure_s: float = 60.0
    outputs_mask: int = 0x3F      # esper, hid: enabled outputs, bit i = output i+1 (0x3f = all six)
    vendor_id: int = 0            # hid: USB vendor id
    product_id: int = 0           # hid: USB product id
    serial: str = ""              # hid: USB serial number string, to choose among identical boxes
    path: str = ""                # hid: hidapi device path (e.g. "/dev/hidraw3"); overrides the ids
    focus_lead_s: float = 0.1     # serial-release: RTS (focus) asserted this long before DTR (shutter)


@dataclass(frozen=True)
class CameraConfig:
    driver: str
    folder: str
    width_px: int
    height_px: int
    fx_px: float
    position_mm: Vec3
    look_at_mm: Vec3
    up: Vec3
    exposure_s: float
    key_exposure_s: float
    gain_dn_per_unit: float
    black_level_dn: int
    white_level_dn: int
    read_noise_dn: float
    electrons_per_dn: float
    fetch_timeout_s: float
    # frame files: driver "folder" watches ``folder`` for them, driver "gphoto2" downloads into ``folder``
    pattern: str = "*.dng"        # glob of frame file names, case-insensitive
    port: str = ""                # gphoto2: "usb:001,004", "ptpip:HOST", "disk:/path"; "" = first camera found
    model: str = ""               # gphoto2: camlib model name; "" = the autodetected one
    capture_mode: str = "external"   # gphoto2: "external" (trigger box fires it) | "capture" (gphoto2 does)
    delete_after_download: bool = False   # gphoto2: remove each frame from the camera's card


@dataclass(frozen=True)
class StationConfig:
    driver: str
    url: str
    station_xyz_mm: Vec3
    station_yaw_deg: float
    noise_mm: float
    crc: bool = True                  # GeoCOM CRC-16 on every request and reply
    max_survey_error_mm: float = 50.0  # a survey farther than this from the target's expected position is refused


@dataclass(frozen=True)
class Target:
    name: str
    xyz_mm: Vec3


@dataclass(frozen=True)
class ObjectConfig:
    shape: str                     # "sphere" (radius_mm, placed by surveying survey_target) or "mesh"
    radius_mm: float
    survey_target: str             # "" for a mesh: its vertices are already in the rig frame, no survey
    target_offset_mm: Vec3
    mesh_path: str = ""
    mesh_units_mm: float = 1.0     # millimetres per mesh unit


@dataclass(frozen=True)
class SceneConfig:
    shape: str
    radius_mm: float
    center_mm: Vec3
    material: str
    sigma_s_prime_per_mm: Vec3
    sigma_a_per_mm: Vec3
    eta: float
    tessellation: int
    seed: int
    render: str = "fast"       # simulated camera: "fast" (Jensen dipole) or "mc" (Monte Carlo, simulators.mc)
    mc_spp: int = 64           # Monte Carlo paths per pixel when render = "mc"


@dataclass(frozen=True)
class EstimationConfig:
    key_light_direction: Vec3
    single_image_method: str
    single_image_subdivisions: int
    eta: float
    complements: bool = False      # gradients as x, y, z + complements instead of full + x, y, z
    single_image_model: str = "dipole-jensen"   # profile model of the single-image fit (estimation.single_image)
    compare_models: bool = True    # also fit every other profile model and report them side by side


@dataclass(frozen=True)
class RunnerConfig:
    """[runner]: what the runner does about faults (docs/capture-and-resume.md)."""

    retries: int = 2                  # extra attempts of a step after a timeout or a garbled reply
    busy_timeout_s: float = 10.0      # a device answering BUSY is asked again, with backoff, for this long
    on_led_fault: str = "pause"       # the sphere's LED-fault bit: "pause" | "abort" | "continue"
    on_over_temperature: str = "hold"  # its over-temperature bit: "hold" (dark until cool) | "pause" | "abort"
    lost_timeout_s: float = 120.0     # a lost device may take this long to come back
    max_hold_s: float = 1800.0        # longest over-temperature hold


@dataclass(frozen=True)
class RigConfig:
    name: str
    sphere: SphereConfig
    trigger: TriggerConfig
    camera: CameraConfig
    total_station: StationConfig
    targets: tuple[Target, ...]
    object: ObjectConfig
    scene: SceneConfig
    estimation: EstimationConfig
    runner: RunnerConfig = field(default_factory=RunnerConfig)
    source: str = field(default="<memory>", compare=False)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d.pop("source")
        return d


class _Reader:
    """Typed field access with errors that name the file and the dotted field (``rig.scene_file`` reads with it)."""

    def __init__(self, file: str, data: dict[str, Any], prefix: str = "") -> None:
        self.file, self.data, self.prefix = file, data, prefix

    def _name(self, key: str) -> str:
        return f"{self.prefix}{key}"

    def section(self, key: str) -> "_Reader":
        value = self.data.get(key)
        if not isinstance(value, dict):
            raise ConfigError(self.file, self._name(key), "a table [" + self._name(key) + "]",
                              None if value is None else type(value).__name__)
        return _Reader(self.file, value, self._name(key) + ".")

    def _get(self, key: str, default: Any) -> Any:
        if key in self.data:
            return self.data[key]
        if default is _REQUIRED:
            raise ConfigError(self.file, self._name(key), "a value (field is missing)")
        return default

    def str(self, key: str, default: Any = None, choices: tuple[str, ...] | None = None) -> str:
        v = self._get(key, _REQUIRED if default is None else default)
        if not isinstance(v, str):
            raise ConfigError(self.file, self._name(key), "a string", v)
        if choices is not None and v not in choices:
            raise ConfigError(self.file, self._name(key), "one of " + ", ".join(choices), v)
        return v

    def num(self, key: str, default: Any = None, *, lo: float | None = None, hi: float | None = None,
            positive: bool = False) -> float:
        v = self._get(key, _REQUIRED if default is None else default)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ConfigError(self.file, self._name(key), "a number", v)
        v = float(v)
        if v != v or v in (float("inf"), float("-inf")):
            raise ConfigError(self.file, self._name(key), "a finite number", v)
        if positive and v <= 0:
            raise ConfigError(self.file, self._name(key), "a number > 0", v)
        if lo is not None and v < lo:
            raise ConfigError(self.file, self._name(key), f"a number >= {lo}", v)
        if hi is not None and v > hi:
            raise ConfigError(self.file, self._name(key), f"a number <= {hi}", v)
        return v

    def bool(self, key: str, default: Any = None) -> bool:
        v = self._get(key, _REQUIRED if default is None else default)
        if not isinstance(v, bool):
            raise ConfigError(self.file, self._name(key), "true or false", v)
        return v

    def int(self, key: str, default: Any = None, *, lo: int | None = None, hi: int | None = None) -> int:
        v = self._get(key, _REQUIRED if default is None else default)
        if isinstance(v, bool) or not isinstance(v, int):
            raise ConfigError(self.file, self._name(key), "an integer", v)
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise ConfigError(self.file, self._name(key), f"an integer in [{lo}, {hi}]", v)
        return v

    def vec3(self, key: str, default: Any = None, *, positive: bool = False,
             nonneg: bool = False) -> Vec3:
        v = self._get(key, _REQUIRED if default is None else default)
        ok = (isinstance(v, (list, tuple)) and len(v) == 3
              and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v))
        if not ok:
            raise ConfigError(self.file, self._name(key), "a list of 3 numbers", v)
        if positive and any(x <= 0 for x in v):
            raise ConfigError(self.file, self._name(key), "3 numbers > 0", v)
        if nonneg and any(x < 0 for x in v):
            raise ConfigError(self.file, self._name(key), "3 numbers >= 0", v)
        return (float(v[0]), float(v[1]), float(v[2]))


_REQUIRED = object()

# [trigger] keys each driver reads; a key of another driver (or a typo) is an error, not silently ignored
TRIGGER_KEYS: dict[str, tuple[str, ...]] = {
    "esper": tuple(schema.EsperTrigger.model_fields),
    "hid": tuple(schema.HidTrigger.model_fields),
    "serial-release": tuple(schema.SerialReleaseTrigger.model_fields),
}
_GPHOTO2_ONLY = tuple(k for k in schema.Gphoto2Camera.model_fields if k not in schema.FolderCamera.model_fields)


def _vec(v: Any) -> Vec3:
    return (float(v[0]), float(v[1]), float(v[2]))


def _trigger(file: str, t: Any) -> TriggerConfig:
    """[trigger]: the driver's own keys (schema), plus the rules across keys."""
    if t.max_exposure_s < t.min_exposure_s:
        raise ConfigError(file, "trigger.max_exposure_s", f"a number >= trigger.min_exposure_s ({t.min_exposure_s:g})",
                          t.max_exposure_s)
    if t.driver == "hid":
        if t.url not in ("", "sim"):
            raise ConfigError(file, "trigger.url", '"sim" or no url (a HID box is found by vendor_id and '
                              "product_id, or by path)", t.url)
        if t.url != "sim" and not t.path:
            for key in ("vendor_id", "product_id"):
                if not getattr(t, key):
                    raise ConfigError(file, f"trigger.{key}", f"the box's USB {key.replace('_', ' ')}, 1..0xffff "
                                      "(or trigger.path, or url = \"sim\")", getattr(t, key))
    return TriggerConfig(**t.model_dump())


def _camera(file: str, c: Any) -> CameraConfig:
    d = c.model_dump()
    if d["key_exposure_s"] is None:
        d["key_exposure_s"] = d["exposure_s"]
    d["position_mm"], d["look_at_mm"], d["up"] = _vec(d["position_mm"]), _vec(d["look_at_mm"]), _vec(d["up"])
    if c.driver == "gphoto2":
        if c.folder == "sim":
            raise ConfigError(file, "camera.folder", 'the folder gphoto2 downloads frames into ("sim" needs '
                              'driver "folder")', "sim")
        if c.port == "sim":
            raise ConfigError(file, "camera.port", 'a gphoto2 port ("usb:BUS,DEV", "ptpip:HOST", "disk:/path") or '
                              '"" for the first camera found; there is no simulated gphoto2 camera', c.port)
    cam = CameraConfig(**d)
    if cam.white_level_dn <= cam.black_level_dn:
        raise ConfigError(file, "camera.white_level_dn", "a value above camera.black_level_dn", cam.white_level_dn)
    view = [a - b for a, b in zip(cam.look_at_mm, cam.position_mm)]
    norm = math.sqrt(sum(x * x for x in view))
    if norm < 1e-6:
        raise ConfigError(file, "camera.look_at_mm", f"a point away from camera.position_mm {list(cam.position_mm)} "
                          "(the camera looks from position_mm towards look_at_mm)", list(cam.look_at_mm))
    up = cam.up
    cross = (view[1] * up[2] - view[2] * up[1], view[2] * up[0] - view[0] * up[2], view[0] * up[1] - view[1] * up[0])
    up_norm = math.sqrt(sum(x * x for x in up))
    if up_norm == 0 or math.sqrt(sum(x * x for x in cross)) < 1e-6 * norm * up_norm:
        raise ConfigError(file, "camera.up", "a direction not parallel to the view direction look_at_mm - "
                          f"position_mm = {[round(x, 6) for x in view]}", list(up))
    return cam


def _check_exposures(file: str, camera: CameraConfig, trigger: TriggerConfig) -> None:
    """Every exposure the plan fires must be inside the trigger's range, and not round to 0 ms."""
    for key in ("exposure_s", "key_exposure_s"):
        v = getattr(camera, key)
        if not trigger.min_exposure_s <= v <= trigger.max_exposure_s:
            raise ConfigError(file, f"camera.{key}", f"an exposure inside the trigger's range trigger.min_exposure_s"
                              f"..trigger.max_exposure_s = {trigger.min_exposure_s:g}..{trigger.max_exposure_s:g} s", v)
        if round(v * 1000.0) < 1:
            raise ConfigError(file, f"camera.{key}", "an exposure of at least 1 ms (the triggers time whole "
                              "milliseconds)", v)


def parse_config(data: dict[str, Any], file: str = "<memory>") -> RigConfig:
    """Validate a parsed TOML document (:mod:`rig.schema` plus the checks across fields); raise
    :class:`ConfigError` naming the first bad field. ``[calibration]`` is checked by :func:`load_config`."""
    m = schema.validate(data, file)
    s = m.sphere.model_dump()
    s["led_intensity"] = _vec(s["led_intensity"])
    sphere = SphereConfig(**s)
    trigger = _trigger(file, m.trigger)
    camera = _camera(file, m.camera)
    _check_exposures(file, camera, trigger)
    station = StationConfig(**{**m.total_station.model_dump(), "station_xyz_mm": _vec(m.total_station.station_xyz_mm)})
    targets = tuple(Target(t.name, _vec(t.xyz_mm)) for t in m.targets)
    names = [tg.name for tg in targets]
    if len(set(names)) != len(names):
        raise ConfigError(file, "targets", "unique target names", names)
    o = m.object.model_dump()
    o["target_offset_mm"] = _vec(o["target_offset_mm"])
    obj = ObjectConfig(**o)
    if obj.survey_target and obj.survey_target not in names:
        raise ConfigError(file, "object.survey_target", "the name of a [[targets]] entry (" + ", ".join(names) + ")"
                          + schema.did_you_mean(obj.survey_target, names), obj.survey_target)
    sc = m.scene.model_dump()
    default_s, default_a = MATERIALS.get(sc["material"], (None, None))
    for key, default in (("sigma_s_prime_per_mm", default_s), ("sigma_a_per_mm", default_a)):
        if sc[key] is None and default is None:
            raise ConfigError(file, f"scene.{key}", 'a value (field is missing; material = "custom")')
        sc[key] = _vec(sc[key] if sc[key] is not None else default)
    sc["center_mm"] = _vec(sc["center_mm"])
    scene = SceneConfig(**sc)
    e = m.estimation.model_dump()
    e["key_light_direction"] = _vec(e["key_light_direction"])
    if not any(e["key_light_direction"]):
        raise ConfigError(file, "estimation.key_light_direction", "a non-zero direction", [0.0, 0.0, 0.0])
    estimation = EstimationConfig(**e)
    runner = RunnerConfig(**m.runner.model_dump())
    return RigConfig(m.rig.name, sphere, trigger, camera, station, targets, obj, scene, estimation, runner, file)


def load_config(path: str | Path | None = None) -> RigConfig:
    """Load and validate a rig config; ``None`` loads the packaged default simulated rig."""
    if path is None:
        text = default_config_text()
        file = f"<package>/rig/data/{DEFAULT_RIG}"
    else:
        p = Path(path)
        file = str(p)
        try:
            text = p.read_text()
        except OSError as exc:
            raise ConfigError(file, "<file>", "a readable TOML file", str(exc)) from exc
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(file, "<syntax>", "valid TOML", str(exc)) from exc
    cfg = parse_config(data, file)
    from .calibration.settings import load_settings   # [calibration]: its keys, types and checks

    load_settings(cfg, data.get("calibration", {}))
    return cfg


