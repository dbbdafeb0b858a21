"""Serial-line shutter release on pyserial ``loop://`` (RTS mirrored on CTS, DTR on DSR)."""
from __future__ import annotations

import os
import threading
import time

import pytest
import serial

from drivers.contracts import Trigger
from drivers.errors import ConnectionLost, LimitError
from drivers.trigger.serial_release import SerialRelease, open_serial_release


class Observer:
    """An injected ``sleep`` that records the mirrored lines at the start of every wait."""

    def __init__(self) -> None:
        self.port = None
        self.calls: list[tuple[float, bool, bool]] = []

    def __call__(self, seconds: float) -> None:
        self.calls.append((seconds, self.port.cts, self.port.dsr))


def observed(**kw) -> tuple[SerialRelease, Observer]:
    obs = Observer()
    rel = open_serial_release("loop://", sleep=obs, **kw)
    obs.port = rel.port
    return rel, obs


def test_pyserial_asserts_both_lines_on_open_which_is_why_the_factory_exists():
    raw = serial.serial_for_url("loop://")
    try:
        assert raw.cts and raw.dsr
    finally:
        raw.close()
    rel = open_serial_release("loop://")
    try:
        assert not rel.port.cts and not rel.port.dsr
    finally:
        rel.close()


def test_focus_then_shutter_for_the_exposure_then_both_released():
    rel, obs = observed(focus_lead_s=0.1)
    rel.fire(0.25)
    # (duration, CTS=focus, DSR=shutter) at the start of each phase
    assert obs.calls == [(0.1, True, False), (0.25, True, True)]
    assert (rel.port.cts, rel.port.dsr) == (False, False)
    rel.close()


def test_exposure_is_rounded_to_whole_ms_and_no_focus_lead_is_allowed():
    rel, obs = observed(focus_lead_s=0.0)
    rel.fire(0.0334)
    assert obs.calls == [(0.033, True, True)]
    rel.close()


def test_real_time_pulse_is_observed_on_cts_and_dsr():
    rel = open_serial_release("loop://", focus_lead_s=0.03)
    port = rel.port
    samples: list[tuple[float, bool, bool]] = []
    stop = threading.Event()

    def sample() -> None:
        while not stop.is_set():
            samples.append((time.monotonic(), port.cts, port.dsr))
            time.sleep(0.0005)

    th = threading.Thread(target=sample)
    th.start()
    time.sleep(0.01)
    rel.fire(0.08)
    time.sleep(0.01)
    stop.set()
    th.join()
    cts_high = [t for t, cts, _ in samples if cts]
    dsr_high = [t for t, _, dsr in samples if dsr]
    assert cts_high and dsr_high
    assert dsr_high[0] - cts_high[0] >= 0.025                        # focus leads the shutter
    assert 0.07 <= dsr_high[-1] - dsr_high[0] <= 0.25                  # shutter held ~ the exposure
    assert all(cts for _, cts, dsr in samples if dsr)                 # focus held while exposing
    assert samples[-1][1:] == (False, False) and not samples[0][1] and not samples[0][2]
    rel.close()


def test_lines_are_released_when_the_exposure_is_interrupted():
    seen = []

    def interrupted(seconds: float) -> None:
        seen.append(rel.port.dsr)
        raise KeyboardInterrupt

    rel = open_serial_release("loop://", focus_lead_s=0.0, sleep=interrupted)
    with pytest.raises(KeyboardInterrupt):
        rel.fire(1.0)
    assert seen == [True]
    assert (rel.port.cts, rel.port.dsr) == (False, False)
    rel.close()


@pytest.mark.parametrize("exposure", [0.0, -0.1, 0.0001, 61.0, float("nan"), "1"])
def test_out_of_range_exposure_touches_no_line(exposure):
    rel, obs = observed()
    with pytest.raises(LimitError):
        rel.fire(exposure)
    assert obs.calls == [] and (rel.port.cts, rel.port.dsr) == (False, False)
    rel.close()


def test_a_pty_cannot_drive_modem_lines_and_says_so():
    master, slave = os.openpty()
    try:
        port = serial.Serial(os.ttyname(slave), timeout=0.1)
        rel = SerialRelease(port, focus_lead_s=0.0, sleep=lambda s: None)
        with pytest.raises(ConnectionLost, match="modem lines"):
            rel.fire(0.01)
        rel.close()
    finally:
        os.close(master)
        os.close(slave)


def test_identify_contract_and_close():
    rel = open_serial_release("loop://")
    assert isinstance(rel, Trigger)
    ident = rel.identify()
    assert ident.kind == "trigger" and ident.extra["shutter_line"] == "DTR"
    rel.close()
    rel.close()
    assert not rel.port.is_open
    with pytest.raises(ConnectionLost):
        rel.fire(0.01)


def test_unopenable_url_is_connection_lost():
    with pytest.raises(ConnectionLost, match="nosuch"):
        open_serial_release("nosuch://x")
