"""The calibration file: round trip, revisions and history, validation with errors naming file and field, and
what the estimators consume."""
from __future__ import annotations

import json

import numpy as np
import pytest

from drivers.errors import RigError
from rig.files.calibration_store import (SCHEMA_VERSION, CalibrationError, load_calibration, read_document,
                                   write_section)

PROV = {"created": "2026-01-01T00:00:00+00:00", "session": "/s/calib-x", "software_version": "0.1.0"}
INTR = {"width_px": 40, "height_px": 30, "fx_px": 100.0, "fy_px": 101.0, "cx_px": 19.5, "cy_px": 14.5,
        "distortion": [-0.1, 0.01, 0.0, 0.0, 0.0]}


def _frame(R=None, C=(0.0, -400.0, 0.0), n=4):
    R = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]) if R is None else R
    pos = np.array([[1000.0, 0, 0], [0, 1000.0, 0], [0, 0, 1000.0], [-1000.0, 0, 0]])[:n]
    return {"camera": {"rotation": R.tolist(), "center_mm": list(C)}, "led_positions_mm": pos.tolist()}


def test_round_trip_revisions_and_history(tmp_path):
    f = tmp_path / "cal.json"
    write_section(f, "intrinsics", result=INTR, residuals={"rms_reprojection_px": 0.05}, provenance=PROV, rig_name="r")
    doc = write_section(f, "rig_frame", result=_frame(), residuals={}, provenance=PROV, rig_name="r")
    assert doc["revision"] == 2 and doc["schema_version"] == SCHEMA_VERSION
    cal = load_calibration(f)
    assert cal.section("intrinsics")["revision"] == 1 and cal.section("rig_frame")["revision"] == 2
    assert cal.result("intrinsics") == {**INTR}
    # rewriting a section bumps the revision and keeps the previous file
    write_section(f, "intrinsics", result={**INTR, "fx_px": 99.0}, residuals={}, provenance=PROV, rig_name="r")
    cal = load_calibration(f)
    assert cal.doc["revision"] == 3 and cal.result("intrinsics")["fx_px"] == 99.0
    hist = sorted((tmp_path / "cal.json.history").glob("*.json"))
    assert [h.name for h in hist] == ["r0001.json", "r0002.json"]
    assert json.loads(hist[-1].read_text())["steps"]["intrinsics"]["result"]["fx_px"] == 100.0
    assert not list(tmp_path.glob(".*tmp"))          # atomic write leaves nothing behind
    prov = cal.provenance()
    assert prov["sections"]["rig_frame"]["session"] == "/s/calib-x" and prov["revision"] == 3


def test_consumers_camera_led_rig_scale_k(tmp_path):
    f = tmp_path / "cal.json"
    for name, result in (("intrinsics", INTR), ("rig_frame", _frame()),
                         ("led_directions", {"led_indices": [1], "directions": [[0.0, 0.6, 0.8]]}),
                         ("gains", {"led_indices": [0, 2], "gains": [[1.1, 1.0, 0.9], [0.5, 0.5, 0.5]],
                                    "design_intensity": [1000.0, 1000.0, 1000.0]}),
                         ("radiometry", {"black_offset_dn": [3.0, 3.0, 3.0], "span_dn": 15871.0,
                                         "nonlinearity": [0.02, 0.02, 0.02], "albedo_scale": [2.0, 2.0, 2.0],
                                         "albedo_scale_exposure_s": 0.02}),
                         ("seed_k", {"k_mm": [0.16, 0.15, 0.13]})):
        write_section(f, name, result=result, residuals={}, provenance=PROV, rig_name="r")
    cal = load_calibration(f)
    cam = cal.camera()
    assert cam.fx_px == 100.0 and cam.center_mm == (0.0, -400.0, 0.0)
    assert np.allclose(cal.distortion(), INTR["distortion"])
    design = np.array([[990.0, 0, 0], [0, 990.0, 0], [0, 0, 990.0], [-990.0, 0, 0]])
    rig = cal.led_rig(design, (1000.0, 1000.0, 1000.0))
    assert np.allclose(rig.directions[1], [0.0, 0.6, 0.8])               # mirror-ball direction wins
    assert np.allclose(rig.distances_mm, 1000.0)                         # surveyed positions, not design
    assert np.allclose(rig.gains[0], np.array([1.1, 1.0, 0.9]) * 1000.0 / 1000.0 ** 2)
    assert np.allclose(rig.gains[3], 1000.0 / 1000.0 ** 2)               # gain 1 where not measured
    assert np.allclose(cal.albedo_scale(0.04), 1.0)
    assert np.allclose(cal.k_mm(), [0.16, 0.15, 0.13])
    lin = cal.linearizer()
    x = np.array([[[0.1, 0.5, 0.9]]])
    v = x * (1 - 0.02 * x) + 3.0 / 15871.0                               # what the sensor recorded
    assert np.allclose(lin(v), x, atol=1e-12)
    with pytest.raises(CalibrationError, match="20 LEDs"):
        cal.led_rig(np.ones((20, 3)), (1.0, 1.0, 1.0))


