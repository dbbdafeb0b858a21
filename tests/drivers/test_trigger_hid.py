"""USB HID trigger box: golden reports, scripted report exchanges (failing on leftovers), the driver against
the fake device model at the ``HidTransport`` seam, faults, the hidapi wrapper, and Hypothesis robustness."""
from __future__ import annotations

import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.contracts import Trigger
from drivers.errors import (ConnectionLost, DeviceBusy, DeviceRejected, DeviceTimeout, LimitError,
                            ProtocolError)
from drivers.trigger import hid_box as hc
from drivers.trigger.hid_box import HidapiTransport, HidTransport, HidTrigger
from simulators.trigger import FakeHidTriggerBox


def h(text: str) -> bytes:
    """Hex with spaces -> bytes, zero-padded to one report."""
    data = bytes.fromhex(text)
    return data + bytes(hc.REPORT_SIZE - len(data))


class ScriptedHid:
    """HidTransport replaying (report the driver must write, report the box answers) pairs exactly."""

    def __init__(self, script: list[tuple[bytes, bytes]]) -> None:
        self.script = list(script)
        self.pending: list[bytes] = []
        self.writes: list[bytes] = []
        self.closed = False

    def write(self, data: bytes) -> int:
        self.writes.append(bytes(data))
        assert self.script, f"driver wrote {data.hex(' ')} after the end of the script"
        expected, reply = self.script.pop(0)
        assert bytes(data) == expected, f"driver wrote {data.hex(' ')}, script expects {expected.hex(' ')}"
        if reply:
            self.pending.append(reply)
        return len(data)

    def read(self, n: int, timeout_ms: int) -> bytes:
        if not self.pending:
            time.sleep(min(timeout_ms, 10) / 1000)
            return b""
        return self.pending.pop(0)[:n]

    def close(self) -> None:
        self.closed = True

    def assert_done(self) -> None:
        assert not self.script, f"script not finished: {self.script}"
        assert not self.pending, f"answers left unread: {self.pending}"


# ----------------------------------------------------------------------------------------- goldens
@pytest.mark.parametrize("report, wire", [
    (hc.OutputReport(hc.CMD_FIRE, 3), h("01 01 03")),
    (hc.OutputReport(hc.CMD_SET_BULB, 2, 250), h("01 02 02 fa 00 00 00")),
    (hc.OutputReport(hc.CMD_SET_BULB, 0xFF, 0x01020304), h("01 02 ff 04 03 02 01")),
    (hc.OutputReport(hc.CMD_ENABLE, 1, 0x3F), h("01 03 01 3f 00 00 00")),
    (hc.OutputReport(hc.CMD_GET_STATUS, 0), h("01 04 00")),
])
def test_output_report_golden(report, wire):
    assert len(wire) == 16
    assert hc.encode_output(report) == wire
    assert hc.decode_output(wire) == report


def test_status_report_golden():
    wire = h("02 07 00 2a 01 00 00 01 25 e8 03 00 00 02 05 00")
    st_ = hc.decode_status(wire)
    assert st_ == hc.StatusReport(seq=7, result=0, shot_count=298, busy=True, enabled_mask=0x25,
                                  bulb_ms=1000, firmware=(2, 5))
    assert hc.encode_status(st_) == wire


@pytest.mark.parametrize("wire, match", [
    (h("02 07 00")[:15], "16 bytes"),
    (h("02 07 00") + b"\x00", "16 bytes"),
    (h("03 07 00"), "report id"),
    (h("02 07 00 00 00 00 00 02"), "reserved"),          # flags bit 1
    (h("02 07 00 00 00 00 00 00 40"), "reserved"),       # mask bit 6
    (h("02 07 00 00 00 00 00 00 00 00 00 00 00 00 00 01"), "reserved"),
])
def test_bad_status_reports_are_protocol_errors(wire, match):
    with pytest.raises(ProtocolError, match=match):
        hc.decode_status(wire)


def test_bad_output_reports_are_protocol_errors():
    with pytest.raises(ProtocolError, match="report id"):
        hc.decode_output(h("02 01 01"))
    with pytest.raises(ProtocolError, match="reserved"):
        hc.decode_output(h("01 01 01 00 00 00 00 01"))
    assert hc.decode_output(h("01 77 01")).command == 0x77     # unknown command: answered, not a framing error


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=40))
def test_arbitrary_bytes_into_report_decoders_raise_only_protocol_error(data):
    for fn in (hc.decode_status, hc.decode_output):
        try:
            fn(data)
        except ProtocolError:
            pass


