"""GeoCOM ASCII codec: golden frames from the wire format in shared/reference/devices.md, CRC-16/ARC,
return-code classification, the polar and rig-frame conventions, and Hypothesis properties."""
from __future__ import annotations

import enum
import math

import pytest
from geocompy.communication import crc16_bitwise as geocompy_crc16
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.errors import ProtocolError
from drivers.total_station import codec
from drivers.total_station.driver import instrument_to_rig, rig_to_instrument


def _crc_reference(data: bytes) -> int:
    """Bit-by-bit CRC-16/ARC straight from its definition (reflected poly 0xA001, init 0, no xorout)."""
    crc = 0
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


# ----------------------------------------------------------------------------------------------- CRC
def test_crc16_arc_check_value():
    assert codec.crc16_arc(b"123456789") == 0xBB3D
    assert codec.crc16_arc("123456789") == 0xBB3D
    assert codec.crc16_arc(b"") == 0


@given(st.binary(max_size=200))
def test_crc16_matches_bitwise_definition_and_geocompy(data):
    assert codec.crc16_arc(data) == _crc_reference(data) == geocompy_crc16(data)


# ------------------------------------------------------------------------------------- golden frames
@pytest.mark.parametrize(("args", "kwargs", "frame"), [
    ((0,), {}, b"%R1Q,0,0:\r\n"),                                             # COM_NullProc
    ((5004,), {"trid": 3}, b"%R1Q,5004,3:\r\n"),                              # CSV_GetInstrumentName
    ((2082, (5000, 1)), {"trid": 17}, b"%R1Q,2082,17:5000,1\r\n"),            # TMC_GetCoordinate
    ((9027, (0.785398, 1.570796, 0, 1, 0)), {"trid": 12},
     b"%R1Q,9027,12:0.785398,1.570796,0,1,0\r\n"),                            # AUT_MakePositioning
    ((2008, (1, 1)), {"trid": 32767}, b"%R1Q,2008,32767:1,1\r\n"),
    ((5008, ("abc", True, False)), {"trid": None}, b'%R1Q,5008:"abc",1,0\r\n'),
    ((5004,), {"trid": 3, "checksum": True}, b"%R1Q,5004,3,862:\r\n"),
    ((2082, (5000, 1)), {"trid": 17, "checksum": True}, b"%R1Q,2082,17,9875:5000,1\r\n"),
])
def test_encode_request_golden(args, kwargs, frame):
    assert codec.encode_request(*args, **kwargs) == frame


@pytest.mark.parametrize(("args", "kwargs", "frame"), [
    ((0,), {}, b"%R1P,0,0:0\r\n"),
    ((0, ("TS60",)), {"trid": 3}, b'%R1P,0,3:0,"TS60"\r\n'),
    ((0, ("TS60",)), {"trid": 3, "checksum": True}, b'%R1P,0,3,25802:0,"TS60"\r\n'),
    ((1284, (1.5, -2.25, 0.125, 42, 1.5, -2.25, 0.125, 42)), {"trid": 17, "checksum": True},
     b"%R1P,0,17,7615:1284,1.5,-2.25,0.125,42,1.5,-2.25,0.125,42\r\n"),
    ((0,), {"trid": 9, "com_rc": 3081}, b"%R1P,3081,9:0\r\n"),
    ((1292,), {"trid": 5}, b"%R1P,0,5:1292\r\n"),
])
def test_encode_reply_golden(args, kwargs, frame):
    assert codec.encode_reply(*args, **kwargs) == frame


def test_decode_reply_golden():
    reply = codec.decode_reply(b"%R1P,0,17,7615:1284,1.5,-2.25,0.125,42,1.5,-2.25,0.125,42\r\n")
    assert reply == codec.Reply(rc=1284, params=("1.5", "-2.25", "0.125", "42", "1.5", "-2.25", "0.125", "42"),
                                trid=17, com_rc=0, crc=7615)
    assert reply.code == 1284
    assert [codec.parse_float(p) for p in reply.params[:3]] == [1.5, -2.25, 0.125]
    timed_out = codec.decode_reply("%R1P,3077,4:0")
    assert (timed_out.com_rc, timed_out.rc, timed_out.code, timed_out.params) == (3077, 0, 3077, ())
    name = codec.decode_reply(b'%R1P,0,3:0,"TS60"')
    assert codec.parse_str(name.params[0]) == "TS60"


