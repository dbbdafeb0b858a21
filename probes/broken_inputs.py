"""Probe (issue 18): broken rig configs and broken inputs through the ``rig`` command line.

1. Every config of :data:`BROKEN` (the packaged default with one mistake) must be refused by ``rig config
   --check`` with exit code 2 and a one-line error naming the file and the field.
2. Every command of :func:`bad_inputs` (missing files, broken JSON, bad arguments, a broken session) must fail
   with a one-line error, never a Python traceback.

    python probes/broken_inputs.py            # prints one JSON line per case on stderr, a summary on stdout
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rig.config import default_config_text  # noqa: E402


def _set(path: str, value: Any) -> Callable[[dict], None]:
    def f(d: dict) -> None:
        *head, last = path.split(".")
        for k in head:
            d = d.setdefault(k, {})
        d[last] = value
    return f


def _del(path: str) -> Callable[[dict], None]:
    def f(d: dict) -> None:
        *head, last = path.split(".")
        for k in head:
            d = d[k]
        del d[last]
    return f


# (what is wrong, mutation, the field the error must name)
BROKEN: list[tuple[str, Callable[[dict], None], str]] = [
    ("typo in [sphere] (a safety setting)", _set("sphere.watchdg_s", 0.5), "sphere.watchdg_s"),
    ("negative sphere radius", _set("sphere.radius_mm", -1.0), "sphere.radius_mm"),
    ("unknown sphere driver", _set("sphere.driver", "usb"), "sphere.driver"),
    ("typo in [trigger]", _set("trigger.outputs_msk", 3), "trigger.outputs_msk"),
    ("trigger max below the key frame's exposure", _set("trigger.max_exposure_s", 1.0), "camera.key_exposure_s"),
    ("trigger min above the gradient exposure", _set("trigger.min_exposure_s", 0.5), "camera.exposure_s"),
    ("camera looks at itself", _set("camera.look_at_mm", [0.0, -400.0, 0.0]), "camera.look_at_mm"),
    ("camera up parallel to the view", _set("camera.up", [0.0, 1.0, 0.0]), "camera.up"),
    ("typo in [camera]", _set("camera.exposure", 0.02), "camera.exposure"),
    ("a string for a number", _set("camera.width_px", "112"), "camera.width_px"),
    ("white level below black", _set("camera.white_level_dn", 100), "camera.white_level_dn"),
    ("a string for a boolean", _set("total_station.crc", "yes"), "total_station.crc"),
    ("typo in [total_station]", _set("total_station.urll", "sim"), "total_station.urll"),
    ("typo in [[targets]]", lambda d: d["targets"][0].update(nam="x"), "targets[0].nam"),
    ("survey target misspelt", _set("object.survey_target", "object_tp"), "object.survey_target"),
    ("unknown object shape", _set("object.shape", "cube"), "object.shape"),
    ("material misspelt", _set("scene.material", "marbel"), "scene.material"),
    ("a 2-vector", _set("scene.sigma_a_per_mm", [0.1, 0.1]), "scene.sigma_a_per_mm"),
    ("unknown single-image method", _set("estimation.single_image_method", "bogus"),
     "estimation.single_image_method"),
    ("zero key-light direction", _set("estimation.key_light_direction", [0.0, 0.0, 0.0]),
     "estimation.key_light_direction"),
    ("unknown profile model", _set("estimation.single_image_model", "diffusion"), "estimation.single_image_model"),
    ("typo in [calibration.board]", _set("calibration.board.view", 8), "calibration.board.view"),
    ("typo in a [calibration] section name", _set("calibration.boards", {"views": 8}), "calibration.boards"),
    ("unknown LED-survey fit", _set("calibration.led_survey.fit", "affine"), "calibration.led_survey.fit"),
    ("too few pose targets", _set("calibration.pose_targets.count", 2), "calibration.pose_targets.count"),
    ("energy budget: a pattern over the current limit", _set("sphere.max_total_current_a", 5.0),
     "sphere.max_total_current_a"),
    ("thermal budget: over-temperature predicted", _set("sphere.over_temperature_c", 30.0),
     "sphere.over_temperature_c"),
    ("watchdog shorter than the key exposure", _set("sphere.watchdog_s", 1.0), "sphere.watchdog_s"),
    ("unknown runner action", _set("runner.on_led_fault", "ignore"), "runner.on_led_fault"),
    ("section name misspelt", lambda d: d.update(sphre=d["sphere"]), "sphre"),
    ("missing required key", _del("sphere.url"), "sphere.url"),
]


def _toml(d: dict) -> str:
    """A small TOML writer for the config's shapes (tables, arrays of tables, scalars, lists)."""
    def val(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, list):
            return "[" + ", ".join(val(x) for x in v) + "]"
        return repr(v)

    lines: list[str] = []

    def table(prefix: str, t: dict) -> None:
        scalars = {k: v for k, v in t.items() if not isinstance(v, dict) and not (isinstance(v, list) and v
                                                                                   and isinstance(v[0], dict))}
        if prefix:
            lines.append(f"[{prefix}]")
        lines.extend(f"{k} = {val(v)}" for k, v in scalars.items())
        for k, v in t.items():
            if isinstance(v, dict):
                table(f"{prefix}.{k}" if prefix else k, v)
            elif isinstance(v, list) and v and isinstance(v[0], dict):
                for item in v:
                    lines.append(f"[[{prefix + '.' if prefix else ''}{k}]]")
                    lines.extend(f"{a} = {val(b)}" for a, b in item.items())
    table("", d)
    return "\n".join(lines) + "\n"