@settings(max_examples=200, deadline=None)
@given(st.builds(hc.StatusReport, st.integers(0, 255), st.integers(0, 255), st.integers(0, hc.U32_MAX),
                 st.booleans(), st.integers(0, hc.ALL_OUTPUTS), st.integers(0, hc.U32_MAX),
                 st.tuples(st.integers(0, 255), st.integers(0, 255))))
def test_status_round_trip(status):
    assert hc.decode_status(hc.encode_status(status)) == status


# ------------------------------------------------------------------------------- scripted dialogue
def test_first_fire_golden_exchange_as_documented():
    hid = ScriptedHid([
        (h("01 03 01 3f 00 00 00"), h("02 01 00 00 00 00 00 00 3f 00 00 00 00 01 00 00")),
        (h("01 02 02 fa 00 00 00"), h("02 02 00 00 00 00 00 00 3f fa 00 00 00 01 00 00")),
        (h("01 01 03"), h("02 03 00 01 00 00 00 01 3f fa 00 00 00 01 00 00")),
        (h("01 04 04"), h("02 04 00 01 00 00 00 00 3f fa 00 00 00 01 00 00")),
    ])
    trig = HidTrigger(hid, timeout_s=0.2)
    t0 = time.monotonic()
    trig.fire(0.25)
    assert time.monotonic() - t0 >= 0.25
    hid.assert_done()


def test_busy_is_polled_until_clear():
    hid = ScriptedHid([
        (h("01 03 01 3f 00 00 00"), h("02 01 00 00 00 00 00 00 3f 00 00 00 00 01 00 00")),
        (h("01 02 02 0a 00 00 00"), h("02 02 00 00 00 00 00 00 3f 0a 00 00 00 01 00 00")),
        (h("01 01 03"), h("02 03 00 01 00 00 00 01 3f 0a 00 00 00 01 00 00")),
        (h("01 04 04"), h("02 04 00 01 00 00 00 01 3f 0a 00 00 00 01 00 00")),     # still busy
        (h("01 04 05"), h("02 05 00 01 00 00 00 00 3f 0a 00 00 00 01 00 00")),     # done
    ])
    HidTrigger(hid, timeout_s=0.3, poll_interval_s=0.001).fire(0.01)
    hid.assert_done()


def test_stale_answer_is_skipped_by_sequence_number():
    hid = ScriptedHid([(h("01 04 01"), h("02 01 00 09 00 00 00 00 00 00 00 00 00 01 00 00"))])
    hid.pending.append(h("02 ff 00 00 00 00 00 00 00 00 00 00 00 01 00 00"))   # an old answer, read first
    assert HidTrigger(hid, timeout_s=0.2).status().shot_count == 9
    hid.assert_done()


def test_answer_with_the_wrong_sequence_number_only_times_out():
    hid = ScriptedHid([(h("01 04 01"), h("02 00 00 09 00 00 00 00 00 00 00 00 00 01 00 00"))])
    with pytest.raises(DeviceTimeout, match="1 stale"):
        HidTrigger(hid, timeout_s=0.1).status()


# ------------------------------------------------------------------------------ driver vs fake box
@pytest.fixture
def box():
    fired: list[float] = []
    fake = FakeHidTriggerBox(fired.append, firmware=(1, 2))
    fake.calls = fired
    return fake


def test_fake_satisfies_the_transport_seam_and_driver_the_contract(box):
    assert isinstance(box, HidTransport)
    assert isinstance(HidTrigger(box), Trigger)


def test_identify_against_fake(box):
    ident = HidTrigger(box).identify()
    assert (ident.kind, ident.model, ident.firmware, ident.serial_number) == \
        ("trigger", "sssrig SimTrigger HID", "1.2", "HID-0001")


def test_fire_against_fake_tells_the_camera_and_waits_for_the_exposure(box):
    trig = HidTrigger(box, timeout_s=0.5)
    t0 = time.monotonic()
    trig.fire(0.03)
    assert time.monotonic() - t0 >= 0.03
    assert box.calls == [0.03]
    st_ = trig.status()
    assert (st_.shot_count, st_.busy, st_.enabled_mask, st_.bulb_ms) == (1, False, 0x3F, 30)
    trig.fire(0.02)
    assert box.calls == [0.03, 0.02] and box.shots == 2
    assert [r.command for r in box.received[:4]] == [hc.CMD_ENABLE, hc.CMD_SET_BULB, hc.CMD_FIRE,
                                                     hc.CMD_GET_STATUS]


