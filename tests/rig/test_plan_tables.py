"""Plan tables: (scene, request) -> expected steps; the dry-run budget; `rig plan` and config errors."""
import json
import tomllib

import numpy as np
import pytest

from drivers.errors import ConfigError, LimitError
from rig.cli import main
from rig.config import default_config_text, parse_config
from rig.acquire.geometry import rig_geometry
from rig.acquire.plan import CaptureRequest, Step, budget, build_plan, omissions, steps_from_dicts, summarize


def _config(**sections):
    data = tomllib.loads(default_config_text())
    for section, fields in sections.items():
        data[section].update(fields)
    return parse_config(data, "test.toml")


MESH = {"shape": "mesh", "mesh_path": "scan.ply"}
GRAD = ["ambient/cross", "full/cross", "x/cross", "y/cross", "z/cross"]


@pytest.mark.parametrize("estimate, complements, obj, frames, surveys", [
    (("gradients",), False, {}, GRAD, ["object_top"]),
    (("gradients",), True, {}, ["ambient/cross", "x/cross", "y/cross", "z/cross", "x_c/cross", "y_c/cross",
                                "z_c/cross"], ["object_top"]),
    (("gradients", "specular"), False, {},
     GRAD + ["ambient/parallel", "full/parallel", "x/parallel", "y/parallel", "z/parallel"], ["object_top"]),
    # specular alone still needs the cross-polarized gradients (specular = parallel - cross)
    (("specular",), False, {}, GRAD + ["ambient/parallel", "full/parallel", "x/parallel", "y/parallel",
                                       "z/parallel"], ["object_top"]),
    (("single-image",), False, {}, ["ambient/cross", "key/cross"], ["object_top", "key_led"]),
    (("gradients", "single-image"), False, {}, GRAD + ["key/cross"], ["object_top", "key_led"]),
    # geometry given as a mesh in rig coordinates: no survey of the object
    (("gradients",), False, MESH, GRAD, []),
    (("single-image",), False, MESH, ["ambient/cross", "key/cross"], ["key_led"]),
])
def test_plan_table(estimate, complements, obj, frames, surveys):
    cfg = _config(object=obj) if obj else _config()
    steps = build_plan(cfg, rig_geometry(cfg).led_directions, request=CaptureRequest(estimate, complements=complements))
    assert [s.frame for s in steps if s.kind == "fetch"] == frames
    assert [s.params["target"] for s in steps if s.kind == "survey"] == surveys
    assert all(s.reason for s in steps)
    assert [s.index for s in steps] == list(range(len(steps)))
    assert steps[-1].kind == "all_off"
    # one upload per distinct lit pattern, in distinct slots
    lit = list(dict.fromkeys(f.split("/")[0] for f in frames if not f.startswith("ambient")))
    ups = [s for s in steps if s.kind == "upload"]
    assert [s.params["pattern"] for s in ups] == lit
    assert sorted(s.params["slot"] for s in ups) == list(range(len(lit)))


def test_frame_groups_and_serves_links():
    cfg = _config(sphere={"settle_s": 0.2})
    steps = build_plan(cfg, rig_geometry(cfg).led_directions,
                       request=CaptureRequest(("gradients", "single-image", "specular")))
    by_index = {s.index: s for s in steps}
    for f in (s for s in steps if s.kind == "fetch"):
        group = [s for s in steps if s.frame == f.frame]
        assert [s.kind for s in group] == ["select", "settle", "trigger", "fetch"]
        assert all(s.serves == (f.index,) for s in group)
        assert by_index[f.index + 1].kind == "checkpoint"
        assert group[2].params["exposure_s"] == f.params["exposure_s"]
        sel = group[0]
        assert (sel.params["slot"] is None) == (f.params["pattern"] == "ambient")
    fetch_of = {s.index: s for s in steps if s.kind == "fetch"}
    for u in (s for s in steps if s.kind == "upload"):
        assert sorted(fetch_of[i].params["pattern"] for i in u.serves) == \
            sorted(s.params["pattern"] for s in fetch_of.values() if s.params["pattern"] == u.params["pattern"])
        assert u.index < min(u.serves)
    for p in (s for s in steps if s.kind == "polarization"):
        assert {fetch_of[i].params["polarization"] for i in p.serves} == {p.params["state"]}
    for s in steps:
        assert s.timeout_s > 0 or s.kind == "checkpoint"
    # the plan is data: it round-trips through the manifest's JSON
    assert steps_from_dicts(json.loads(json.dumps([s.to_dict() for s in steps]))) == steps
    with pytest.raises(ValueError, match="unknown kind"):
        Step.from_dict({"index": 0, "kind": "capture"})


