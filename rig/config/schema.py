"""The strict schema of the rig config (``rig.toml``), validated with pydantic v2.

Every table refuses unknown keys (with a "did you mean" for a near miss), every enumeration is a ``Literal``,
numbers are strict (a string or a boolean is never taken for a number) and finite. :func:`validate` turns the
first problem into one :class:`~drivers.errors.ConfigError` line naming the file, the dotted field, what was
expected and the value found. Checks across fields (degenerate camera poses, exposures against the trigger's
range, driver-specific rules, the plan's energy and thermal budget) live in :mod:`rig.config` and
:mod:`rig.acquire.config_check`, which raise the same error. :func:`json_schema` is the JSON Schema editors use
(``rig/data/rig-config.schema.json``; ``rig config --schema``).

The ``[calibration]`` table has its own models, built from the dataclasses of
:mod:`rig.config.calibration_settings` by :func:`model_from_dataclass` (one description of each key, not two).
"""
from __future__ import annotations

import dataclasses
import difflib
import types
import typing
from typing import Annotated, Any, Literal, Mapping, Union

from pydantic import AllowInfNan, BaseModel, ConfigDict, Field, Strict, ValidationError, create_model

from drivers.errors import ConfigError

__all__ = ["RigFile", "validate", "model_from_dataclass", "did_you_mean", "to_config_error", "union_models",
           "MATERIAL_NAMES"]

# ----------------------------------------------------------------------------------------------- scalar types
Num = Annotated[float, Strict(), AllowInfNan(False)]          # an int is taken (TOML 1 == 1.0), a string is not
Int = Annotated[int, Strict()]
Str = Annotated[str, Strict()]
Bool = Annotated[bool, Strict()]
Pos = Annotated[Num, Field(gt=0)]
NonNeg = Annotated[Num, Field(ge=0)]
Vec3 = tuple[Num, Num, Num]
PosVec3 = tuple[Pos, Pos, Pos]
NonNegVec3 = tuple[NonNeg, NonNeg, NonNeg]

MATERIAL_NAMES = ("apple", "chicken1", "chicken2", "cream", "ketchup", "marble", "potato", "skimmilk", "skin1",
                  "skin2", "wholemilk")


