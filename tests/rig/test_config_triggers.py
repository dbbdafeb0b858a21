"""[trigger] driver choices (esper, hid, serial-release) and [camera] driver gphoto2: parsing, errors naming
the field, the factory building the right driver, and a small simulated capture through each new trigger
(the HID box's fake at the HidTransport seam, the serial release on pyserial loop://) firing the camera."""
from __future__ import annotations

import dataclasses
import re
import tomllib
from pathlib import Path

import pytest

from drivers.contracts import Trigger
from drivers.errors import ConfigError, ConnectionLost
from drivers.trigger.hid_box import HidTrigger
from drivers.trigger.serial_release import SerialRelease
from rig.config import TRIGGER_KEYS, TriggerConfig, default_config_text, parse_config
from rig.acquire.factory import open_camera, open_devices, open_trigger, start_simulators
from rig.acquire.geometry import geometry_to_dict, rig_geometry
from rig.acquire.plan import build_plan
from rig.acquire.runner import run_plan
from rig.files.session import Session

ROOT = Path(__file__).resolve().parents[2]

try:
    import gphoto2  # noqa: F401
    HAVE_GPHOTO2 = True
except ImportError:
    HAVE_GPHOTO2 = False


def _small_text() -> str:
    text = default_config_text()
    for old, new in (("width_px = 112", "width_px = 64"), ("height_px = 112", "height_px = 64"),
                     ("fx_px = 1700.0", "fx_px = 1000.0"), ("geodesic_frequency = 6", "geodesic_frequency = 5")):
        assert old in text
        text = text.replace(old, new)
    return text


def _with(trigger: dict | None = None, camera: dict | None = None) -> dict:
    data = tomllib.loads(_small_text())
    if trigger is not None:
        data["trigger"] = trigger
    if camera is not None:
        data["camera"].update(camera)
    return data


# ----------------------------------------------------------------------------------------------- parsing
def test_esper_stays_the_default_with_documented_defaults():
    t = parse_config(_with()).trigger
    assert t == TriggerConfig(driver="esper", url="sim")
    assert (t.timeout_s, t.min_exposure_s, t.max_exposure_s, t.outputs_mask) == (1.0, 0.001, 60.0, 0x3F)


@pytest.mark.parametrize("trigger, expected", [
    ({"driver": "esper", "url": "/dev/ttyUSB0", "outputs_mask": 0x05, "timeout_s": 2.5},
     dict(url="/dev/ttyUSB0", outputs_mask=5, timeout_s=2.5)),
    ({"driver": "hid", "vendor_id": 0x16C0, "product_id": 0x05DF, "serial": "TB-7", "outputs_mask": 1},
     dict(url="", vendor_id=0x16C0, product_id=0x05DF, serial="TB-7", outputs_mask=1)),
    ({"driver": "hid", "path": "/dev/hidraw3"}, dict(path="/dev/hidraw3", vendor_id=0, product_id=0)),
    ({"driver": "hid", "url": "sim"}, dict(url="sim")),
    ({"driver": "serial-release", "url": "/dev/ttyUSB1", "focus_lead_s": 0.25, "max_exposure_s": 30.0},
     dict(url="/dev/ttyUSB1", focus_lead_s=0.25, max_exposure_s=30.0)),
    ({"driver": "serial-release", "url": "loop://", "focus_lead_s": 0}, dict(url="loop://", focus_lead_s=0.0)),
])
def test_each_trigger_driver_parses(trigger, expected):
    t = parse_config(_with(trigger)).trigger
    assert t.driver == trigger["driver"]
    assert {k: getattr(t, k) for k in expected} == expected