def test_missing_section_names_the_step(tmp_path):
    f = tmp_path / "cal.json"
    write_section(f, "intrinsics", result=INTR, residuals={}, provenance=PROV, rig_name="r")
    cal = load_calibration(f)
    with pytest.raises(CalibrationError, match=r"steps\.seed_k.*rig calibrate seed-k"):
        cal.k_mm()
    with pytest.raises(CalibrationError, match=r"steps\.rig_frame"):
        cal.camera()


@pytest.mark.parametrize("mutate, field", [
    (lambda d: d.update(format="other"), "format"),
    (lambda d: d.update(schema_version=99), "schema_version"),
    (lambda d: d["steps"].update(bogus={}), "steps.bogus"),
    (lambda d: d["steps"]["intrinsics"]["result"].update(fx_px=-3), "steps.intrinsics.result.fx_px"),
    (lambda d: d["steps"]["intrinsics"]["result"].update(distortion=[0.1, 0.2]),
     "steps.intrinsics.result.distortion"),
    (lambda d: d["steps"]["intrinsics"]["provenance"].pop("session"), "steps.intrinsics.provenance.session"),
    (lambda d: d["steps"]["rig_frame"]["result"]["camera"].update(rotation=np.diag([1.0, 1.0, -1.0]).tolist()),
     "steps.rig_frame.result.camera.rotation"),
    (lambda d: d["steps"]["rig_frame"]["result"].update(led_positions_mm=[[1, 2]]),
     "steps.rig_frame.result.led_positions_mm"),
    (lambda d: d["steps"]["rig_frame"].pop("residuals"), "steps.rig_frame.residuals"),
])
def test_bad_files_are_rejected_with_file_and_field(tmp_path, mutate, field):
    f = tmp_path / "cal.json"
    write_section(f, "intrinsics", result=INTR, residuals={}, provenance=PROV, rig_name="r")
    write_section(f, "rig_frame", result=_frame(), residuals={}, provenance=PROV, rig_name="r")
    doc = json.loads(f.read_text())
    mutate(doc)
    f.write_text(json.dumps(doc))
    with pytest.raises(CalibrationError) as ei:
        load_calibration(f)
    assert ei.value.field == field
    assert str(f) in str(ei.value) and f"'{field}'" in str(ei.value)
    assert isinstance(ei.value, RigError)          # `rig` reports it as an error, not a traceback


def test_unreadable_and_foreign_files(tmp_path):
    f = tmp_path / "cal.json"
    with pytest.raises(CalibrationError, match="run `rig calibrate"):
        read_document(f)
    f.write_text("{not json")
    with pytest.raises(CalibrationError, match="<syntax>"):
        read_document(f)
    f.unlink()
    write_section(f, "intrinsics", result=INTR, residuals={}, provenance=PROV, rig_name="rig-a")
    with pytest.raises(CalibrationError, match="rig-a"):
        write_section(f, "intrinsics", result=INTR, residuals={}, provenance=PROV, rig_name="rig-b")


def test_invalid_section_is_not_written(tmp_path):
    f = tmp_path / "cal.json"
    write_section(f, "intrinsics", result=INTR, residuals={}, provenance=PROV, rig_name="r")
    before = f.read_bytes()
    with pytest.raises(CalibrationError, match=r"steps\.gains\.result\.gains"):
        write_section(f, "gains", result={"led_indices": [0, 1], "gains": [[1.0, 1.0, 1.0]],
                                          "design_intensity": [1.0, 1.0, 1.0]}, residuals={}, provenance=PROV,
                      rig_name="r")
    assert f.read_bytes() == before
    with pytest.raises(ValueError, match="unknown calibration section"):
        write_section(f, "focus", result={}, residuals={}, provenance=PROV, rig_name="r")
