"""Rig configuration: TOML -> frozen dataclasses, validated on load.

Every error names the file, the field and what was expected (``drivers.errors.ConfigError``). The
default simulated rig ships in ``rig/data/default_rig.toml`` so that ``rig demo`` needs no user files.
"""
from __future__ import annotations

import tomllib
from dataclasses import asdict, dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from drivers.errors import ConfigError

DEFAULT_RIG = "default_rig.toml"

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
    source: str = field(default="<memory>", compare=False)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d.pop("source")
        return d


class _Reader:
    """Typed field access with errors that name the file and the dotted field."""

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
_TRIGGER_COMMON = ("driver", "url", "timeout_s", "min_exposure_s", "max_exposure_s")
TRIGGER_KEYS: dict[str, tuple[str, ...]] = {
    "esper": _TRIGGER_COMMON + ("outputs_mask",),
    "hid": _TRIGGER_COMMON + ("outputs_mask", "vendor_id", "product_id", "serial", "path"),
    "serial-release": ("driver", "url", "min_exposure_s", "max_exposure_s", "focus_lead_s"),
}
_GPHOTO2_ONLY = ("port", "model", "capture_mode", "delete_after_download")


def _parse_trigger(t: _Reader) -> TriggerConfig:
    """[trigger]: the driver's own keys, validated; see :class:`TriggerConfig`."""
    driver = t.str("driver", choices=TRIGGER_DRIVERS)
    allowed = TRIGGER_KEYS[driver]
    for key in t.data:
        if key not in allowed:
            raise ConfigError(t.file, t._name(key), f"a key of [trigger] for driver {driver!r} ("
                              + ", ".join(allowed) + ")", key)
    min_s = t.num("min_exposure_s", 0.001, positive=True, hi=3600.0)
    max_s = t.num("max_exposure_s", 60.0, positive=True, hi=3600.0)
    if max_s < min_s:
        raise ConfigError(t.file, t._name("max_exposure_s"), f"a number >= {t.prefix}min_exposure_s ({min_s:g})",
                          max_s)
    common: dict[str, Any] = {"driver": driver, "min_exposure_s": min_s, "max_exposure_s": max_s}
    if driver == "serial-release":
        return TriggerConfig(url=t.str("url"), focus_lead_s=t.num("focus_lead_s", 0.1, lo=0.0, hi=10.0),
                             **common)
    common["timeout_s"] = t.num("timeout_s", 1.0, positive=True, hi=60.0)
    common["outputs_mask"] = t.int("outputs_mask", 0x3F, lo=1, hi=0x3F)
    if driver == "esper":
        return TriggerConfig(url=t.str("url"), **common)
    url = t.str("url", "")
    if url not in ("", "sim"):
        raise ConfigError(t.file, t._name("url"), '"sim" or no url (a HID box is found by vendor_id and '
                          "product_id, or by path)", url)
    path = t.str("path", "")
    vendor_id = t.int("vendor_id", 0, lo=0, hi=0xFFFF)
    product_id = t.int("product_id", 0, lo=0, hi=0xFFFF)
    if url != "sim" and not path:
        for key, value in (("vendor_id", vendor_id), ("product_id", product_id)):
            if not value:
                raise ConfigError(t.file, t._name(key), f"the box's USB {key.replace('_', ' ')}, 1..0xffff "
                                  f"(or {t.prefix}path, or url = \"sim\")", t.data.get(key))
    return TriggerConfig(url=url, vendor_id=vendor_id, product_id=product_id, serial=t.str("serial", ""),
                         path=path, **common)