def test_decode_request_golden():
    assert codec.decode_request(b"%R1Q,9027,12:0.785398,1.570796,0,1,0\r\n") == codec.Request(
        rpc=9027, params=("0.785398", "1.570796", "0", "1", "0"), trid=12, crc=None)
    # geocompy sends a bare LF first; GeoCOM allows a leading LF before a request; the trid may be omitted
    assert codec.decode_request(b"\n%R1Q,0,0:\r\n") == codec.Request(rpc=0, params=(), trid=0)
    assert codec.decode_request(b"%R1Q,5008:").trid is None
    assert codec.decode_request(b"%R1Q,2082,17,9875:5000,1\r\n").crc == 9875
    # commas inside quoted strings do not split parameters
    assert codec.decode_request(b'%R1Q,1,1:"a,b",2').params == ('"a,b"', "2")


def test_geocompy_request_frames_decode():
    """The frames geocompy 1.0 writes (format copied from GeoCom.request) decode to what it meant."""
    cmd = "%R1Q,2082,17:5000,1"
    framed = f"%R1Q,2082,17,{geocompy_crc16(cmd)}:5000,1\r\n".encode()
    assert codec.decode_request(framed, require_crc=True).params == ("5000", "1")


def test_wrong_or_missing_crc_is_a_checksum_error():
    with pytest.raises(codec.ChecksumError) as info:
        codec.decode_reply(b'%R1P,0,3,25803:0,"TS60"')
    assert info.value.trid == 3
    with pytest.raises(codec.ChecksumError):
        codec.decode_request(b"%R1Q,5004,3,863:")
    with pytest.raises(codec.ChecksumError):
        codec.decode_reply(b"%R1P,0,3:0", require_crc=True)
    with pytest.raises(codec.ChecksumError):
        codec.decode_request(b"%R1Q,5004,3:", require_crc=True)
    assert issubclass(codec.ChecksumError, ProtocolError)


@pytest.mark.parametrize("line", [
    b"", b"\r\n", b"%R1Q", b"%R1Q,abc,1:", b"%R1Q,1,1", b"%R1Q,1,99999:", b"%R1Q,123456,1:", b"%R1P,0,1:",
    b"%R1P,0,1:x", b'%R1P,0,0:0,"abc', b"%R1P,0,0:0,,1", b"%R1P,0,0:0, 1", b"%R1P,0,0:0,1;2", b"%R1P,0,0:0,nan",
    b"%R1P,0,0:0,1\r2", b"%R1P,0,0:0,\xb0", b"R1P,0,0:0", b"%R2P,0,0:0", b"%R1P,0,40000:0", b"?",
])
def test_malformed_lines_raise_protocol_error(line):
    for decode in (codec.decode_reply, codec.decode_request):
        with pytest.raises(ProtocolError):
            decode(line)


# ----------------------------------------------------------------------------------------- values
@pytest.mark.parametrize(("value", "digits", "text"), [
    (2.0, 15, "2.0"), (0.1, 15, "0.1"), (-0.0, 15, "0.0"), (-1e-20, 15, "0.0"), (10.0, 0, "10.0"),
    (1.23456789, 4, "1.2346"), (3.14159265358979, 15, "3.14159265358979"), (-2.5, 6, "-2.5"),
])
def test_format_float_golden(value, digits, text):
    assert codec.format_float(value, digits) == text


class _Mode(enum.Enum):
    TARGET = 1


def test_format_value_types_and_refusals():
    assert [codec.format_value(v) for v in (7, -3, True, "x y", _Mode.TARGET)] == ["7", "-3", "1", '"x y"', "1"]
    for bad in ('say "hi"', "line\nbreak", "grad°"):
        with pytest.raises(ValueError):
            codec.format_value(bad)
    for bad in (float("nan"), float("inf")):
        with pytest.raises(ValueError):
            codec.format_value(bad)
    with pytest.raises(TypeError):
        codec.format_value(b"raw")
    with pytest.raises(ValueError):
        codec.encode_request(1, trid=None, checksum=True)
    with pytest.raises(ValueError):
        codec.encode_request(1, trid=codec.MAX_TRID)


def test_parse_helpers_refuse_wrong_types():
    assert codec.parse_int("-12") == -12 and codec.parse_float("1e-3") == 0.001 and codec.parse_str('""') == ""
    for parse, token in ((codec.parse_int, "1.5"), (codec.parse_float, '"1"'), (codec.parse_str, "1"),
                         (codec.parse_float, "1e999"), (codec.parse_int, "")):
        with pytest.raises(ProtocolError):
            parse(token)


