"""ESPER-style ASCII trigger box: golden codec frames, scripted dialogues (pymeasure ``expected_protocol``
style, failing on leftovers), error mapping, limits, resync, and Hypothesis robustness of the decoders."""
from __future__ import annotations

import math
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.contracts import Trigger
from drivers.errors import (ConnectionLost, DeviceBusy, DeviceRejected, DeviceTimeout, LimitError,
                            ProtocolError)
from drivers.trigger import esper as ec
from drivers.trigger.esper import EsperTrigger


class ScriptedPort:
    """A ByteTransport replaying (bytes the driver must send, bytes the box answers) pairs byte-exactly."""

    def __init__(self, script: list[tuple[bytes, bytes]]) -> None:
        self.script = list(script)
        self.timeout = 0.01
        self._written = bytearray()
        self._reply = bytearray()
        self.closed = False
        self.all_written = bytearray()

    def write(self, data: bytes) -> int:
        self.all_written += data
        self._written += data
        assert self.script, f"driver sent {bytes(self._written)!r} after the end of the script"
        expected, reply = self.script[0]
        assert expected.startswith(bytes(self._written)), \
            f"driver sent {bytes(self._written)!r}, script expects {expected!r}"
        if bytes(self._written) == expected:
            self.script.pop(0)
            self._written.clear()
            self._reply += reply
        return len(data)

    def read(self, size: int = 1) -> bytes:
        if not self._reply:
            time.sleep(self.timeout)
            return b""
        out = bytes(self._reply[:size])
        del self._reply[:size]
        return out

    def reset_input_buffer(self) -> None:
        assert not self._reply, f"unread reply bytes {bytes(self._reply)!r} before the next command"

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self.closed = True

    def assert_done(self) -> None:
        assert not self.script, f"script not finished: {self.script}"
        assert not self._written, f"partial command left: {bytes(self._written)!r}"
        assert not self._reply, f"reply bytes left unread: {bytes(self._reply)!r}"


ACK = b"tenFour\n"


def make(script, **kw) -> tuple[EsperTrigger, ScriptedPort]:
    port = ScriptedPort(script)
    kw.setdefault("timeout_s", 0.2)
    return EsperTrigger(port, **kw), port


# ------------------------------------------------------------------------------------- codec goldens
@pytest.mark.parametrize("cmd, wire", [
    (ec.SetMode(0), b"m0\n"),
    (ec.EnableOutputs((True,) * 6), b"s111111\n"),
    (ec.EnableOutputs((True, False, True, False, False, True)), b"s101001\n"),
    (ec.SetBulb(250), b"b250\n"),
    (ec.SetBulb(1), b"b1\n"),
    (ec.SetBulb(9_999_999), b"b9999999\n"),
    (ec.Fire(), b"S\n"),
    (ec.Identify(), b"?\n"),
    (ec.GetCount(), b"c\n"),
])
def test_command_golden_frames(cmd, wire):
    assert ec.encode_command(cmd) == wire
    assert ec.parse_command(wire.rstrip(b"\n")) == cmd
    assert ec.parse_command(wire.rstrip(b"\n") + b"\r") == cmd


@pytest.mark.parametrize("cmd", [ec.SetMode(10), ec.SetBulb(0), ec.SetBulb(10_000_000),
                                 ec.EnableOutputs((True,) * 5)])
def test_encode_refuses_out_of_range_commands(cmd):
    with pytest.raises(ValueError):
        ec.encode_command(cmd)


@pytest.mark.parametrize("line, code", [
    (b"b0", ec.ERR_BAD_ARGUMENT), (b"b-5", ec.ERR_BAD_ARGUMENT), (b"b12345678", ec.ERR_BAD_ARGUMENT),
    (b"s11", ec.ERR_BAD_ARGUMENT), (b"s1111112", ec.ERR_BAD_ARGUMENT), (b"m", ec.ERR_BAD_ARGUMENT),
    (b"X", ec.ERR_UNKNOWN_COMMAND), (b"SS", ec.ERR_UNKNOWN_COMMAND), (b"\xff", ec.ERR_UNKNOWN_COMMAND),
])
def test_parse_command_rejects_with_the_right_code(line, code):
    with pytest.raises(ProtocolError):
        ec.parse_command(line)
    assert ec.command_error_code(line) == code


