"""The device contract exercised on whatever the rig config names (hardware, or the simulators)."""
from __future__ import annotations

import numpy as np
import pytest

from drivers.contracts import Camera, LightSource, Polarization, PositionFeed, Trigger
from drivers.errors import LimitError
from rig.acquire.patterns import pattern_rgb16


def test_every_device_satisfies_its_contract_and_identifies(rig):
    _, _, d = rig
    assert isinstance(d.light, LightSource) and isinstance(d.trigger, Trigger)
    assert isinstance(d.camera, Camera) and isinstance(d.feed, PositionFeed)
    for dev in (d.light, d.trigger, d.camera, d.feed):
        ident = dev.identify()
        assert ident.model, f"{type(dev).__name__} reported an empty model"


def test_sphere_led_count_matches_the_config_layout(rig):
    _, geo, d = rig
    d.light.identify()
    assert d.light.led_count == len(geo.led_positions_mm)


def test_pattern_upload_select_status_and_all_off(rig):
    cfg, geo, d = rig
    pattern = pattern_rgb16("z", geo.led_directions, peak=min(0.1, cfg.sphere.pattern_peak))
    d.light.upload_pattern(0, pattern)
    d.light.set_polarization(Polarization.CROSS)
    d.light.select_slot(0)
    st = d.light.status()
    assert st.lit and st.active_slot == 0 and st.polarization == Polarization.CROSS
    d.light.all_off()
    d.light.all_off()                      # idempotent
    assert not d.light.status().lit


def test_over_limit_pattern_is_refused_before_sending(rig):
    _, geo, d = rig
    full = np.full((len(geo.led_positions_mm), 3), 65535, np.uint16)
    with pytest.raises(LimitError):
        d.light.upload_pattern(1, full)


def test_trigger_and_camera_deliver_a_frame(rig):
    cfg, _, d = rig
    d.light.all_off()
    d.camera.arm()
    d.trigger.fire(0.005)
    frame = d.camera.fetch(cfg.camera.fetch_timeout_s)
    assert frame.rgb.ndim == 3 and frame.rgb.shape[2] == 3
    assert np.isfinite(frame.rgb).all()


def test_total_station_measures_the_object_target(rig):
    cfg, geo, d = rig
    target = cfg.object.survey_target
    pt = d.feed.measure(target)
    # the surveyed point must be near where the config expects it (a few mm: survey vs design)
    assert np.linalg.norm(np.subtract(pt.xyz_mm, geo.targets[target])) < 5.0