# ----------------------------------------------------------------------------------- return codes
@pytest.mark.parametrize(("code", "severity", "name"), [
    (0, codec.Severity.OK, "OK"),
    (1283, codec.Severity.WARNING, "TMC_NO_FULL_CORRECTION"),
    (1284, codec.Severity.WARNING, "TMC_ACCURACY_GUARANTEE"),
    (1285, codec.Severity.ERROR, "TMC_ANGLE_OK"),          # angles only: no usable 3D point
    (1292, codec.Severity.ERROR, "TMC_DIST_ERROR"),
    (1293, codec.Severity.ERROR, "TMC_BUSY"),
    (3077, codec.Severity.ERROR, "COM_TIMEDOUT"),
    (2, codec.Severity.ERROR, "IVPARAM"),
    (26, codec.Severity.ERROR, "NOTOK"),
    (4242, codec.Severity.ERROR, "GRC_4242"),
])
def test_classify_and_names(code, severity, name):
    assert codec.classify(code) is severity
    assert codec.code_name(code) == name


def test_busy_codes_are_errors_and_include_tmc_busy():
    assert codec.TMC_BUSY in codec.BUSY_CODES
    assert all(codec.classify(c) is codec.Severity.ERROR for c in codec.BUSY_CODES)
    assert not codec.BUSY_CODES & codec.WARNING_CODES


# ------------------------------------------------------------------------------------ line framing
def test_split_line_needs_more_then_cuts():
    assert codec.split_line(b"%R1P,0,0") == (0, None)
    assert codec.split_line(b"%R1P,0,0:0\r\n%R1") == (12, b"%R1P,0,0:0")
    assert codec.split_line(b"abc\nrest") == (4, b"abc")
    assert codec.split_line(b"\n\r\n") == (1, b"")
    with pytest.raises(ProtocolError):
        codec.split_line(b"x" * (codec.MAX_LINE_BYTES + 1))


def _lines(stream: bytes, chunk: int) -> list[bytes]:
    buf, out = bytearray(), []
    for i in range(0, len(stream), chunk):
        buf += stream[i:i + chunk]
        while True:
            used, line = codec.split_line(buf)
            if line is None:
                break
            del buf[:used]
            out.append(line)
    return out


@pytest.mark.parametrize("chunk", [1, 2, 7, 1000])
def test_split_line_is_independent_of_chunking(chunk):
    stream = b"".join(codec.encode_reply(0, (i, 0.5 * i), trid=i) for i in range(5)) + b"%R1P,0,9:"
    lines = _lines(stream, chunk)
    assert [codec.decode_reply(line).trid for line in lines] == [0, 1, 2, 3, 4]


# ------------------------------------------------------------------------------- polar convention
@pytest.mark.parametrize(("delta", "hz", "v"), [
    ((0.0, 2.0, 0.0), 0.0, math.pi / 2),               # due north, horizontal
    ((2.0, 0.0, 0.0), math.pi / 2, math.pi / 2),       # east: Hz clockwise from north
    ((0.0, -2.0, 0.0), math.pi, math.pi / 2),
    ((-2.0, 0.0, 0.0), 3 * math.pi / 2, math.pi / 2),
    ((0.0, 0.0, 2.0), 0.0, 0.0),                       # zenith
    ((1.0, 1.0, -math.sqrt(2.0)), math.pi / 4, 3 * math.pi / 4),
])
def test_polar_golden(delta, hz, v):
    got_hz, got_v, d = codec.polar_from_delta(*delta)
    assert got_hz == pytest.approx(hz, abs=1e-12)
    assert got_v == pytest.approx(v, abs=1e-12)
    assert d == pytest.approx(2.0)


_coord = st.floats(min_value=-5e4, max_value=5e4, allow_nan=False)


@given(_coord, _coord, _coord)
def test_polar_round_trip(e, n, h):
    hz, v, d = codec.polar_from_delta(e, n, h)
    assert 0.0 <= hz < 2 * math.pi and 0.0 <= v <= math.pi
    back = codec.delta_from_polar(hz, v, d)
    assert back == pytest.approx((e, n, h), abs=1e-9 * max(1.0, d))


