"""Sans-IO codec of the LED sphere's binary serial protocol (``docs/protocols/led-sphere-serial.md``).

Frame layout (all multi-byte integers little-endian)::

    +------+---------+-----+-----+-------------------+---------+
    | 0xA5 | len u16 | seq | cmd | payload (len B)   | crc u16 |
    +------+---------+-----+-----+-------------------+---------+

``crc`` is CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final XOR) over
``len .. payload`` (everything but the SOF byte and the CRC itself). A reply echoes the request's ``seq``;
an ACK's ``cmd`` is the request's ``cmd | 0x80``, a NACK's is ``0xFF`` with payload ``(cmd, code)``.

Two layers, neither touches a port:

* framing: :func:`encode_frame` and :func:`decode` (``decode(buf) -> (consumed, Frame | None)``), which
  resynchronises on garbage by dropping a candidate SOF byte whose frame does not validate;
* messages: one frozen dataclass per command and reply, :func:`encode` (message -> frame bytes) and
  :func:`parse_request` / :func:`parse_reply` (frame -> message), which raise only
  :class:`~drivers.errors.ProtocolError` (:class:`MalformedMessage` carries the NACK code a device answers).

The driver (:mod:`drivers.led_sphere.driver`) and the simulator (``simulators.led_sphere``) share this module;
golden frames in the protocol document anchor both to the specification.
"""
from __future__ import annotations

import binascii
import enum
import struct
from dataclasses import dataclass
from typing import Callable, ClassVar, Union

import numpy as np
import numpy.typing as npt

from ..errors import ProtocolError

SOF = 0xA5
HEADER_LEN = 5                 # SOF, len lo, len hi, seq, cmd
CRC_LEN = 2
OVERHEAD = HEADER_LEN + CRC_LEN
MAX_PAYLOAD = 1000             # a longer declared length is not a frame: the SOF byte was garbage
MAX_FRAME = MAX_PAYLOAD + OVERHEAD
ACK_FLAG = 0x80
NACK = 0xFF                    # cmd byte of every NACK reply
CHANNELS = 3
FULL_SCALE = 65535
DARK_SLOT = 0xFF               # SELECT_SLOT argument meaning "no slot: dark"; STATUS active slot when dark
UPLOAD_HEADER_LEN = 5          # slot u8, offset u16, count u16
MAX_UPLOAD_LEDS = (MAX_PAYLOAD - UPLOAD_HEADER_LEN) // (2 * CHANNELS)   # 165 LEDs per UPLOAD_PATTERN frame
MAX_STRING = 64                # IDENTIFY strings


class Command(enum.IntEnum):
    """Request command bytes (``cmd``); the ACK uses ``cmd | 0x80``."""

    IDENTIFY = 0x01
    STATUS = 0x02
    UPLOAD_PATTERN = 0x10
    SELECT_SLOT = 0x11
    SET_POLARIZATION = 0x12
    ALL_OFF = 0x13
    WATCHDOG = 0x14


class NackCode(enum.IntEnum):
    """Error codes carried by a NACK."""

    BAD_CRC = 1            # a frame arrived whole but its CRC failed (the command was not executed)
    UNKNOWN_COMMAND = 2
    BAD_LENGTH = 3         # payload length wrong for the command
    BAD_SLOT = 4           # slot number out of range
    OVER_POWER_LIMIT = 5   # the selected pattern would draw more than the device's current limit
    OVER_TEMPERATURE = 6   # refusing to light while the over-temperature interlock is tripped
    BUSY = 7               # try again later
    BAD_ARGUMENT = 8       # a field out of range (polarization value, LED range beyond the LED count)


class FaultFlag(enum.IntFlag):
    """STATUS ``faults`` bits."""

    OVER_TEMPERATURE = 0x0001
    WATCHDOG_TRIPPED = 0x0002
    LED_FAULT = 0x0004


def nack_name(code: int) -> str:
    try:
        return NackCode(code).name
    except ValueError:
        return f"CODE_{code}"