@pytest.mark.parametrize("wire, reply", [
    (b"tenFour\n", ec.Ack()),
    (b"id:ESPER,TriggerBox,1.0.0,TB-0001\n", ec.Identity("ESPER", "TriggerBox", "1.0.0", "TB-0001")),
    (b"count:0\n", ec.ShotCount(0)),
    (b"count:1234567\n", ec.ShotCount(1234567)),
    (b"err:3\n", ec.ErrorReply(3)),
])
def test_reply_golden_frames(wire, reply):
    assert ec.encode_reply(reply) == wire
    assert ec.decode_reply(wire) == (len(wire), reply)
    assert ec.parse_reply(wire.rstrip(b"\n") + b"\r") == reply


@pytest.mark.parametrize("line", [b"tenfour", b"tenFour!", b"count:", b"count:-1", b"err:x", b"id:a,b,c",
                                  b"id:a,b,c,d,e", b"\x00tenFour", b"ten\xc3\xa9Four", b" tenFour"])
def test_parse_reply_rejects_malformed_lines(line):
    with pytest.raises(ProtocolError):
        ec.parse_reply(line)


def test_decode_reply_needs_more_until_the_terminator():
    wire = b"\r\n\ncount:42\r\ntenFour\n"
    for cut in range(len(b"\r\n\ncount:42\r")):
        consumed, reply = ec.decode_reply(wire[:cut])
        assert reply is None
        assert consumed <= cut
    consumed, reply = ec.decode_reply(wire)
    assert reply == ec.ShotCount(42)
    assert ec.decode_reply(wire[consumed:]) == (len(ACK), ec.Ack())


def test_decode_reply_gives_up_on_an_endless_line():
    with pytest.raises(ProtocolError, match="no line terminator"):
        ec.decode_reply(b"x" * (ec.MAX_LINE + 1))


# --------------------------------------------------------------------------------- Hypothesis
@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_arbitrary_bytes_into_decoders_raise_only_protocol_error(data):
    for fn in (ec.decode_reply, ec.parse_reply, ec.parse_command):
        try:
            fn(data)
        except ProtocolError:
            pass


_field = st.text(alphabet=st.characters(min_codepoint=0x21, max_codepoint=0x7E, blacklist_characters=","),
                 min_size=1, max_size=12)
_replies = st.one_of(st.just(ec.Ack()), st.builds(ec.ShotCount, st.integers(0, 10 ** 10 - 1)),
                     st.builds(ec.ErrorReply, st.integers(0, 999)),
                     st.builds(ec.Identity, _field, _field, _field, _field))
_commands = st.one_of(st.builds(ec.SetMode, st.integers(0, 9)),
                      st.builds(ec.EnableOutputs, st.tuples(*[st.booleans()] * 6)),
                      st.builds(ec.SetBulb, st.integers(1, ec.BULB_MAX_MS)),
                      st.just(ec.Fire()), st.just(ec.Identify()), st.just(ec.GetCount()))


@settings(max_examples=200, deadline=None)
@given(st.lists(_replies, min_size=1, max_size=5), st.integers(1, 7))
def test_replies_round_trip_through_any_chunking(replies, chunk):
    wire = b"".join(ec.encode_reply(r) for r in replies)
    buf, got = b"", []
    for i in range(0, len(wire), chunk):
        buf += wire[i:i + chunk]
        while True:
            consumed, reply = ec.decode_reply(buf)
            buf = buf[consumed:]
            if reply is None:
                break
            got.append(reply)
    assert got == replies and buf == b""


@settings(max_examples=200, deadline=None)
@given(_commands)
def test_commands_round_trip(cmd):
    assert ec.parse_command(ec.encode_command(cmd).rstrip(b"\n")) == cmd


# --------------------------------------------------------------------------------- driver dialogues
def test_first_fire_configures_then_fires_golden_dialogue():
    trig, port = make([(b"m0\n", ACK), (b"s111111\n", ACK), (b"b250\n", ACK), (b"S\n", ACK)],
                      wait_for_exposure=False)
    trig.fire(0.25)
    port.assert_done()
    port.script = [(b"b20\n", ACK), (b"S\n", b"\r\n" + ACK)]      # later fires: bulb + fire only
    trig.fire(0.02)
    port.assert_done()