def _camera_driver_fields(c: _Reader) -> dict[str, Any]:
    """[camera] keys that depend on the driver (the rest of [camera] describes the simulated sensor)."""
    driver = c.str("driver", choices=CAMERA_DRIVERS)
    if driver == "folder":
        for key in _GPHOTO2_ONLY:
            if key in c.data:
                raise ConfigError(c.file, c._name(key), 'no such key with driver "folder" (it is used by '
                                  'driver "gphoto2")', c.data[key])
        return {"pattern": c.str("pattern", "*.dng")}
    if c.str("folder") == "sim":
        raise ConfigError(c.file, c._name("folder"), 'the folder gphoto2 downloads frames into ("sim" needs '
                          'driver "folder")', "sim")
    port = c.str("port", "")
    if port == "sim":
        raise ConfigError(c.file, c._name("port"), 'a gphoto2 port ("usb:BUS,DEV", "ptpip:HOST", '
                          '"disk:/path") or "" for the first camera found; there is no simulated gphoto2 camera',
                          port)
    return {"pattern": c.str("pattern", "*"), "port": port, "model": c.str("model", ""),
            "capture_mode": c.str("capture_mode", "external", choices=GPHOTO2_CAPTURE_MODES),
            "delete_after_download": c.bool("delete_after_download", False)}


