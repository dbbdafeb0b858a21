"""``rig config --check``: everything about a rig config that can be known without a device.

:func:`check_config` loads the file (the schema of :mod:`rig.config.schema`, the checks across keys of
:mod:`rig.config`, ``[calibration]``), then builds the plan of every estimator and refuses the config if that
plan has a problem: a pattern over the current limit, a watchdog that does not cover an exposure, a predicted
over-temperature (``rig.acquire.plan.budget``). It returns the resolved config (every default filled in).
:func:`json_schema` is the JSON Schema of the file for editors (``rig/data/rig-config.schema.json``).
"""
from __future__ import annotations

import dataclasses
from importlib import resources
from pathlib import Path
from typing import Any

from drivers.errors import ConfigError

SCHEMA_FILE = "rig-config.schema.json"
ALL_ESTIMATES = ("gradients", "single-image", "specular")

__all__ = ["check_config", "json_schema", "SCHEMA_FILE", "packaged_schema_text"]


def check_config(path: str | Path | None) -> dict[str, Any]:
    """Validate the config at ``path`` (None: the packaged default) and the plan of every estimator on it.

    Returns ``{"file", "ok": True, "rig", "config", "calibration", "budget"}`` with the resolved values;
    raises :class:`ConfigError` naming the file and the field of the first problem."""
    from rig.config.calibration_settings import load_settings
    from rig.config import load_config
    from rig.acquire.geometry import rig_geometry
    from rig.acquire.plan import CaptureRequest, budget, build_plan

    cfg = load_config(path)
    settings = load_settings(cfg)
    steps = build_plan(cfg, rig_geometry(cfg).led_directions, request=CaptureRequest(ALL_ESTIMATES))
    b = budget(steps, cfg)
    if b["problems"]:
        raise ConfigError(cfg.source, b["problem_fields"][0], "a rig the plan of every estimator can run on: "
                          + b["problems"][0])
    return {"file": cfg.source, "ok": True, "rig": cfg.name, "config": cfg.to_dict(),
            "calibration": dataclasses.asdict(settings), "budget": b}


def json_schema() -> dict[str, Any]:
    """JSON Schema (draft 2020-12) of a rig config file, ``[calibration]`` included."""
    from rig.config.calibration_settings import _model
    from rig.config.schema import RigFile

    out = RigFile.model_json_schema()
    cal = _model().model_json_schema()
    defs = out.setdefault("$defs", {})
    defs.update(cal.pop("$defs", {}))
    defs["CalibrationTable"] = cal
    out["properties"]["calibration"] = {"$ref": "#/$defs/CalibrationTable"}
    out["title"] = "sssrig rig config (rig.toml)"
    out["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    return out


def packaged_schema_text() -> str:
    return resources.files("rig.data").joinpath(SCHEMA_FILE).read_text()