def test_fire_rounds_to_whole_milliseconds_and_uses_configured_outputs():
    trig, port = make([(b"m0\n", ACK), (b"s100001\n", ACK), (b"b33\n", ACK), (b"S\n", ACK)],
                      outputs=(True, False, False, False, False, True), wait_for_exposure=False)
    trig.fire(0.0334)
    port.assert_done()


def test_fire_returns_only_after_the_exposure():
    trig, port = make([(b"m0\n", ACK), (b"s111111\n", ACK), (b"b120\n", ACK), (b"S\n", ACK)])
    t0 = time.monotonic()
    trig.fire(0.12)
    assert time.monotonic() - t0 >= 0.12
    port.assert_done()


def test_identify_golden_dialogue():
    trig, port = make([(b"?\n", b"id:ESPER,TriggerBox,2.1.3,TB-0042\r\n")])
    ident = trig.identify()
    port.assert_done()
    assert (ident.kind, ident.model, ident.firmware, ident.serial_number) == \
        ("trigger", "ESPER TriggerBox", "2.1.3", "TB-0042")
    assert isinstance(trig, Trigger)


def test_shot_count_golden_dialogue():
    trig, port = make([(b"c\n", b"count:17\n")])
    assert trig.shot_count() == 17
    port.assert_done()


@pytest.mark.parametrize("exposure", [0.0, -1.0, 0.0004, 60.5, math.nan, math.inf, "0.1", None])
def test_out_of_range_exposure_is_refused_before_sending(exposure):
    trig, port = make([])
    with pytest.raises(LimitError):
        trig.fire(exposure)
    assert port.all_written == b""


def test_custom_exposure_limits():
    trig, port = make([], max_exposure_s=0.5)
    with pytest.raises(LimitError, match="0.5"):
        trig.fire(0.6)
    assert port.all_written == b""


@pytest.mark.parametrize("code, exc, name", [(1, DeviceRejected, "UNKNOWN_COMMAND"),
                                             (3, DeviceRejected, "NO_BULB"), (4, DeviceBusy, "BUSY")])
def test_error_replies_become_typed_errors(code, exc, name):
    trig, port = make([(b"m0\n", ACK), (b"s111111\n", ACK), (b"b10\n", ACK), (b"S\n", f"err:{code}\n".encode())])
    with pytest.raises(exc) as info:
        trig.fire(0.01)
    assert info.value.code == code and info.value.name == name
    port.assert_done()


def test_mute_box_times_out_within_the_timeout():
    trig, port = make([(b"?\n", b"")], timeout_s=0.15)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match="'\\?'"):
        trig.identify()
    assert 0.15 <= time.monotonic() - t0 < 0.5
    port.assert_done()


def test_partial_reply_then_silence_times_out():
    trig, port = make([(b"c\n", b"count:1")], timeout_s=0.1)
    with pytest.raises(DeviceTimeout, match="partial"):
        trig.shot_count()


def test_endless_empty_lines_still_time_out():
    trig, port = make([(b"c\n", b"")], timeout_s=0.05)
    port.read = lambda size=1: (time.sleep(0.0001), b"\n")[1]       # a box that chatters forever
    with pytest.raises(DeviceTimeout):
        trig.shot_count()


def test_garbage_line_raises_protocol_error_and_next_command_resyncs():
    trig, port = make([(b"c\n", b"\x07#garbage\n"), (b"c\n", b"count:5\n")])
    with pytest.raises(ProtocolError, match="garbled"):
        trig.shot_count()
    assert trig.shot_count() == 5
    port.assert_done()


def test_wrong_kind_of_reply_is_a_protocol_error():
    trig, port = make([(b"m0\n", b"count:3\n")])
    with pytest.raises(ProtocolError, match="tenFour"):
        trig.configure()


def test_closed_trigger_refuses_and_close_is_idempotent():
    trig, port = make([])
    trig.close()
    trig.close()
    assert port.closed
    with pytest.raises(ConnectionLost):
        trig.shot_count()