def parse_config(data: dict[str, Any], file: str = "<memory>") -> RigConfig:
    """Validate a parsed TOML document; raise :class:`ConfigError` naming the first bad field."""
    top = _Reader(file, data)
    s = top.section("sphere")
    sphere = SphereConfig(
        driver=s.str("driver", choices=SPHERE_DRIVERS), url=s.str("url"),
        radius_mm=s.num("radius_mm", positive=True),
        geodesic_frequency=s.int("geodesic_frequency", lo=1, hi=40),
        min_elevation_deg=s.num("min_elevation_deg", -90.0, lo=-90.0, hi=90.0),
        led_intensity=s.vec3("led_intensity", positive=True),
        led_current_a_per_channel=s.num("led_current_a_per_channel", positive=True),
        max_total_current_a=s.num("max_total_current_a", positive=True),
        max_mean_duty=s.num("max_mean_duty", lo=0.0, hi=1.0, positive=True),
        slots=s.int("slots", 16, lo=1, hi=255), watchdog_s=s.num("watchdog_s", 5.0, lo=0.0, hi=60.0),
        settle_s=s.num("settle_s", 0.0, lo=0.0, hi=10.0),
        pattern_peak=s.num("pattern_peak", 1.0, lo=0.0, hi=1.0, positive=True),
        led_forward_voltage_v=s.num("led_forward_voltage_v", 3.0, positive=True),
        ambient_c=s.num("ambient_c", 25.0, lo=-40.0, hi=80.0),
        thermal_c_per_a=s.num("thermal_c_per_a", 2.5, lo=0.0),
        thermal_tau_s=s.num("thermal_tau_s", 30.0, positive=True),
        over_temperature_c=s.num("over_temperature_c", 70.0, lo=0.0, hi=200.0))
    trigger = _parse_trigger(top.section("trigger"))
    c = top.section("camera")
    camera = CameraConfig(
        driver=c.str("driver", choices=CAMERA_DRIVERS), folder=c.str("folder"),
        width_px=c.int("width_px", lo=8, hi=20000), height_px=c.int("height_px", lo=8, hi=20000),
        fx_px=c.num("fx_px", positive=True), position_mm=c.vec3("position_mm"),
        look_at_mm=c.vec3("look_at_mm"), up=c.vec3("up", (0.0, 0.0, 1.0)),
        exposure_s=c.num("exposure_s", lo=1e-6, hi=60.0),
        key_exposure_s=c.num("key_exposure_s", c.data.get("exposure_s", 0.0), lo=1e-6, hi=60.0),
        gain_dn_per_unit=c.num("gain_dn_per_unit", positive=True),
        black_level_dn=c.int("black_level_dn", lo=0, hi=65535),
        white_level_dn=c.int("white_level_dn", lo=1, hi=65535),
        read_noise_dn=c.num("read_noise_dn", 0.0, lo=0.0),
        electrons_per_dn=c.num("electrons_per_dn", 1.0, positive=True),
        fetch_timeout_s=c.num("fetch_timeout_s", 30.0, positive=True), **_camera_driver_fields(c))
    if camera.white_level_dn <= camera.black_level_dn:
        raise ConfigError(file, "camera.white_level_dn", "a value above camera.black_level_dn",
                          camera.white_level_dn)
    g = top.section("total_station")
    station = StationConfig(
        driver=g.str("driver", choices=STATION_DRIVERS), url=g.str("url"),
        station_xyz_mm=g.vec3("station_xyz_mm"), station_yaw_deg=g.num("station_yaw_deg", 0.0),
        noise_mm=g.num("noise_mm", 0.0, lo=0.0))
    raw_targets = data.get("targets", [])
    if not isinstance(raw_targets, list):
        raise ConfigError(file, "targets", "an array of tables [[targets]]", type(raw_targets).__name__)
    targets = []
    for i, item in enumerate(raw_targets):
        if not isinstance(item, dict):
            raise ConfigError(file, f"targets[{i}]", "a table with name and xyz_mm", item)
        r = _Reader(file, item, f"targets[{i}].")
        targets.append(Target(r.str("name"), r.vec3("xyz_mm")))
    names = [tg.name for tg in targets]
    if len(set(names)) != len(names):
        raise ConfigError(file, "targets", "unique target names", names)
    ob = top.section("object")
    shape = ob.str("shape", choices=("sphere", "mesh"))
    if shape == "mesh":     # a mesh in rig coordinates (e.g. a registered scan): nothing to survey
        obj = ObjectConfig(shape=shape, radius_mm=ob.num("radius_mm", 0.0, lo=0.0),
                           survey_target=ob.str("survey_target", ""),
                           target_offset_mm=ob.vec3("target_offset_mm", (0.0, 0.0, 0.0)),
                           mesh_path=ob.str("mesh_path"),
                           mesh_units_mm=ob.num("mesh_units_mm", 1.0, positive=True))
    else:
        obj = ObjectConfig(shape=shape, radius_mm=ob.num("radius_mm", positive=True),
                           survey_target=ob.str("survey_target"),
                           target_offset_mm=ob.vec3("target_offset_mm", (0.0, 0.0, 0.0)))
    if obj.survey_target and obj.survey_target not in names:
        raise ConfigError(file, "object.survey_target", "the name of a [[targets]] entry ("
                          + ", ".join(names) + ")", obj.survey_target)
    sc = top.section("scene")
    material = sc.str("material", "custom")
    if material != "custom" and material not in MATERIALS:
        raise ConfigError(file, "scene.material", "one of custom, " + ", ".join(MATERIALS), material)
    default_s, default_a = MATERIALS.get(material, (None, None))
    scene = SceneConfig(
        shape=sc.str("shape", choices=("sphere",)), radius_mm=sc.num("radius_mm", positive=True),
        center_mm=sc.vec3("center_mm", (0.0, 0.0, 0.0)), material=material,
        sigma_s_prime_per_mm=sc.vec3("sigma_s_prime_per_mm", default_s, positive=True),
        sigma_a_per_mm=sc.vec3("sigma_a_per_mm", default_a, nonneg=True),
        eta=sc.num("eta", 1.3, lo=1.0, hi=3.0), tessellation=sc.int("tessellation", 4, lo=1, hi=7),
        seed=sc.int("seed", 0, lo=0), render=sc.str("render", "fast", choices=("fast", "mc")),
        mc_spp=sc.int("mc_spp", 64, lo=2, hi=1_000_000))
    e = top.section("estimation")
    estimation = EstimationConfig(
        key_light_direction=e.vec3("key_light_direction"),
        single_image_method=e.str("single_image_method", "direct"),
        single_image_subdivisions=e.int("single_image_subdivisions", 3, lo=1, hi=6),
        eta=e.num("eta", 1.3, lo=1.0, hi=3.0),
        complements=e.bool("complements", False),
        single_image_model=e.str("single_image_model", "dipole-jensen",
                                 choices=("mc-table", "dipole-better", "dipole-jensen")),
        compare_models=e.bool("compare_models", True))
    name = top.section("rig").str("name")
    return RigConfig(name, sphere, trigger, camera, station, tuple(targets), obj, scene, estimation, file)


def load_config(path: str | Path | None = None) -> RigConfig:
    """Load and validate a rig config; ``None`` loads the packaged default simulated rig."""
    if path is None:
        text = resources.files("rig.data").joinpath(DEFAULT_RIG).read_text()
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
    return parse_config(data, file)


def default_config_text() -> str:
    return resources.files("rig.data").joinpath(DEFAULT_RIG).read_text()