class _Table(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


# ------------------------------------------------------------------------------------------------- sections
class RigSection(_Table):
    name: Str


class Sphere(_Table):
    driver: Literal["serial", "modbus-tcp", "modbus-rtu"]
    url: Str
    radius_mm: Pos
    geodesic_frequency: Annotated[Int, Field(ge=1, le=40)]
    min_elevation_deg: Annotated[Num, Field(ge=-90.0, le=90.0)] = -90.0
    led_intensity: PosVec3
    led_current_a_per_channel: Pos
    max_total_current_a: Pos
    max_mean_duty: Annotated[Num, Field(gt=0.0, le=1.0)]
    slots: Annotated[Int, Field(ge=1, le=255)] = 16
    watchdog_s: Annotated[Num, Field(ge=0.0, le=60.0)] = 5.0
    settle_s: Annotated[Num, Field(ge=0.0, le=10.0)] = 0.0
    pattern_peak: Annotated[Num, Field(gt=0.0, le=1.0)] = 1.0
    led_forward_voltage_v: Pos = 3.0
    ambient_c: Annotated[Num, Field(ge=-40.0, le=80.0)] = 25.0
    thermal_c_per_a: NonNeg = 2.5
    thermal_tau_s: Pos = 30.0
    over_temperature_c: Annotated[Num, Field(ge=0.0, le=200.0)] = 70.0


_Exposure = Annotated[Num, Field(gt=0.0, le=3600.0)]
_Mask = Annotated[Int, Field(ge=1, le=0x3F)]
_Timeout = Annotated[Num, Field(gt=0.0, le=60.0)]


class EsperTrigger(_Table):
    driver: Literal["esper"]
    url: Str
    timeout_s: _Timeout = 1.0
    min_exposure_s: _Exposure = 0.001
    max_exposure_s: _Exposure = 60.0
    outputs_mask: _Mask = 0x3F


class HidTrigger(_Table):
    driver: Literal["hid"]
    url: Str = ""
    timeout_s: _Timeout = 1.0
    min_exposure_s: _Exposure = 0.001
    max_exposure_s: _Exposure = 60.0
    outputs_mask: _Mask = 0x3F
    vendor_id: Annotated[Int, Field(ge=0, le=0xFFFF)] = 0
    product_id: Annotated[Int, Field(ge=0, le=0xFFFF)] = 0
    serial: Str = ""
    path: Str = ""


class SerialReleaseTrigger(_Table):
    driver: Literal["serial-release"]
    url: Str
    min_exposure_s: _Exposure = 0.001
    max_exposure_s: _Exposure = 60.0
    focus_lead_s: Annotated[Num, Field(ge=0.0, le=10.0)] = 0.1


class _CameraCommon(_Table):
    folder: Str
    width_px: Annotated[Int, Field(ge=8, le=20000)]
    height_px: Annotated[Int, Field(ge=8, le=20000)]
    fx_px: Pos
    position_mm: Vec3
    look_at_mm: Vec3
    up: Vec3 = (0.0, 0.0, 1.0)
    exposure_s: Annotated[Num, Field(ge=1e-6, le=60.0)]
    key_exposure_s: Annotated[Num, Field(ge=1e-6, le=60.0)] | None = None     # None: exposure_s
    gain_dn_per_unit: Pos
    black_level_dn: Annotated[Int, Field(ge=0, le=65535)]
    white_level_dn: Annotated[Int, Field(ge=1, le=65535)]
    read_noise_dn: NonNeg = 0.0
    electrons_per_dn: Pos = 1.0
    fetch_timeout_s: Pos = 30.0


class FolderCamera(_CameraCommon):
    driver: Literal["folder"]
    pattern: Str = "*.dng"


class Gphoto2Camera(_CameraCommon):
    driver: Literal["gphoto2"]
    pattern: Str = "*"
    port: Str = ""
    model: Str = ""
    capture_mode: Literal["external", "capture"] = "external"
    delete_after_download: Bool = False


class TotalStation(_Table):
    driver: Literal["geocom"]
    url: Str
    station_xyz_mm: Vec3
    station_yaw_deg: Num = 0.0
    noise_mm: NonNeg = 0.0
    crc: Bool = True                      # GeoCOM CRC-16 on every request and reply (docs/protocols/geocom.md)
    max_survey_error_mm: Pos = 50.0       # a survey this far from the target's expected position is refused


class TargetEntry(_Table):
    name: Str
    xyz_mm: Vec3


class SphereObject(_Table):
    shape: Literal["sphere"]
    radius_mm: Pos
    survey_target: Str
    target_offset_mm: Vec3 = (0.0, 0.0, 0.0)


class MeshObject(_Table):
    shape: Literal["mesh"]
    radius_mm: NonNeg = 0.0
    survey_target: Str = ""
    target_offset_mm: Vec3 = (0.0, 0.0, 0.0)
    mesh_path: Str
    mesh_units_mm: Pos = 1.0


class Scene(_Table):
    shape: Literal["sphere"]
    radius_mm: Pos
    center_mm: Vec3 = (0.0, 0.0, 0.0)
    material: Literal[("custom",) + MATERIAL_NAMES] = "custom"         # type: ignore[valid-type]
    sigma_s_prime_per_mm: PosVec3 | None = None                        # None: the material's
    sigma_a_per_mm: NonNegVec3 | None = None
    eta: Annotated[Num, Field(ge=1.0, le=3.0)] = 1.3
    tessellation: Annotated[Int, Field(ge=1, le=7)] = 4
    seed: Annotated[Int, Field(ge=0)] = 0
    render: Literal["fast", "mc"] = "fast"
    mc_spp: Annotated[Int, Field(ge=2, le=1_000_000)] = 64


class Estimation(_Table):
    key_light_direction: Vec3
    single_image_method: Literal["direct", "tikhonov", "pinv"] = "direct"
    single_image_subdivisions: Annotated[Int, Field(ge=1, le=6)] = 3
    eta: Annotated[Num, Field(ge=1.0, le=3.0)] = 1.3
    complements: Bool = False
    single_image_model: Literal["mc-table", "dipole-better", "dipole-jensen"] = "dipole-jensen"
    compare_models: Bool = True


class Runner(_Table):
    """``[runner]``: what the runner does about faults (docs/capture-and-resume.md)."""

    retries: Annotated[Int, Field(ge=0, le=10)] = 2
    busy_timeout_s: Annotated[Num, Field(ge=0.0, le=600.0)] = 10.0
    on_led_fault: Literal["pause", "abort", "continue"] = "pause"
    on_over_temperature: Literal["hold", "pause", "abort"] = "hold"
    lost_timeout_s: Annotated[Num, Field(gt=0.0, le=3600.0)] = 120.0
    max_hold_s: Annotated[Num, Field(gt=0.0, le=86400.0)] = 1800.0


class RigFile(_Table):
    """A whole rig config file. ``[calibration]`` is checked by :mod:`rig.config.calibration_settings`."""

    rig: RigSection
    sphere: Sphere
    trigger: Annotated[Union[EsperTrigger, HidTrigger, SerialReleaseTrigger], Field(discriminator="driver")]
    camera: Annotated[Union[FolderCamera, Gphoto2Camera], Field(discriminator="driver")]
    total_station: TotalStation
    targets: list[TargetEntry] = []
    object: Annotated[Union[SphereObject, MeshObject], Field(discriminator="shape")]
    scene: Scene
    estimation: Estimation
    runner: Runner = Runner()
    calibration: dict[str, Any] = {}


_UNIONS = {"trigger": "driver", "camera": "driver", "object": "shape"}


# ------------------------------------------------------------------------------------------------ errors
def did_you_mean(key: str, known: Any) -> str:
    """`` (did you mean 'x'?)`` for the closest of ``known`` to ``key``, or ``""``."""
    close = difflib.get_close_matches(str(key), [str(k) for k in known], n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _dotted(loc: tuple[Any, ...]) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def _get(data: Any, loc: tuple[Any, ...]) -> Any:
    for part in loc:
        try:
            data = data[part]
        except (KeyError, IndexError, TypeError):
            return None
    return data


def _model_at(model: type[BaseModel], loc: tuple[Any, ...], data: Any) -> type[BaseModel] | None:
    """The model class that owns the last element of ``loc`` (unions resolved by the data's tag)."""
    cur: Any = model
    for i, part in enumerate(loc[:-1]):
        if isinstance(part, int):
            continue
        field = cur.model_fields.get(part) if isinstance(cur, type) and issubclass(cur, BaseModel) else None
        if field is None:
            return None
        cur = _unwrap(field.annotation, _get(data, loc[:i + 1]))
    return cur if isinstance(cur, type) and issubclass(cur, BaseModel) else None


def _unwrap(tp: Any, value: Any) -> Any:
    """The model class inside ``tp`` (list[M], Annotated[Union[...]], M | None) matching ``value``."""
    origin = typing.get_origin(tp)
    if origin is Annotated:
        return _unwrap(typing.get_args(tp)[0], value)
    if origin in (list, tuple):
        return _unwrap(typing.get_args(tp)[0], value)
    if origin in (Union, types.UnionType):
        models = [a for a in typing.get_args(tp) if isinstance(a, type) and issubclass(a, BaseModel)]
        for m in models:
            tag = next((f for f in ("driver", "shape") if f in m.model_fields), None)
            if tag and isinstance(value, dict) and value.get(tag) in typing.get_args(m.model_fields[tag].annotation):
                return m
        return models[0] if len(models) == 1 else None
    return tp


def union_models(root: type[BaseModel], name: Any) -> list[type[BaseModel]]:
    field = root.model_fields.get(name)
    if field is None:
        return []
    return [a for a in typing.get_args(typing.get_args(field.annotation)[0] if typing.get_origin(field.annotation)
                                       is Annotated else field.annotation)
            if isinstance(a, type) and issubclass(a, BaseModel)]


def _base(tp: Any) -> Any:
    while typing.get_origin(tp) is Annotated:
        tp = typing.get_args(tp)[0]
    return tp


def _is_table(tp: Any) -> bool:
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        return True
    return any(_is_table(a) for a in typing.get_args(tp))


def _bounds(model: type[BaseModel] | None, name: Any) -> dict[str, float]:
    if model is None or name not in model.model_fields:
        return {}
    out: dict[str, float] = {}

    def walk(tp: Any, meta: list[Any]) -> None:
        for m in meta:
            for attr in ("gt", "ge", "lt", "le"):
                v = getattr(m, attr, None)
                if v is not None:
                    out[attr] = v
            walk_meta = getattr(m, "metadata", None)
            if walk_meta:
                walk(None, list(walk_meta))
        if tp is not None and typing.get_origin(tp) is Annotated:
            args = typing.get_args(tp)
            walk(args[0], list(args[1:]))

    f = model.model_fields[name]
    walk(f.annotation, list(f.metadata))
    return out


def _expected(err: Mapping[str, Any], model: type[BaseModel] | None, name: Any, integer: bool) -> str:
    t, ctx = err["type"], err.get("ctx") or {}
    if t == "missing":
        return "a value (field is missing)"
    if t in ("float_type", "float_parsing"):
        return "a number"
    if t in ("int_type", "int_parsing", "int_from_float"):
        return "an integer"
    if t == "string_type":
        return "a string"
    if t == "bool_type":
        return "true or false"
    if t == "finite_number":
        return "a finite number"
    if t == "literal_error":
        return "one of " + ctx.get("expected", "").replace("'", "").replace(" or ", ", ")
    if t in ("greater_than", "greater_than_equal", "less_than", "less_than_equal"):
        b = _bounds(model, name)
        lo, hi = b.get("ge", b.get("gt")), b.get("le", b.get("lt"))
        if integer and lo is not None and hi is not None:
            return f"an integer in [{lo}, {hi}]"
        sym = {"greater_than": ">", "greater_than_equal": ">=", "less_than": "<", "less_than_equal": "<="}[t]
        bound = next(iter(v for k, v in ctx.items() if k in ("gt", "ge", "lt", "le")), "?")
        if sym == ">" and bound == 0:
            return "a number > 0"
        return f"a number {sym} {float(bound) if not integer else bound}"
    if t in ("model_type", "model_attributes_type", "dict_type"):
        return "a table"
    if t == "list_type":
        return "an array of tables"
    return err.get("msg", "a valid value")


def to_config_error(exc: ValidationError, data: Any, file: str, root: type[BaseModel],
                    prefix: tuple[Any, ...] = ()) -> ConfigError:
    """The first error of ``exc`` as a :class:`ConfigError` (file, dotted field, expectation, value)."""
    err = exc.errors(include_url=False)[0]
    loc = tuple(err["loc"])
    if loc and loc[0] in _UNIONS and len(loc) > 2 and isinstance(loc[1], str):
        loc = (loc[0],) + loc[2:]                       # drop the union's tag ("trigger.esper.url")
    t = err["type"]
    full = prefix + loc
    if t == "extra_forbidden":
        owner = _model_at(root, loc, data)
        known = list(owner.model_fields) if owner is not None else []
        section = _dotted(full[:-1]) or "the file"
        table = f"[{section}]" if full[:-1] else "the rig config"
        extra = listing = ""
        tag = _UNIONS.get(loc[0]) if len(loc) == 2 else None
        if owner is not None and tag in owner.model_fields:
            extra = f" for {tag} {_get(data, (loc[0], tag))!r}"
            others = [m for m in union_models(root, loc[0]) if m is not owner and loc[-1] in m.model_fields]
            if others:
                listing = f" (it is a key of {tag} " + ", ".join(
                    repr(typing.get_args(m.model_fields[tag].annotation)[0]) for m in others) + ")"
        hint = did_you_mean(loc[-1], known)
        if not listing and len(known) <= 12:
            listing = " (" + ", ".join(known) + ")"
        what = "section" if not full[:-1] else "key"
        return ConfigError(file, _dotted(full), f"a {what} of {table}{extra}{hint}{listing}", _get(data, loc))
    if t in ("union_tag_invalid", "union_tag_not_found"):
        tag = _UNIONS.get(loc[0], "driver")
        tags = (err.get("ctx") or {}).get("expected_tags", "").replace("'", "")
        if t == "union_tag_not_found":
            return ConfigError(file, _dotted(full + (tag,)), "a value (field is missing)")
        return ConfigError(file, _dotted(full + (tag,)), f"one of {tags}", _get(data, loc + (tag,)))
    integer = t.startswith("int")
    if loc and isinstance(loc[-1], int) and len(loc) >= 2 and t not in ("model_type", "model_attributes_type",
                                                                        "dict_type"):
        owner = _model_at(root, loc[:-1], data)         # an element of a 3-vector: name the vector
        value = _get(data, loc[:-1])
        if owner is not None and loc[-2] in owner.model_fields:
            if t == "greater_than":
                expected = "3 numbers > 0"
            elif t == "greater_than_equal":
                expected = "3 numbers >= 0"
            else:
                expected = "a list of 3 numbers"
            return ConfigError(file, _dotted(prefix + loc[:-1]), expected, value)
    owner = _model_at(root, loc, data)
    if t == "missing" and owner is not None and loc and _is_table(owner.model_fields[loc[-1]].annotation):
        return ConfigError(file, _dotted(full), f"a table [{_dotted(full)}] (section is missing)")
    if t in ("too_long", "too_short", "tuple_type"):
        return ConfigError(file, _dotted(full), "a list of 3 numbers", _get(data, loc))
    if t in ("model_type", "model_attributes_type", "dict_type"):
        return ConfigError(file, _dotted(full), f"a table [{_dotted(full)}]", type(_get(data, loc)).__name__)
    if t == "list_type" and loc == ("targets",):
        return ConfigError(file, "targets", "an array of tables [[targets]]", type(_get(data, loc)).__name__)
    if owner is not None and loc and loc[-1] in owner.model_fields:
        integer = integer or _base(owner.model_fields[loc[-1]].annotation) is int
    return ConfigError(file, _dotted(full), _expected(err, owner, loc[-1] if loc else None, integer),
                       None if t == "missing" else _get(data, loc))


def validate(data: Any, file: str, model: type[BaseModel] = RigFile, prefix: tuple[Any, ...] = ()) -> Any:
    """Validate ``data`` against ``model``; raise :class:`ConfigError` for the first problem."""
    if not isinstance(data, dict):
        raise ConfigError(file, _dotted(prefix) or "<document>", "a table", type(data).__name__)
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise to_config_error(exc, data, file, model, prefix) from None


# -------------------------------------------------------------------------------------- dataclass -> model
def _field_type(tp: Any) -> Any:
    if tp is bool:
        return Bool
    if tp is int:
        return Int
    if tp is float:
        return Num
    if tp is str:
        return Str
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple[_field_type(args[0]), ...]
        return tuple[tuple(_field_type(a) for a in args)]  # type: ignore[misc]
    if origin in (Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        return Union[tuple(_field_type(a) for a in inner) + (type(None),)]  # type: ignore[misc]
    return tp


def model_from_dataclass(cls: type, *, name: str | None = None) -> type[BaseModel]:
    """A strict pydantic model with ``cls``'s fields, defaults and types (unknown keys refused); nested
    dataclass fields become nested models."""
    hints = typing.get_type_hints(cls)
    fields: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp):
            fields[f.name] = (model_from_dataclass(tp), Field(default_factory=dict))
            continue
        default = f.default if f.default is not dataclasses.MISSING else ...
        fields[f.name] = (_field_type(tp), default)
    return create_model(name or cls.__name__ + "Table", __config__=ConfigDict(extra="forbid", frozen=True),
                        **fields)