class MalformedMessage(ProtocolError):
    """A frame with a valid CRC whose command or payload is invalid; ``nack_code`` is what a device answers."""

    def __init__(self, message: str, nack_code: NackCode) -> None:
        super().__init__(message)
        self.nack_code = nack_code


# ------------------------------------------------------------------------------------------------ CRC
def crc16_ccitt_false(data: bytes | bytearray | memoryview, init: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, MSB first, no final XOR; ``b"123456789"`` -> 0x29B1.

    ``binascii.crc_hqx`` is exactly this CRC with a caller-supplied initial value.
    """
    return binascii.crc_hqx(bytes(data), init)


# -------------------------------------------------------------------------------------------- framing
@dataclass(frozen=True)
class Frame:
    """One validated frame: the CRC matched. ``payload`` may still be malformed for ``cmd``."""

    seq: int
    cmd: int
    payload: bytes = b""


@dataclass(frozen=True)
class CorruptFrame:
    """A complete candidate frame whose CRC failed (reported through ``decode(..., on_corrupt=)``).

    ``seq`` and ``cmd`` are as received and may themselves be corrupted.
    """

    seq: int
    cmd: int
    length: int


def encode_frame(seq: int, cmd: int, payload: bytes = b"") -> bytes:
    """Frame ``payload``; ``ValueError`` if a field is out of range (a programming error, not wire data)."""
    if not 0 <= seq <= 0xFF:
        raise ValueError(f"seq must be 0..255, got {seq}")
    if not 0 <= cmd <= 0xFF:
        raise ValueError(f"cmd must be 0..255, got {cmd}")
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes exceeds MAX_PAYLOAD={MAX_PAYLOAD}")
    body = struct.pack("<HBB", len(payload), seq, cmd) + bytes(payload)
    return bytes([SOF]) + body + struct.pack("<H", crc16_ccitt_false(body))


def decode(buf: bytes | bytearray | memoryview, *, final: bool = False,
           on_corrupt: Callable[[CorruptFrame], None] | None = None) -> tuple[int, Frame | None]:
    """Find the next valid frame in ``buf``.

    Returns ``(consumed, frame)``: drop ``buf[:consumed]`` (garbage skipped, plus the frame if one was found).
    ``frame is None`` means "need more bytes": what is left in ``buf[consumed:]`` is empty or the beginning
    of a candidate frame. Resynchronisation: a byte that is not SOF is skipped; a SOF whose declared length
    exceeds :data:`MAX_PAYLOAD`, or whose complete frame fails the CRC, is dropped (that single byte) and
    the scan goes on from the next byte, so a real frame behind a false SOF is never lost.

    ``final=True`` says no more bytes will follow the current candidate (the line went idle; a device's
    inter-byte timeout): an incomplete candidate is then dropped like a bad one instead of waited for.
    ``on_corrupt`` is called with each complete candidate whose CRC failed (a device NACKs those).
    Never raises on any content of ``buf``.
    """
    data = bytes(buf)
    n = len(data)
    i = 0
    while True:
        i = data.find(SOF, i)
        if i < 0:
            return n, None
        if n - i < HEADER_LEN:
            if final:
                i += 1
                continue
            return i, None
        length = data[i + 1] | (data[i + 2] << 8)
        if length > MAX_PAYLOAD:
            i += 1
            continue
        end = i + HEADER_LEN + length + CRC_LEN
        if end > n:
            if final:
                i += 1
                continue
            return i, None
        body = data[i + 1:end - CRC_LEN]
        crc = data[end - 2] | (data[end - 1] << 8)
        if crc16_ccitt_false(body) != crc:
            if on_corrupt is not None:
                on_corrupt(CorruptFrame(seq=data[i + 3], cmd=data[i + 4], length=length))
            i += 1
            continue
        return end, Frame(seq=data[i + 3], cmd=data[i + 4], payload=data[i + HEADER_LEN:end - CRC_LEN])


def decode_all(buf: bytes | bytearray, *, final: bool = False) -> tuple[list[Frame], bytes]:
    """Decode every frame in ``buf``; return the frames and the undecoded rest (a partial frame)."""
    frames: list[Frame] = []
    rest = bytes(buf)
    while rest:
        consumed, frame = decode(rest, final=final)
        rest = rest[consumed:]
        if frame is None:
            break
        frames.append(frame)
    return frames, rest


# ------------------------------------------------------------------------------------------- messages
def _u8(name: str, v: int) -> None:
    if not isinstance(v, (int, np.integer)) or not 0 <= v <= 0xFF:
        raise ValueError(f"{name} must be an integer 0..255, got {v!r}")


def _u16(name: str, v: int) -> None:
    if not isinstance(v, (int, np.integer)) or not 0 <= v <= 0xFFFF:
        raise ValueError(f"{name} must be an integer 0..65535, got {v!r}")


def _ascii(name: str, s: str) -> bytes:
    try:
        b = s.encode("ascii")
    except (UnicodeEncodeError, AttributeError) as exc:
        raise ValueError(f"{name} must be an ASCII string, got {s!r}") from exc
    if len(b) > MAX_STRING:
        raise ValueError(f"{name} longer than {MAX_STRING} bytes: {s!r}")
    return b


def _expect_len(what: str, payload: bytes, n: int) -> None:
    if len(payload) != n:
        raise MalformedMessage(f"{what}: expected a {n}-byte payload, got {len(payload)}", NackCode.BAD_LENGTH)


# requests --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Identify:
    """IDENTIFY: empty payload; answered by :class:`IdentifyReply`."""

    CMD: ClassVar[int] = Command.IDENTIFY

    def payload(self) -> bytes:
        return b""


@dataclass(frozen=True)
class Status:
    """STATUS: empty payload; answered by :class:`StatusReply`."""

    CMD: ClassVar[int] = Command.STATUS

    def payload(self) -> bytes:
        return b""


@dataclass(frozen=True)
class UploadPattern:
    """UPLOAD_PATTERN: LEDs ``offset .. offset+count-1`` of pattern ``slot``.

    ``data`` is the raw little-endian u16 (R, G, B) triplets, ``count * 6`` bytes; use :meth:`from_array`
    and :meth:`to_array` to convert from/to a (count, 3) uint16 array.
    """

    CMD: ClassVar[int] = Command.UPLOAD_PATTERN
    slot: int
    offset: int
    data: bytes

    def __post_init__(self) -> None:
        _u8("slot", self.slot)
        _u16("offset", self.offset)
        if len(self.data) % (2 * CHANNELS):
            raise ValueError(f"data must hold whole (R, G, B) u16 triplets, got {len(self.data)} bytes")
        if self.count > MAX_UPLOAD_LEDS:
            raise ValueError(f"at most {MAX_UPLOAD_LEDS} LEDs per UPLOAD_PATTERN frame, got {self.count}")

    @property
    def count(self) -> int:
        return len(self.data) // (2 * CHANNELS)

    @classmethod
    def from_array(cls, slot: int, offset: int, rgb16: npt.NDArray[np.uint16]) -> "UploadPattern":
        a = np.asarray(rgb16)
        if a.ndim != 2 or a.shape[1] != CHANNELS or a.dtype != np.uint16:
            raise ValueError(f"expected a (count, 3) uint16 array, got shape {a.shape} dtype {a.dtype}")
        return cls(slot, offset, a.astype("<u2", copy=False).tobytes())

    def to_array(self) -> npt.NDArray[np.uint16]:
        return np.frombuffer(self.data, dtype="<u2").reshape(self.count, CHANNELS).astype(np.uint16)

    def payload(self) -> bytes:
        return struct.pack("<BHH", self.slot, self.offset, self.count) + self.data


@dataclass(frozen=True)
class SelectSlot:
    """SELECT_SLOT: light pattern ``slot``; ``DARK_SLOT`` (0xFF) darkens the sphere."""

    CMD: ClassVar[int] = Command.SELECT_SLOT
    slot: int

    def __post_init__(self) -> None:
        _u8("slot", self.slot)

    def payload(self) -> bytes:
        return bytes([self.slot])


@dataclass(frozen=True)
class SetPolarization:
    """SET_POLARIZATION: 0 none, 1 parallel, 2 cross (``drivers.contracts.Polarization``)."""

    CMD: ClassVar[int] = Command.SET_POLARIZATION
    state: int

    def __post_init__(self) -> None:
        _u8("state", self.state)

    def payload(self) -> bytes:
        return bytes([self.state])


@dataclass(frozen=True)
class AllOff:
    """ALL_OFF: darken every LED (as SELECT_SLOT 0xFF) and clear the watchdog-tripped fault bit."""

    CMD: ClassVar[int] = Command.ALL_OFF

    def payload(self) -> bytes:
        return b""


@dataclass(frozen=True)
class SetWatchdog:
    """WATCHDOG: ``timeout_ms`` (0 disables). Any valid frame feeds it; on expiry the sphere goes dark."""

    CMD: ClassVar[int] = Command.WATCHDOG
    timeout_ms: int

    def __post_init__(self) -> None:
        _u16("timeout_ms", self.timeout_ms)

    def payload(self) -> bytes:
        return struct.pack("<H", self.timeout_ms)


Request = Union[Identify, Status, UploadPattern, SelectSlot, SetPolarization, AllOff, SetWatchdog]
REQUEST_TYPES: dict[int, type] = {t.CMD: t for t in
                                  (Identify, Status, UploadPattern, SelectSlot, SetPolarization, AllOff,
                                   SetWatchdog)}


# replies ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class IdentifyReply:
    """ACK of IDENTIFY: ``led_count u16, channels u8, slot_count u8`` then three length-prefixed ASCII
    strings (``len u8`` + bytes): model, firmware, serial number."""

    CMD: ClassVar[int] = Command.IDENTIFY | ACK_FLAG
    led_count: int
    channels: int
    slot_count: int
    model: str
    firmware: str
    serial_number: str

    def __post_init__(self) -> None:
        _u16("led_count", self.led_count)
        _u8("channels", self.channels)
        _u8("slot_count", self.slot_count)
        for name in ("model", "firmware", "serial_number"):
            _ascii(name, getattr(self, name))

    def payload(self) -> bytes:
        out = bytearray(struct.pack("<HBB", self.led_count, self.channels, self.slot_count))
        for s in (self.model, self.firmware, self.serial_number):
            b = s.encode("ascii")
            out += bytes([len(b)]) + b
        return bytes(out)


@dataclass(frozen=True)
class StatusReply:
    """ACK of STATUS: ``temperature i16 (centi-degC), current u16 (mA), faults u16, active_slot u8
    (0xFF = dark), polarization u8, lit u8 (0/1)``: 9 bytes."""

    CMD: ClassVar[int] = Command.STATUS | ACK_FLAG
    temperature_centi_c: int
    current_ma: int
    faults: int
    active_slot: int
    polarization: int
    lit: bool

    def __post_init__(self) -> None:
        if not isinstance(self.temperature_centi_c, (int, np.integer)) or \
                not -32768 <= self.temperature_centi_c <= 32767:
            raise ValueError(f"temperature_centi_c must fit an i16, got {self.temperature_centi_c!r}")
        _u16("current_ma", self.current_ma)
        _u16("faults", self.faults)
        _u8("active_slot", self.active_slot)
        _u8("polarization", self.polarization)

    def payload(self) -> bytes:
        return struct.pack("<hHHBBB", self.temperature_centi_c, self.current_ma, self.faults,
                           self.active_slot, self.polarization, 1 if self.lit else 0)


@dataclass(frozen=True)
class UploadAck:
    """ACK of UPLOAD_PATTERN: echoes ``slot u8, offset u16, count u16``."""

    CMD: ClassVar[int] = Command.UPLOAD_PATTERN | ACK_FLAG
    slot: int
    offset: int
    count: int

    def __post_init__(self) -> None:
        _u8("slot", self.slot)
        _u16("offset", self.offset)
        _u16("count", self.count)

    def payload(self) -> bytes:
        return struct.pack("<BHH", self.slot, self.offset, self.count)


@dataclass(frozen=True)
class SelectAck:
    """ACK of SELECT_SLOT: echoes ``slot u8``."""

    CMD: ClassVar[int] = Command.SELECT_SLOT | ACK_FLAG
    slot: int

    def __post_init__(self) -> None:
        _u8("slot", self.slot)

    def payload(self) -> bytes:
        return bytes([self.slot])


@dataclass(frozen=True)
class PolarizationAck:
    """ACK of SET_POLARIZATION: echoes ``state u8``."""

    CMD: ClassVar[int] = Command.SET_POLARIZATION | ACK_FLAG
    state: int

    def __post_init__(self) -> None:
        _u8("state", self.state)

    def payload(self) -> bytes:
        return bytes([self.state])


@dataclass(frozen=True)
class AllOffAck:
    """ACK of ALL_OFF: empty payload."""

    CMD: ClassVar[int] = Command.ALL_OFF | ACK_FLAG

    def payload(self) -> bytes:
        return b""


@dataclass(frozen=True)
class WatchdogAck:
    """ACK of WATCHDOG: echoes ``timeout_ms u16``."""

    CMD: ClassVar[int] = Command.WATCHDOG | ACK_FLAG
    timeout_ms: int

    def __post_init__(self) -> None:
        _u16("timeout_ms", self.timeout_ms)

    def payload(self) -> bytes:
        return struct.pack("<H", self.timeout_ms)


@dataclass(frozen=True)
class Nack:
    """NACK (cmd 0xFF): ``cmd u8`` (the refused command as received) and ``code u8`` (:class:`NackCode`)."""

    CMD: ClassVar[int] = NACK
    cmd: int
    code: int

    def __post_init__(self) -> None:
        _u8("cmd", self.cmd)
        _u8("code", self.code)

    def payload(self) -> bytes:
        return bytes([self.cmd, self.code])


Reply = Union[IdentifyReply, StatusReply, UploadAck, SelectAck, PolarizationAck, AllOffAck, WatchdogAck, Nack]
REPLY_TYPES: dict[int, type] = {t.CMD: t for t in
                                (IdentifyReply, StatusReply, UploadAck, SelectAck, PolarizationAck, AllOffAck,
                                 WatchdogAck, Nack)}
Message = Union[Request, Reply]


def encode(seq: int, message: Message) -> bytes:
    """The complete frame carrying ``message`` with sequence number ``seq``."""
    return encode_frame(seq, message.CMD, message.payload())


def parse_request(frame: Frame) -> Request:
    """The request carried by a host->device ``frame``; :class:`MalformedMessage` if invalid."""
    cmd, p = frame.cmd, frame.payload
    if cmd == Command.IDENTIFY:
        _expect_len("IDENTIFY", p, 0)
        return Identify()
    if cmd == Command.STATUS:
        _expect_len("STATUS", p, 0)
        return Status()
    if cmd == Command.ALL_OFF:
        _expect_len("ALL_OFF", p, 0)
        return AllOff()
    if cmd == Command.SELECT_SLOT:
        _expect_len("SELECT_SLOT", p, 1)
        return SelectSlot(p[0])
    if cmd == Command.SET_POLARIZATION:
        _expect_len("SET_POLARIZATION", p, 1)
        return SetPolarization(p[0])
    if cmd == Command.WATCHDOG:
        _expect_len("WATCHDOG", p, 2)
        return SetWatchdog(struct.unpack_from("<H", p)[0])
    if cmd == Command.UPLOAD_PATTERN:
        if len(p) < UPLOAD_HEADER_LEN:
            raise MalformedMessage(f"UPLOAD_PATTERN: payload of {len(p)} bytes is shorter than its "
                                   f"{UPLOAD_HEADER_LEN}-byte header", NackCode.BAD_LENGTH)
        slot, offset, count = struct.unpack_from("<BHH", p)
        _expect_len(f"UPLOAD_PATTERN of {count} LEDs", p, UPLOAD_HEADER_LEN + count * 2 * CHANNELS)
        if count > MAX_UPLOAD_LEDS:   # unreachable while MAX_PAYLOAD bounds the frame; kept explicit
            raise MalformedMessage(f"UPLOAD_PATTERN: {count} LEDs > {MAX_UPLOAD_LEDS}", NackCode.BAD_LENGTH)
        return UploadPattern(slot, offset, bytes(p[UPLOAD_HEADER_LEN:]))
    raise MalformedMessage(f"unknown command 0x{cmd:02X}", NackCode.UNKNOWN_COMMAND)


def _string(p: bytes, i: int, what: str) -> tuple[str, int]:
    if i >= len(p):
        raise MalformedMessage(f"IDENTIFY reply truncated before {what}", NackCode.BAD_LENGTH)
    n = p[i]
    if i + 1 + n > len(p):
        raise MalformedMessage(f"IDENTIFY reply truncated inside {what}", NackCode.BAD_LENGTH)
    if n > MAX_STRING:
        raise MalformedMessage(f"IDENTIFY reply: {what} of {n} bytes > {MAX_STRING}", NackCode.BAD_LENGTH)
    raw = p[i + 1:i + 1 + n]
    try:
        return raw.decode("ascii"), i + 1 + n
    except UnicodeDecodeError as exc:
        raise MalformedMessage(f"IDENTIFY reply: {what} is not ASCII: {raw!r}", NackCode.BAD_ARGUMENT) from exc


def parse_reply(frame: Frame) -> Reply:
    """The reply carried by a device->host ``frame``; :class:`MalformedMessage` if invalid."""
    cmd, p = frame.cmd, frame.payload
    if cmd == NACK:
        _expect_len("NACK", p, 2)
        return Nack(p[0], p[1])
    if cmd == Command.IDENTIFY | ACK_FLAG:
        if len(p) < 4:
            raise MalformedMessage(f"IDENTIFY reply of {len(p)} bytes is shorter than 4", NackCode.BAD_LENGTH)
        led_count, channels, slot_count = struct.unpack_from("<HBB", p)
        i = 4
        model, i = _string(p, i, "model")
        firmware, i = _string(p, i, "firmware")
        serial_number, i = _string(p, i, "serial number")
        if i != len(p):
            raise MalformedMessage(f"IDENTIFY reply has {len(p) - i} trailing bytes", NackCode.BAD_LENGTH)
        return IdentifyReply(led_count, channels, slot_count, model, firmware, serial_number)
    if cmd == Command.STATUS | ACK_FLAG:
        _expect_len("STATUS reply", p, 9)
        t, ma, faults, slot, pol, lit = struct.unpack("<hHHBBB", p)
        if lit > 1:
            raise MalformedMessage(f"STATUS reply: lit flag {lit} is not 0/1", NackCode.BAD_ARGUMENT)
        return StatusReply(t, ma, faults, slot, pol, bool(lit))
    if cmd == Command.UPLOAD_PATTERN | ACK_FLAG:
        _expect_len("UPLOAD_PATTERN reply", p, 5)
        return UploadAck(*struct.unpack("<BHH", p))
    if cmd == Command.SELECT_SLOT | ACK_FLAG:
        _expect_len("SELECT_SLOT reply", p, 1)
        return SelectAck(p[0])
    if cmd == Command.SET_POLARIZATION | ACK_FLAG:
        _expect_len("SET_POLARIZATION reply", p, 1)
        return PolarizationAck(p[0])
    if cmd == Command.ALL_OFF | ACK_FLAG:
        _expect_len("ALL_OFF reply", p, 0)
        return AllOffAck()
    if cmd == Command.WATCHDOG | ACK_FLAG:
        _expect_len("WATCHDOG reply", p, 2)
        return WatchdogAck(struct.unpack("<H", p)[0])
    raise MalformedMessage(f"unknown reply command 0x{cmd:02X}", NackCode.UNKNOWN_COMMAND)