@pytest.mark.parametrize("trigger, field, expected", [
    ({"driver": "usb-box", "url": "sim"}, "trigger.driver", "one of esper, hid, serial-release"),
    ({"driver": "hid"}, "trigger.vendor_id", "the box's USB vendor id"),
    ({"driver": "hid", "vendor_id": 0x16C0}, "trigger.product_id", "the box's USB product id"),
    ({"driver": "hid", "vendor_id": 0x10000, "product_id": 1}, "trigger.vendor_id", "an integer in [0, 65535]"),
    ({"driver": "hid", "vendor_id": "16c0", "product_id": 1}, "trigger.vendor_id", "an integer"),
    ({"driver": "hid", "url": "/dev/hidraw0"}, "trigger.url", '"sim" or no url'),
    ({"driver": "hid", "url": "sim", "outputs_mask": 64}, "trigger.outputs_mask", "an integer in [1, 63]"),
    ({"driver": "hid", "url": "sim", "outputs_mask": 0}, "trigger.outputs_mask", "an integer in [1, 63]"),
    ({"driver": "hid", "url": "sim", "serial": 42}, "trigger.serial", "a string"),
    ({"driver": "hid", "url": "sim", "focus_lead_s": 0.1}, "trigger.focus_lead_s",
     "a key of [trigger] for driver 'hid'"),
    ({"driver": "serial-release"}, "trigger.url", "a value (field is missing)"),
    ({"driver": "serial-release", "url": "loop://", "focus_lead_s": -0.1}, "trigger.focus_lead_s",
     "a number >= 0.0"),
    ({"driver": "serial-release", "url": "loop://", "vendor_id": 1}, "trigger.vendor_id",
     "a key of [trigger] for driver 'serial-release'"),
    ({"driver": "serial-release", "url": "loop://", "timeout_s": 1.0}, "trigger.timeout_s",
     "a key of [trigger] for driver 'serial-release'"),
    ({"driver": "esper", "url": "sim", "min_exposure_s": 0.5, "max_exposure_s": 0.1}, "trigger.max_exposure_s",
     "a number >= trigger.min_exposure_s"),
    ({"driver": "esper", "url": "sim", "min_exposure_s": 0}, "trigger.min_exposure_s", "a number > 0"),
    ({"driver": "esper", "url": "sim", "timeout_s": "1"}, "trigger.timeout_s", "a number"),
    ({"driver": "esper", "url": "sim", "vendorid": 1}, "trigger.vendorid", "a key of [trigger] for driver"),
])
def test_bad_trigger_values_name_the_field(trigger, field, expected):
    with pytest.raises(ConfigError) as err:
        parse_config(_with(trigger), "rig.toml")
    assert err.value.field == field
    assert str(err.value).startswith(f"rig.toml: field '{field}'") and expected in str(err.value)


def test_gphoto2_camera_parses_with_driver_defaults():
    cam = parse_config(_with(camera={"driver": "gphoto2", "folder": "/data/frames", "port": "usb:001,004",
                                     "model": "Nikon DSC D750"})).camera
    assert (cam.driver, cam.folder, cam.port, cam.model) == ("gphoto2", "/data/frames", "usb:001,004",
                                                              "Nikon DSC D750")
    assert (cam.capture_mode, cam.pattern, cam.delete_after_download) == ("external", "*", False)
    cam = parse_config(_with(camera={"driver": "gphoto2", "folder": "dl", "capture_mode": "capture",
                                     "pattern": "*.nef", "delete_after_download": True})).camera
    assert (cam.capture_mode, cam.pattern, cam.delete_after_download, cam.port) == ("capture", "*.nef", True, "")
    assert parse_config(_with()).camera.pattern == "*.dng"          # driver "folder" keeps its default


@pytest.mark.parametrize("camera, field, expected", [
    ({"driver": "webcam"}, "camera.driver", "one of folder, gphoto2"),
    ({"driver": "gphoto2", "folder": "sim"}, "camera.folder", "the folder gphoto2 downloads frames into"),
    ({"driver": "gphoto2", "folder": "dl", "port": "sim"}, "camera.port", "there is no simulated gphoto2"),
    ({"driver": "gphoto2", "folder": "dl", "capture_mode": "sometimes"}, "camera.capture_mode",
     "one of external, capture"),
    ({"driver": "gphoto2", "folder": "dl", "delete_after_download": "yes"}, "camera.delete_after_download",
     "true or false"),
    ({"port": "usb:001,002"}, "camera.port", "a key of [camera] for driver 'folder' (it is a key of driver 'gphoto2')"),
])
def test_bad_camera_driver_values_name_the_field(camera, field, expected):
    with pytest.raises(ConfigError) as err:
        parse_config(_with(camera=camera), "rig.toml")
    assert err.value.field == field and expected in str(err.value)


def test_every_trigger_key_is_documented():
    toml_text = default_config_text()
    doc = (ROOT / "docs" / "protocols" / "trigger-boxes.md").read_text()
    for driver, keys in TRIGGER_KEYS.items():
        assert f'"{driver}"' in toml_text and f"`{driver}`" in doc, driver
        for key in keys:
            assert re.search(rf"\b{key}\b", toml_text), f"{key} not in rig/data/default_rig.toml"
            assert f"`{key}`" in doc, f"{key} not in docs/protocols/trigger-boxes.md"
    for key in ("port", "model", "capture_mode", "pattern", "delete_after_download"):
        assert re.search(rf"\b{key}\b", toml_text), key


