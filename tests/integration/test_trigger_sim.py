"""The ESPER driver against its simulator over a real pty and loopback TCP (with faults), the sans-IO model,
the command-line entry point, and the trigger -> simulated camera -> FolderCamera chain."""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from drivers.camera import FolderCamera
from drivers.errors import ConnectionLost, DeviceBusy, DeviceRejected, DeviceTimeout, LimitError, ProtocolError
from drivers.trigger import open_esper_trigger
from simulators.dng import write_dng
from simulators.serve import Faults, serve
from simulators.trigger import EsperTriggerModel, start_esper_simulator

ROOT = Path(__file__).resolve().parents[2]


# ------------------------------------------------------------------------------------- sans-IO model
def test_model_dialogue_and_on_fire_before_the_answer():
    events: list[str] = []
    model = EsperTriggerModel(lambda s: events.append(f"fire {s}"))
    assert model.receive(b"s111111\nb20\n") == b"tenFour\ntenFour\n"
    reply = model.receive(b"S\n")
    events.append("replied")
    assert reply == b"tenFour\n"
    assert events == ["fire 0.02", "replied"]
    assert model.receive(b"c\r\n") == b"count:1\n"
    assert model.receive(b"?\n") == b"id:ESPER,TriggerBox,1.0.0,TB-0001\n"


def test_model_handles_split_and_merged_input_and_refusals():
    model = EsperTriggerModel()
    out = b"".join(model.receive(bytes([b])) for b in b"m0\n\nS\nb0\nm3\nzz\n")
    assert out == b"tenFour\nerr:3\nerr:2\nerr:2\nerr:1\n"
    assert model.commands == [b"m0", b"S", b"b0", b"m3", b"zz"]
    assert model.receive(b"x" * 200) == b"err:1\n"                 # flood without newline
    assert model.receive(b"c\n") == b"count:0\n"


def test_model_reset_restores_power_up_state_and_clears_faults():
    model = EsperTriggerModel()
    model.receive(b"s111111\nb5\nS\n")
    model.error_next = 4
    model.fire_without_camera = True
    model.receive(b"partial")
    model.reset()
    assert (model.shots, model.bulb_ms, model.enabled, model.error_next, model.fire_without_camera) == \
        (0, None, (False,) * 6, None, False)
    assert model.receive(b"c\n") == b"count:0\n"


def test_model_without_enabled_outputs_or_with_camera_unplugged_does_not_fire():
    """``S`` with every output disabled fires nothing and is refused err:5 NO_OUTPUTS (tenFour means the outputs
    fired, docs/protocols/trigger-boxes.md); with the release cable unplugged the box fires into nothing."""
    fired: list[float] = []
    model = EsperTriggerModel(fired.append)
    assert model.receive(b"b10\nS\n") == b"tenFour\nerr:5\n"     # power-up: outputs disabled
    assert model.shots == 0
    model.receive(b"s000001\n")
    model.fire_without_camera = True
    assert model.receive(b"S\n") == b"tenFour\n"
    assert fired == [] and model.shots == 1


def test_overlapping_fire_is_answered_busy():
    """A second ``S`` while the first exposure still runs is refused err:4 BUSY and fires nothing; once the bulb
    time is over the box fires again."""
    now = [100.0]
    fired: list[float] = []
    model = EsperTriggerModel(fired.append, clock=lambda: now[0])
    assert model.receive(b"s111111\nb500\nS\n") == b"tenFour\ntenFour\ntenFour\n"
    now[0] += 0.2
    assert model.receive(b"S\n") == b"err:4\n"
    now[0] += 0.31
    assert model.receive(b"S\n") == b"tenFour\n"
    assert fired == [0.5, 0.5] and model.shots == 2


def test_driver_reconfigures_a_power_cycled_box(tmp_path):
    """A box that lost its output configuration (power-cycled) answers ``S`` NO_OUTPUTS; the driver sends
    ``m0`` and ``s...`` again and fires, over a real pty."""
    fired: list[float] = []
    server, model = start_esper_simulator("pty", fired.append)
    try:
        with open_esper_trigger(server.url, timeout_s=0.5) as trig:
            trig.fire(0.01)
            model.reset()                                  # power cycle: outputs disabled, no bulb time
            model.on_fire = fired.append
            trig.fire(0.01)
        assert fired == [0.01, 0.01]
        assert model.commands == [b"b10", b"S", b"m0", b"s111111", b"S"]     # refused, configured, fired
    finally:
        server.close()


def test_driver_busy_over_a_pty():
    """A box busy for a reason of its own raises DeviceBusy (the runner asks again with backoff); a BUSY caused by
    our own previous exposure, still running on the box, is waited out once and the shot fires."""
    fired: list[float] = []
    server, model = start_esper_simulator("pty", fired.append)
    try:
        with open_esper_trigger(server.url, timeout_s=0.5, wait_for_exposure=False) as trig:
            model.busy_next = 1
            with pytest.raises(DeviceBusy) as err:
                trig.fire(0.2)
            assert err.value.code == 4 and fired == []
            trig.fire(0.2)
            t0 = time.monotonic()
            trig.fire(0.2)                     # the host did not wait the first exposure out: BUSY, waited out
            assert fired == [0.2, 0.2] and time.monotonic() - t0 >= 0.15
            assert model.commands.count(b"S") == 4            # refused, fired, refused (busy), fired
    finally:
        server.close()


# ------------------------------------------------------------------------------ over pty and TCP
@pytest.fixture(params=["pty", "tcp://127.0.0.1:0"])
def sim(request):
    fired: list[float] = []
    server, model = start_esper_simulator(request.param, fired.append)
    model.fired_calls = fired
    yield server, model
    server.close()