def test_fire_with_no_outputs_enabled_does_not_reach_the_camera(box):
    trig = HidTrigger(box, outputs_mask=0)
    trig.fire(0.005)
    assert box.shots == 1 and box.calls == []


def test_limit_error_sends_nothing(box):
    trig = HidTrigger(box)
    for bad in (0.0, 61.0, float("nan")):
        with pytest.raises(LimitError):
            trig.fire(bad)
    with pytest.raises(LimitError):
        trig.enable(0x40)
    assert box.received == [] and box.calls == []


def test_mute_box_times_out(box):
    box.mute = True
    trig = HidTrigger(box, timeout_s=0.1)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout):
        trig.status()
    assert 0.1 <= time.monotonic() - t0 < 0.5


def test_stale_reports_from_the_box_are_skipped(box):
    box.stale_next = 3
    assert HidTrigger(box, timeout_s=0.2).status().seq == 1


def test_garbled_report_is_a_protocol_error_then_the_next_command_works(box):
    box.garble_next = b"\x02\xff\xff"
    trig = HidTrigger(box, timeout_s=0.2)
    with pytest.raises(ProtocolError, match="garbled"):
        trig.status()
    assert trig.status().result == hc.RESULT_OK


@pytest.mark.parametrize("code, exc", [(hc.RESULT_BUSY, DeviceBusy), (hc.RESULT_BAD_ARGUMENT, DeviceRejected)])
def test_refusals_become_typed_errors(box, code, exc):
    box.error_next = code
    with pytest.raises(exc) as info:
        HidTrigger(box).status()
    assert info.value.code == code


def test_fire_twice_during_exposure_is_busy_without_waiting(box):
    trig = HidTrigger(box, wait_for_exposure=False)
    trig.fire(0.5)
    with pytest.raises(DeviceBusy):
        trig.fire(0.5)
    assert box.shots == 1


def test_box_that_never_finishes_the_exposure_times_out():
    now = [0.0]
    box = FakeHidTriggerBox(clock=lambda: now[0])        # frozen clock: the exposure never ends
    trig = HidTrigger(box, timeout_s=0.1, poll_interval_s=0.005)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match="still busy"):
        trig.fire(0.02)
    assert 0.12 <= time.monotonic() - t0 < 0.6
    assert box.shots == 1


def test_unplugged_box_is_connection_lost(box):
    trig = HidTrigger(box, timeout_s=0.2)
    assert trig.status().result == hc.RESULT_OK
    box.unplugged = True
    with pytest.raises(ConnectionLost):
        trig.fire(0.01)
    assert box.shots == 0


def test_fake_ignores_malformed_output_reports(box):
    assert box.write(b"\x01\x01") == 2
    assert box.bad_reports == [b"\x01\x01"] and box.read(16, 1) == b""


# ------------------------------------------------------------------------------- hidapi wrapper
class FakeHidapiDevice:
    def __init__(self, write_result=16, read_data=(2, 0)):
        self.write_result, self.read_data, self.closed = write_result, list(read_data), False

    def get_manufacturer_string(self):
        return "ACME"

    def get_product_string(self):
        return "Trig"

    def get_serial_number_string(self):
        raise OSError("no serial")

    def write(self, data):
        return self.write_result

    def read(self, n, timeout_ms):
        return self.read_data[:n]

    def error(self):
        return "pipe error"

    def close(self):
        self.closed = True


def test_hidapi_wrapper_converts_and_maps_errors():
    t = HidapiTransport(FakeHidapiDevice())
    assert (t.manufacturer, t.product, t.serial) == ("ACME", "Trig", "")
    assert t.write(bytes(16)) == 16
    assert t.read(16, 5) == b"\x02\x00"
    bad = HidapiTransport(FakeHidapiDevice(write_result=-1))
    with pytest.raises(ConnectionLost, match="pipe error"):
        bad.write(bytes(16))


def test_opening_an_absent_device_is_connection_lost():
    with pytest.raises(ConnectionLost, match="f00d:beef"):
        HidapiTransport.open(0xF00D, 0xBEEF)
