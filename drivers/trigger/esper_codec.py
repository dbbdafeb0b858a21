"""Sans-IO codec of the ESPER-style ASCII trigger box (``docs/protocols/trigger-boxes.md``): commands and replies
as dataclasses, their newline-terminated ASCII lines, the line splitter and the bulb time. Never touches a port;
shared by the driver (:mod:`drivers.trigger.esper`) and ``simulators.trigger``.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Union

from ..errors import LimitError, ProtocolError
from .exposure import exposure_ms

TERMINATOR = b"\n"
ACK = b"tenFour"
OUTPUT_COUNT = 6
BULB_MAX_MS = 9_999_999           # seven digits
MAX_LINE = 128                    # a longer line without a terminator is garbage, not a reply in progress
BAUDRATE = 115200

# err:<code> values
ERR_UNKNOWN_COMMAND = 1
ERR_BAD_ARGUMENT = 2
ERR_NO_BULB = 3                   # 'S' before any 'b<ms>'
ERR_BUSY = 4                      # 'S' while an exposure is still running
ERR_NO_OUTPUTS = 5                # 'S' while every output is disabled: nothing would fire
ERROR_NAMES = {
    ERR_UNKNOWN_COMMAND: "UNKNOWN_COMMAND",
    ERR_BAD_ARGUMENT: "BAD_ARGUMENT",
    ERR_NO_BULB: "NO_BULB",
    ERR_BUSY: "BUSY",
    ERR_NO_OUTPUTS: "NO_OUTPUTS",
}


# --------------------------------------------------------------------------------------------- commands
@dataclass(frozen=True)
class SetMode:
    mode: int


@dataclass(frozen=True)
class EnableOutputs:
    enabled: tuple[bool, ...]     # OUTPUT_COUNT flags, output 1 first


@dataclass(frozen=True)
class SetBulb:
    ms: int


@dataclass(frozen=True)
class Fire:
    pass


@dataclass(frozen=True)
class Identify:
    pass


@dataclass(frozen=True)
class GetCount:
    pass


Command = Union[SetMode, EnableOutputs, SetBulb, Fire, Identify, GetCount]


# ---------------------------------------------------------------------------------------------- replies
@dataclass(frozen=True)
class Ack:
    pass


@dataclass(frozen=True)
class Identity:
    maker: str
    model: str
    firmware: str
    serial: str


@dataclass(frozen=True)
class ShotCount:
    count: int


@dataclass(frozen=True)
class ErrorReply:
    code: int

    @property
    def name(self) -> str:
        return ERROR_NAMES.get(self.code, "UNKNOWN")


Reply = Union[Ack, Identity, ShotCount, ErrorReply]

_ID_FIELD = re.compile(r"[\x21-\x2b\x2d-\x7e][\x20-\x2b\x2d-\x7e]*")   # printable, no comma, no leading blank
_DIGITS = re.compile(r"[0-9]{1,10}")


def _ascii_line(line: bytes, what: str) -> str:
    if line.endswith(b"\r"):
        line = line[:-1]
    try:
        text = line.decode("ascii")
    except UnicodeDecodeError:
        raise ProtocolError(f"{what} is not ASCII: {line!r}") from None
    if not text.isprintable():
        raise ProtocolError(f"{what} holds control characters: {line!r}")
    return text


def encode_command(cmd: Command) -> bytes:
    """The bytes the host sends for ``cmd``, terminator included."""
    if isinstance(cmd, SetMode):
        if not 0 <= cmd.mode <= 9:
            raise ValueError(f"mode must be a single digit 0..9, got {cmd.mode}")
        body = f"m{cmd.mode}"
    elif isinstance(cmd, EnableOutputs):
        if len(cmd.enabled) != OUTPUT_COUNT:
            raise ValueError(f"expected {OUTPUT_COUNT} output flags, got {len(cmd.enabled)}")
        body = "s" + "".join("1" if e else "0" for e in cmd.enabled)
    elif isinstance(cmd, SetBulb):
        if not 1 <= cmd.ms <= BULB_MAX_MS:
            raise ValueError(f"bulb time must be 1..{BULB_MAX_MS} ms, got {cmd.ms}")
        body = f"b{cmd.ms}"
    elif isinstance(cmd, Fire):
        body = "S"
    elif isinstance(cmd, Identify):
        body = "?"
    elif isinstance(cmd, GetCount):
        body = "c"
    else:
        raise TypeError(f"not an ESPER command: {cmd!r}")
    return body.encode("ascii") + TERMINATOR


def parse_command(line: bytes) -> Command:
    """Parse one command line (terminator removed; a trailing ``\\r`` is tolerated).

    Raises :class:`ProtocolError` for anything else; ``command_error_code`` says which ``err:`` to answer.
    """
    text = _ascii_line(line, "command")
    if text == "S":
        return Fire()
    if text == "?":
        return Identify()
    if text == "c":
        return GetCount()
    head, arg = text[:1], text[1:]
    if head == "m" and re.fullmatch(r"[0-9]", arg):
        return SetMode(int(arg))
    if head == "s" and re.fullmatch(rf"[01]{{{OUTPUT_COUNT}}}", arg):
        return EnableOutputs(tuple(ch == "1" for ch in arg))
    if head == "b" and re.fullmatch(r"[0-9]{1,7}", arg) and int(arg) >= 1:
        return SetBulb(int(arg))
    raise ProtocolError(f"not an ESPER command: {line!r}")


def command_error_code(line: bytes) -> int:
    """The ``err:`` code a box answers to a line that :func:`parse_command` refused."""
    return ERR_BAD_ARGUMENT if line[:1] in (b"m", b"s", b"b") else ERR_UNKNOWN_COMMAND


def encode_reply(reply: Reply) -> bytes:
    """The bytes the box sends for ``reply``, terminator included."""
    if isinstance(reply, Ack):
        body = ACK.decode()
    elif isinstance(reply, Identity):
        fields = (reply.maker, reply.model, reply.firmware, reply.serial)
        for f in fields:
            if not _ID_FIELD.fullmatch(f):
                raise ValueError(f"identity field {f!r} must be printable ASCII without commas")
        body = "id:" + ",".join(fields)
    elif isinstance(reply, ShotCount):
        if not 0 <= reply.count < 10 ** 10:
            raise ValueError(f"shot count out of range: {reply.count}")
        body = f"count:{reply.count}"
    elif isinstance(reply, ErrorReply):
        if not 0 <= reply.code < 10 ** 10:
            raise ValueError(f"error code out of range: {reply.code}")
        body = f"err:{reply.code}"
    else:
        raise TypeError(f"not an ESPER reply: {reply!r}")
    return body.encode("ascii") + TERMINATOR


def parse_reply(line: bytes) -> Reply:
    """Parse one reply line (terminator removed, trailing ``\\r`` tolerated); :class:`ProtocolError` otherwise."""
    text = _ascii_line(line, "reply")
    if text == ACK.decode():
        return Ack()
    if text.startswith("id:"):
        fields = text[3:].split(",")
        if len(fields) == 4 and all(_ID_FIELD.fullmatch(f) for f in fields):
            return Identity(*fields)
    elif text.startswith("count:") and _DIGITS.fullmatch(text[6:]):
        return ShotCount(int(text[6:]))
    elif text.startswith("err:") and _DIGITS.fullmatch(text[4:]):
        return ErrorReply(int(text[4:]))
    raise ProtocolError(f"unrecognized reply line {line!r}")


def split_line(buf: bytes) -> tuple[int, bytes | None]:
    """Find the first complete line in ``buf``: ``(bytes consumed, line without terminator)`` or
    ``(0, None)`` when more bytes are needed. Raises :class:`ProtocolError` when ``MAX_LINE`` bytes hold no
    terminator."""
    end = buf.find(TERMINATOR)
    if end < 0:
        if len(buf) > MAX_LINE:
            raise ProtocolError(f"no line terminator in {len(buf)} bytes: {bytes(buf[:32])!r}...")
        return 0, None
    if end > MAX_LINE:
        raise ProtocolError(f"line of {end} bytes exceeds {MAX_LINE}: {bytes(buf[:32])!r}...")
    return end + 1, bytes(buf[:end])


def decode_reply(buf: bytes) -> tuple[int, Reply | None]:
    """Sans-IO reply decoder: ``(bytes consumed, reply | None)``; empty lines are consumed and skipped.

    ``(0, None)`` means "need more bytes"; a malformed line raises :class:`ProtocolError`.
    """
    consumed = 0
    while True:
        n, line = split_line(buf[consumed:])
        if line is None:
            return consumed, None
        consumed += n
        if line in (b"", b"\r"):
            continue
        return consumed, parse_reply(line)


# ----------------------------------------------------------------------------------------------- driver
def bulb_ms_for(exposure_s: float, *, min_exposure_s: float, max_exposure_s: float) -> int:
    """Whole milliseconds for the ``b<ms>`` command; :class:`LimitError` when out of range (nothing is sent)."""
    ms = exposure_ms(exposure_s, min_exposure_s=min_exposure_s, max_exposure_s=max_exposure_s)
    if ms > BULB_MAX_MS:
        raise LimitError(f"exposure {exposure_s:g} s is {ms} ms, outside the bulb range 1..{BULB_MAX_MS} ms")
    return ms