# -------------------------------------------------------------------------------- rig convention
@pytest.mark.parametrize(("yaw", "delta_m", "rig_mm"), [
    (0.0, (1.0, 0.0, 0.0), (1010.0, 20.0, 30.0)),      # yaw 0: E = x, N = y, H = z
    (0.0, (0.0, 1.0, 0.5), (10.0, 1020.0, 530.0)),
    (90.0, (1.0, 0.0, 0.0), (10.0, 1020.0, 30.0)),     # yaw 90: E points along rig +y
    (90.0, (0.0, 1.0, 0.0), (-990.0, 20.0, 30.0)),     # ... and N along rig -x
    (180.0, (0.0, 0.0, -0.25), (10.0, 20.0, -220.0)),
])
def test_rig_frame_golden(yaw, delta_m, rig_mm):
    station = (10.0, 20.0, 30.0)
    assert instrument_to_rig(delta_m, station_xyz_mm=station, station_yaw_deg=yaw) == pytest.approx(rig_mm)
    assert rig_to_instrument(rig_mm, station_xyz_mm=station, station_yaw_deg=yaw) == pytest.approx(delta_m)


# ------------------------------------------------------------------------------------ properties
_token_values = st.one_of(
    st.integers(min_value=-(10**12), max_value=10**12),
    st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False),
    st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126, blacklist_characters='"'), max_size=20),
    st.booleans(),
)


def _same(value, token):
    if isinstance(value, bool):
        return codec.parse_int(token) == int(value)
    if isinstance(value, int):
        return codec.parse_int(token) == value
    if isinstance(value, float):
        return abs(codec.parse_float(token) - value) <= 0.6e-9 + 1e-15 * abs(value)
    return codec.parse_str(token) == value


@given(rpc=st.integers(0, 99999), trid=st.integers(0, codec.MAX_TRID - 1),
       params=st.lists(_token_values, max_size=8), checksum=st.booleans())
def test_request_round_trip(rpc, trid, params, checksum):
    frame = codec.encode_request(rpc, params, trid=trid, checksum=checksum, digits=9)
    request = codec.decode_request(frame, require_crc=checksum)
    assert (request.rpc, request.trid, len(request.params)) == (rpc, trid, len(params))
    assert all(_same(v, t) for v, t in zip(params, request.params))
    assert codec.encode_request_frame(request) == frame


@given(rc=st.integers(0, 99999), com_rc=st.integers(0, 99999), trid=st.integers(0, codec.MAX_TRID - 1),
       params=st.lists(_token_values, max_size=8), checksum=st.booleans())
def test_reply_round_trip(rc, com_rc, trid, params, checksum):
    frame = codec.encode_reply(rc, params, trid=trid, com_rc=com_rc, checksum=checksum, digits=9)
    reply = codec.decode_reply(frame, require_crc=checksum)
    assert (reply.rc, reply.com_rc, reply.trid, len(reply.params)) == (rc, com_rc, trid, len(params))
    assert all(_same(v, t) for v, t in zip(params, reply.params))
    assert codec.encode_reply_frame(reply) == frame


@settings(suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=300))
def test_arbitrary_bytes_raise_only_protocol_error(data):
    for decode in (codec.decode_request, codec.decode_reply):
        try:
            decode(data)
        except ProtocolError:
            pass
    try:
        codec.split_line(data)
    except ProtocolError:
        pass


@given(prefix=st.sampled_from([b"%R1Q,", b"%R1P,", b"%R1P,0,", b"%R1P,0,1:", b"%R1Q,1,2,3:"]),
       tail=st.binary(max_size=60))
def test_plausible_garbage_raises_only_protocol_error(prefix, tail):
    for decode in (codec.decode_request, codec.decode_reply):
        try:
            decode(prefix + tail)
        except ProtocolError:
            pass


@given(params=st.lists(st.integers(-1000, 1000), min_size=1, max_size=6), data=st.data())
def test_any_single_byte_change_in_a_checksummed_body_is_detected(params, data):
    frame = codec.encode_reply(0, params, trid=5, checksum=True).rstrip(b"\r\n")
    body_start = frame.index(b":") + 1
    pos = data.draw(st.integers(body_start, len(frame) - 1))
    new = data.draw(st.integers(0, 255).filter(lambda b: b != frame[pos]))
    corrupted = frame[:pos] + bytes([new]) + frame[pos + 1:]
    with pytest.raises(ProtocolError):
        codec.decode_reply(corrupted)