def rig(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), *sys.path]))
    return subprocess.run([sys.executable, "-m", "rig.cli", *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=300)


def bad_inputs(work: Path) -> list[tuple[str, list[str]]]:
    (work / "bad.json").write_text("{not json")
    (work / "cal.json").write_text(json.dumps({"format": "sssrig-calibration", "schema_version": 1, "rig": "x",
                                               "revision": 1, "updated": "now", "steps": {"intrinsicz": {}}}))
    (work / "scene.toml").write_text("[scene]\nfoo = 1\n")
    (work / "empty").mkdir(exist_ok=True)
    sess = work / "sessions" / "broken"
    sess.mkdir(parents=True, exist_ok=True)
    (sess / "manifest.json").write_text("{\"format\": 1")
    (sess / "events.jsonl").write_text("")
    (work / "syntax.toml").write_text("[sphere\nradius_mm = 1\n")
    return [
        ("config syntax error", ["config", "--check", "syntax.toml"]),
        ("missing config", ["config", "--check", "nope.toml"]),
        ("capture with a broken config", ["capture", "--sim", "--config", "broken-0.toml", "--sessions", "s"]),
        ("calibrate with a broken config", ["calibrate", "intrinsics", "--sim", "--config", "broken-21.toml"]),
        ("capture with a broken calibration file", ["capture", "--sim", "--calibration", "bad.json", "--sessions", "s"]),
        ("capture with a calibration of an unknown step", ["capture", "--sim", "--calibration", "cal.json",
                                                          "--sessions", "s"]),
        ("estimate a missing session", ["estimate", "session", "nope"]),
        ("estimate a broken session", ["estimate", "session", str(sess)]),
        ("resume a broken session", ["resume", str(sess)]),
        ("report a missing session", ["report", "nope"]),
        ("scene file with an unknown key", ["estimate", "single-image", "scene.toml"]),
        ("missing scene file", ["estimate", "single-image", "nope.toml"]),
        ("capture folder without capture.toml", ["estimate", "gradients", "empty"]),
        ("bad channels", ["plan", "--channels", "XY"]),
        ("roi with three numbers", ["plan", "--roi", "1", "2", "3"]),
        ("roi outside the frame", ["capture", "--sim", "--roi", "0", "0", "500", "500", "--sessions", "s"]),
        ("bad session name", ["capture", "--sim", "--name", "../evil", "--sessions", "s"]),
        ("unknown fault", ["sim", "--fault", "sphere:nope", "--seconds", "0.1"]),
        ("unknown command option", ["demo", "--bogus"]),
        ("bad log level", ["--log-level", "LOUD", "plan"]),
    ]


def main() -> int:
    base = tomllib.loads(default_config_text())
    refused, named, tracebacks, results = 0, 0, 0, []
    with tempfile.TemporaryDirectory(prefix="sssrig-probe-") as tmp:
        work = Path(tmp)
        for i, (what, mutate, field) in enumerate(BROKEN):
            d = json.loads(json.dumps(base))
            mutate(d)
            f = work / f"broken-{i}.toml"
            f.write_text(_toml(d))
            res = rig("config", "--check", f.name, cwd=work)
            err = res.stderr.strip().splitlines()
            line = next((x for x in err if "error" in x), "")
            ok_refused = res.returncode == 2
            ok_named = f.name in line and f"field '{field}'" in line
            tb = "Traceback" in res.stderr
            refused += ok_refused
            named += ok_refused and ok_named
            tracebacks += tb
            results.append({"case": what, "refused": ok_refused, "file_and_field": ok_named, "traceback": tb,
                            "error": line})
        n_inputs = 0
        for what, args in bad_inputs(work):
            res = rig(*args, cwd=work)
            tb = "Traceback" in res.stderr or "Traceback" in res.stdout
            tracebacks += tb
            n_inputs += 1
            last = (res.stderr.strip().splitlines() or [""])[-1]
            results.append({"case": what, "exit": res.returncode, "traceback": tb, "error": last})
    for r in results:
        print(json.dumps(r), file=sys.stderr)
    print(json.dumps({"broken_configs": len(BROKEN), "refused": refused, "refused_naming_file_and_field": named,
                      "bad_inputs": n_inputs, "tracebacks": tracebacks}))
    return 0 if named == len(BROKEN) and tracebacks == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
