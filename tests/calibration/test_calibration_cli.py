"""``rig calibrate`` (rig.calibration.cli) and single steps run on their own."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from rig.calibration.cli import STEP_HELP, add_parser
from rig.calibration.run import CalibrationFailed, make_world, run_step
from rig.files.calibration_store import load_calibration, write_section
from rig.acquire.capture import simulated

RIG_TOML = Path(__file__).with_name("calibration_rig.toml")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="rig")
    add_parser(p.add_subparsers(dest="command", required=True))
    return p


def test_parser_has_every_step():
    p = _parser()
    for step in STEP_HELP:
        args = p.parse_args(["calibrate", step, "--sim", "--json", "--out", "x.json"])
        assert args.step == step and args.sim and args.json and str(args.out) == "x.json" and callable(args.func)
    with pytest.raises(SystemExit):
        p.parse_args(["calibrate", "focus"])


def test_cli_extinction_json(tmp_path, capsys):
    out = tmp_path / "cal.json"
    args = _parser().parse_args(["calibrate", "extinction", "--sim", "--json", "--config", str(RIG_TOML),
                                 "--out", str(out)])
    assert args.func(args) == 0
    doc = json.loads(capsys.readouterr().out)
    step = doc["steps"][0]
    assert step["step"] == "extinction" and step["revision"] == 1
    assert abs(step["truth_comparison"]["ratio_rel_error"]) < 0.05
    assert load_calibration(out).result("extinction")["passed"] is True
    assert (tmp_path / "calibration-sessions").is_dir()
    # run alone: its predecessors are missing, so it says it used design values (issue 18: it was silent)
    (warning,) = step["warnings"]
    assert "intrinsics, rig-frame, radiometry, led-directions, gains" in warning and "design values" in warning
    prov = load_calibration(out).section("extinction")["provenance"]
    assert prov["inputs"]["missing_predecessors"] == ["intrinsics", "rig-frame", "radiometry", "led-directions",
                                                      "gains"]


def test_a_step_without_its_predecessors_can_be_refused(tmp_path, cal_config):
    out = tmp_path / "cal.json"
    with pytest.raises(CalibrationFailed, match="has no intrinsics, rig-frame.*section"):
        run_step("seed-k", cal_config, out=out, simulate=True, require_predecessors=True)
    assert not out.exists() and not (tmp_path / "calibration-sessions").exists()    # nothing was captured


def test_the_chain_in_order_warns_about_nothing(chain):
    assert all(not r.warnings for r in chain["reports"].values())


def test_cli_rig_frame_with_true_intrinsics_meets_0_1_deg(tmp_path, capsys, cal_config, cal_settings):
    """With the lens known exactly, the rig-frame step alone puts the camera within 1 mm and 0.1 degree (in the
    chain the intrinsics' principal-point uncertainty adds to the bare rotation; see test_calibration_chain)."""
    out = tmp_path / "cal.json"
    world = make_world(simulated(cal_config), cal_settings)
    t = world.truth.camera
    p = t.pinhole
    write_section(out, "intrinsics", result={"width_px": p.width_px, "height_px": p.height_px, "fx_px": p.fx_px,
                                             "fy_px": p.fy_px, "cx_px": p.cx_px, "cy_px": p.cy_px,
                                             "distortion": list(t.distortion)},
                  residuals={}, provenance={"created": "now", "session": "oracle", "software_version": "test"},
                  rig_name=cal_config.name)
    args = _parser().parse_args(["calibrate", "rig-frame", "--sim", "--config", str(RIG_TOML), "--out", str(out)])
    assert args.func(args) == 0
    text = capsys.readouterr().out
    assert "rig-frame: revision 2" in text and "vs simulator truth" in text
    cal = load_calibration(out)
    cam = cal.camera()
    assert np.linalg.norm(cam.C - p.C) < 1.0
    M = cam.R @ p.R.T
    assert np.degrees(np.arccos(np.clip((np.trace(M) - 1) / 2, -1, 1))) < 0.1
    assert cal.section("rig_frame")["provenance"]["inputs"]["intrinsics"].startswith("calibrated")


def test_failed_step_names_its_session(tmp_path, cal_config, cal_settings):
    settings = cal_settings.with_(board={"views": 3})
    world = make_world(simulated(cal_config), settings)
    with pytest.raises(CalibrationFailed,
                       match=r"calibrate intrinsics: the board was found in 0 of 3 views.*frames kept in .*calib-"):
        run_step("intrinsics", cal_config, out=tmp_path / "cal.json", settings=settings, simulate=True, world=world,
                 operator=lambda op: world.operate({"target": "dark"}))      # the operator forgot the board
    assert not (tmp_path / "cal.json").exists()