def test_driver_against_simulator(sim):
    server, model = sim
    trig = open_esper_trigger(server.url, timeout_s=0.5)
    try:
        ident = trig.identify()
        assert (ident.model, ident.serial_number) == ("ESPER TriggerBox", "TB-0001")
        t0 = time.monotonic()
        trig.fire(0.02)
        assert model.fired_calls == [0.02]          # the camera was told before fire() returned
        assert time.monotonic() - t0 >= 0.02
        trig.fire(0.005)
        assert model.fired_calls == [0.02, 0.005]
        assert trig.shot_count() == 2
        assert model.commands == [b"?", b"m0", b"s111111", b"b20", b"S", b"b5", b"S", b"c"]
        with pytest.raises(LimitError):
            trig.fire(120.0)
        assert model.commands[-1] == b"c"
    finally:
        trig.close()


def test_mute_simulator_times_out_then_recovers(sim):
    server, model = sim
    trig = open_esper_trigger(server.url, timeout_s=0.2)
    try:
        server.faults.mute = True
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout):
            trig.shot_count()
        assert time.monotonic() - t0 < 1.0
        server.faults.clear()
        assert trig.shot_count() == 0
    finally:
        trig.close()


def test_garbage_line_is_a_protocol_error_then_the_driver_resyncs(sim):
    server, model = sim
    trig = open_esper_trigger(server.url, timeout_s=0.3)
    try:
        server.faults.garbage = b"\x00\xfe#noise\n"
        with pytest.raises(ProtocolError):
            trig.shot_count()
        time.sleep(0.05)                      # let the real answer behind the garbage arrive (then flushed)
        assert trig.shot_count() == 0
        trig.configure()
        model.garble_next = b"tenF0ur\n"             # the answer to b10 is garbled: S must not follow
        with pytest.raises(ProtocolError):
            trig.fire(0.01)
        assert model.commands[-1] == b"b10" and model.fired_calls == []
        trig.fire(0.01)
        assert model.fired_calls == [0.01]
    finally:
        trig.close()


def test_split_slow_replies_are_reassembled(sim):
    server, model = sim
    server.faults.split_at = 1
    server.faults.latency_s = 0.01
    trig = open_esper_trigger(server.url, timeout_s=1.0)
    try:
        assert trig.identify().firmware == "1.0.0"
        trig.fire(0.01)
        assert model.fired_calls == [0.01]
    finally:
        trig.close()


def test_device_refusal_reaches_the_caller_with_its_code(sim):
    server, model = sim
    trig = open_esper_trigger(server.url, timeout_s=0.5)
    try:
        model.error_next = 4
        with pytest.raises(DeviceRejected) as info:
            trig.shot_count()
        assert info.value.code == 4 and info.value.name == "BUSY"
    finally:
        trig.close()


def test_tcp_disconnect_is_connection_lost():
    server, model = start_esper_simulator("tcp://127.0.0.1:0")
    trig = open_esper_trigger(server.url, timeout_s=0.5)
    try:
        assert trig.shot_count() == 0
        server.disconnect()
        time.sleep(0.05)
        with pytest.raises((ConnectionLost, DeviceTimeout)) as info:
            trig.shot_count()
        assert isinstance(info.value, ConnectionLost), info.value
    finally:
        trig.close()
        server.close()


def test_unopenable_url_is_connection_lost():
    with pytest.raises(ConnectionLost, match="/dev/nonexistent-trigger"):
        open_esper_trigger("/dev/nonexistent-trigger")


# ------------------------------------------------------------------------------ command line
def test_main_prints_a_url_the_driver_can_open():
    proc = subprocess.Popen([sys.executable, "-m", "simulators.trigger", "--url", "tcp://127.0.0.1:0", "--quiet"],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        url = proc.stdout.readline().strip()
        assert url.startswith("socket://127.0.0.1:")
        trig = open_esper_trigger(url, timeout_s=1.0)
        try:
            assert trig.identify().model == "ESPER TriggerBox"
        finally:
            trig.close()
    finally:
        proc.terminate()
        proc.wait(timeout=5)


def test_main_refuses_a_bad_url(capsys):
    from simulators.trigger import main

    assert main(["--url", "udp://x"]) == 2
    assert "udp://x" in capsys.readouterr().err


# --------------------------------------------------------------------- trigger -> camera -> folder
def test_fire_drops_a_frame_that_the_folder_camera_fetches(tmp_path):
    scene = np.random.default_rng(7).uniform(0.1, 0.9, (12, 12, 3))
    shot = [0]

    def simulated_camera(exposure_s: float) -> None:        # renders "instantly" under the current light
        shot[0] += 1
        write_dng(tmp_path / f"IMG_{shot[0]:04d}.dng", scene * exposure_s / 0.04, exposure_s=exposure_s)

    server = serve(EsperTriggerModel(simulated_camera), "pty", Faults())
    trig = open_esper_trigger(server.url, timeout_s=0.5)
    cam = FolderCamera(tmp_path, settle_s=0.01)
    try:
        cam.arm()
        trig.fire(0.02)
        frame = cam.fetch(timeout_s=1.0)
        assert frame.exposure_s == 0.02 and os.path.basename(frame.path) == "IMG_0001.dng"
        np.testing.assert_allclose(frame.rgb, scene / 2, atol=0.5 / (16383 - 512) + 1e-7)
        cam.arm()
        with pytest.raises(DeviceTimeout):            # no fire, no frame
            cam.fetch(timeout_s=0.1)
    finally:
        trig.close()
        server.close()
