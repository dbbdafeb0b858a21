"""Scene-file writing shared by the scene-file tests (docs/scene-file.md): a minimal TOML writer, section merging,
and the CLI run of ``rig estimate single-image SCENE --json``."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from rig.cli import main as rig_main


def toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v) if isinstance(v, int) else repr(float(v))
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise TypeError(type(v))


def dump_toml(doc: dict[str, Any]) -> str:
    """Minimal TOML writer: top-level scalars, tables and arrays of tables (enough for scene files)."""
    lines = [f"{k} = {toml_value(v)}" for k, v in doc.items() if not isinstance(v, (dict, list))
             or (isinstance(v, list) and not (v and isinstance(v[0], dict)))]
    for k, v in doc.items():
        if isinstance(v, dict):
            lines.append(f"\n[{k}]")
            lines += [f"{kk} = {toml_value(vv)}" for kk, vv in v.items()]
        elif isinstance(v, list) and v and isinstance(v[0], dict):
            for item in v:
                lines.append(f"\n[[{k}]]")
                lines += [f"{kk} = {toml_value(vv)}" for kk, vv in item.items()]
    return "\n".join(lines) + "\n"


def merge_sections(doc: dict[str, Any], sections: dict[str, Any]) -> dict[str, Any]:
    """Override sections of a scene document: None removes a section, a dict merges into it (a None value removes
    that key), anything else replaces it."""
    for key, value in sections.items():
        if value is None:
            doc.pop(key, None)
        elif isinstance(value, dict) and isinstance(doc.get(key), dict):
            doc[key] = {k: v for k, v in {**doc[key], **value}.items() if v is not None}
        else:
            doc[key] = value
    return doc


def write_scene(folder: Path, doc: dict[str, Any], name: str = "scene.toml") -> Path:
    p = folder / name
    p.write_text(dump_toml(doc))
    return p


def run_single_image(capsys: pytest.CaptureFixture[str], scene: Path, *extra: str) -> tuple[int, dict[str, Any] | None, str]:
    code = rig_main(["estimate", "single-image", str(scene), "--json", *extra])
    out, err = capsys.readouterr()
    return code, (json.loads(out) if out.strip() else None), err