# ---------------------------------------------------------------------------------------------- factory
def test_factory_opens_real_transports_for_non_simulated_triggers():
    release = open_trigger(TriggerConfig(driver="serial-release", url="loop://", focus_lead_s=0.0))
    try:
        assert isinstance(release, SerialRelease) and isinstance(release, Trigger)
        release.fire(0.002)
        assert not release.port.cts and not release.port.dsr       # both lines released afterwards
    finally:
        release.close()
    # hidapi is real here; no box with this id is plugged in
    with pytest.raises(ConnectionLost, match="cannot open HID device 16c0:05df"):
        open_trigger(TriggerConfig(driver="hid", vendor_id=0x16C0, product_id=0x05DF))
    with pytest.raises(ValueError, match="needs the simulated rig"):
        open_trigger(TriggerConfig(driver="hid", url="sim"))


@pytest.mark.skipif(not HAVE_GPHOTO2, reason="python-gphoto2 is not installed (pip install 'sssrig[gphoto]')")
def test_factory_opens_a_gphoto2_camera(tmp_path):
    card = tmp_path / "card"
    card.mkdir()
    cfg = parse_config(_with(camera={"driver": "gphoto2", "folder": str(tmp_path / "dl"),
                                     "port": f"disk:{card}", "model": "Directory Browse"}))
    camera = open_camera(cfg.camera)
    try:
        ident = camera.identify()
        assert ident.model == "Directory Browse" and ident.extra["port"] == f"disk:{card}"
        assert camera.download_dir == tmp_path / "dl" and camera.pattern == "*"
    finally:
        camera.close()


# ------------------------------------------------------------------------------------ simulated capture
@pytest.mark.parametrize("driver, driver_cls", [("hid", HidTrigger), ("serial-release", SerialRelease)])
def test_small_simulated_capture_fires_the_camera(tmp_path, driver, driver_cls):
    trigger = {"driver": driver, "url": "sim"}
    if driver == "serial-release":
        trigger["focus_lead_s"] = 0.02
    cfg = parse_config(_with(trigger), "small.toml")
    geo = rig_geometry(cfg)
    sim = start_simulators(cfg, geo, tmp_path / "sim")
    try:
        devices = open_devices(cfg, geo, sim)
        try:
            assert isinstance(devices.trigger, driver_cls)
            steps = build_plan(cfg, geo.led_directions)
            session = Session.create(tmp_path / "sessions", f"t-{driver}", config=cfg.to_dict(),
                                     devices={"trigger": dataclasses.asdict(devices.trigger.identify())},
                                     plan=[s.to_dict() for s in steps], geometry=geometry_to_dict(geo))
            run_plan(steps, devices, session, led_directions=geo.led_directions,
                     pattern_peak=cfg.sphere.pattern_peak, settle_s=cfg.sphere.settle_s,
                     fetch_timeout_s=cfg.camera.fetch_timeout_s)
        finally:
            devices.close()
        fired = sim.transports["trigger"].fired
        # one shot per "capture" step (or per "trigger" step where the plan splits trigger and fetch)
        shots_s = [s.params["exposure_s"] for s in steps if s.kind in ("capture", "trigger")]
    finally:
        sim.close()
    frames = session.frames()
    assert len(shots_s) >= 2 and len(frames) == len(shots_s) == len(fired)
    assert [f.exposure_s for f in frames] == shots_s
    assert session.verify() == []
    if driver == "hid":
        # the box times the exposure: the camera saw exactly the bulb times asked for (whole ms), in order
        assert fired == [round(x * 1000) / 1000 for x in shots_s]
    else:
        # the host times DTR: never shorter than asked, late by at most a scheduler hiccup
        assert all(x <= f < x + 0.010 for f, x in zip(fired, shots_s)), (fired, shots_s)
        assert all(sim.transports["trigger"].focused)             # focus (RTS) came before every shutter


@pytest.mark.parametrize("driver", ["hid", "serial-release"])
def test_simulated_trigger_can_be_closed_and_reopened(tmp_path, driver):
    """The runner may reopen devices after a fault: the simulated transport must come back, lines low."""
    trigger = {"driver": driver, "url": "sim"}
    if driver == "serial-release":
        trigger["focus_lead_s"] = 0.0
    cfg = parse_config(_with(trigger))
    sim = start_simulators(cfg, rig_geometry(cfg), tmp_path / "sim")
    try:
        first = open_trigger(cfg.trigger, sim)
        first.fire(0.005)
        first.close()
        with pytest.raises(ConnectionLost):
            first.fire(0.005)                       # a closed driver refuses
        second = open_trigger(cfg.trigger, sim)
        try:
            second.fire(0.007)
        finally:
            second.close()
        fired = sim.transports["trigger"].fired
    finally:
        sim.close()
    assert len(fired) == 2 and 0.005 <= fired[0] < 0.015 and 0.007 <= fired[1] < 0.017