def test_channels_not_requested_stay_dark():
    cfg = _config()
    dirs = rig_geometry(cfg).led_directions
    rgb = build_plan(cfg, dirs, estimate=("gradients",))
    g = build_plan(cfg, dirs, estimate=("gradients",), channels="g")
    up_rgb = {s.params["pattern"]: s.params for s in rgb if s.kind == "upload"}
    up_g = {s.params["pattern"]: s.params for s in g if s.kind == "upload"}
    assert all(p["channels"] == "G" for p in up_g.values())
    for name in up_rgb:
        assert up_g[name]["current_a"] == pytest.approx(up_rgb[name]["current_a"] / 3, rel=1e-3)
    assert budget(g, cfg)["led_energy_j"] == pytest.approx(budget(rgb, cfg)["led_energy_j"] / 3, rel=1e-3)
    assert any("R, B not requested" in n for n in omissions(cfg, CaptureRequest(("gradients",), "G")))


def test_request_validation_and_slot_limit():
    cfg = _config()
    dirs = rig_geometry(cfg).led_directions
    with pytest.raises(ValueError, match="unknown estimator"):
        build_plan(cfg, dirs, estimate=("tarot",))
    with pytest.raises(ValueError, match="subset of R, G, B"):
        CaptureRequest(("gradients",), "RX")
    small = _config(sphere={"slots": 3})
    with pytest.raises(LimitError, match="needs 4 pattern slots"):
        build_plan(small, rig_geometry(small).led_directions, estimate=("gradients",))


def test_budget_duration_energy_and_thermal():
    cfg = _config()
    steps = build_plan(cfg, rig_geometry(cfg).led_directions)
    b = budget(steps, cfg)
    assert b["frames"] == 6 and b["problems"] == []
    assert b["duration_s"] == pytest.approx(sum(s.nominal_s for s in steps), abs=1e-3)
    # energy = V x I x lit time, summed over the lit frames (select -> next select)
    assert b["led_energy_j"] > 0 and b["max_current_a"] <= cfg.sphere.max_total_current_a
    assert cfg.sphere.ambient_c < b["peak_temperature_c"] < cfg.sphere.over_temperature_c
    hot = _config(sphere={"thermal_c_per_a": 200.0, "thermal_tau_s": 1.0})
    hb = budget(build_plan(hot, rig_geometry(hot).led_directions), hot)
    assert hb["peak_temperature_c"] >= hot.sphere.over_temperature_c
    assert any("interlock" in p for p in hb["problems"])
    dog = _config(sphere={"watchdog_s": 1.0})       # key exposure 1.5 s: the watchdog would cut it
    assert any("watchdog_s" in p for p in budget(build_plan(dog, rig_geometry(dog).led_directions), dog)["problems"])


def test_dry_run_text_names_frames_devices_budget_and_reasons():
    cfg = _config(object=MESH)
    req = CaptureRequest(("gradients",))
    text = summarize(build_plan(cfg, rig_geometry(cfg).led_directions, request=req), cfg, req)
    for needle in ("devices used:", "sphere", "trigger", "camera", "estimated duration:", "LED energy:",
                   "thermal budget:", "left out: no survey of the object", "left out: no parallel-polarized",
                   "frames: ambient/cross, full/cross"):
        assert needle in text, needle
    assert "total_station" not in text       # nothing to survey: the total station is not used


def test_rig_plan_json(capsys):
    assert main(["plan", "--estimate", "gradients", "specular", "--channels", "RG", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["request"] == {"estimate": ["gradients", "specular"], "channels": "RG", "complements": False,
                              "roi_px": None}
    assert out["budget"]["frames"] == 10 and set(out["devices"]) == {"sphere", "trigger", "camera",
                                                                      "total_station"}
    assert all(s["reason"] for s in out["steps"])


@pytest.mark.parametrize("cmd", [["plan"], ["capture", "--sim"], ["devices"]])
def test_bad_config_names_file_field_and_expectation(tmp_path, capsys, cmd):
    bad = tmp_path / "bad.toml"
    bad.write_text(default_config_text().replace('shape = "sphere"             # "sphere" (radius_mm)',
                                                 'shape = "cube"             # "sphere" (radius_mm)'))
    assert main([*cmd, "--config", str(bad), *(["--sessions", str(tmp_path)] if "capture" in cmd else [])]) == 2
    err = capsys.readouterr().err
    assert f"{bad}: field 'object.shape': expected one of sphere, mesh, got 'cube'" in err
    assert not any(tmp_path.glob("capture-*"))     # nothing was created


def test_mesh_object_needs_its_path():
    data = tomllib.loads(default_config_text())
    data["object"].update(shape="mesh")
    with pytest.raises(ConfigError, match="object.mesh_path"):
        parse_config(data, "m.toml")
    assert np.isfinite(_config(object=MESH).object.mesh_units_mm)
