"""Sans-IO codec for Leica GeoCOM ASCII requests and replies (see ``docs/protocols/geocom.md``).

Wire format (one frame per line, terminated by CR LF)::

    request  %R1Q,<rpc>[,<trid>[,<crc>]]:<p0>,<p1>,...
    reply    %R1P,<com_rc>,<trid>[,<crc>]:<rc>,<p0>,<p1>,...

``<crc>`` is the decimal CRC-16/ARC of the frame text *without* the ``,<crc>`` field and without the
terminator. Parameters are decimal integers, fixed-point decimals (angles in radians, lengths in metres)
or double-quoted strings. A bare ``c`` line aborts a running motorized function and is answered ``?``.

Nothing here touches a port: :func:`split_line` cuts complete lines off a receive buffer, the
``encode_*`` functions build frames, the ``decode_*`` functions parse one line or raise
:class:`~drivers.errors.ProtocolError`. The return-code table classifies codes as OK, WARNING (the result
is still usable) or ERROR; the driver turns them into exceptions.

The codec also owns the instrument's polar convention (:func:`polar_from_delta`, :func:`delta_from_polar`):
Hz is the azimuth, clockwise from +N towards +E; V is the zenith angle (0 = up, pi/2 = horizontal in face I).
"""
from __future__ import annotations

import enum
import math
import re
from dataclasses import dataclass
from typing import Iterable

from ..errors import ProtocolError

TERMINATOR = b"\r\n"
ABORT_REQUEST = b"c"
ABORT_REPLY = b"?"
MAX_TRID = 2**15            # transaction ids count up modulo 2**15
MAX_LINE_BYTES = 4096       # a longer line without terminator is garbage
DEFAULT_DIGITS = 15         # COM_GetDoublePrecision default


class ChecksumError(ProtocolError):
    """A frame's CRC field does not match its contents (``trid`` is the frame's id when it was readable)."""

    def __init__(self, message: str, trid: int | None = None) -> None:
        super().__init__(message)
        self.trid = trid


# --------------------------------------------------------------------------------------------------
# Return codes
# --------------------------------------------------------------------------------------------------

class Severity(enum.Enum):
    """What a return code means for the caller."""

    OK = "ok"
    WARNING = "warning"   # the result is valid but carries a caveat (e.g. accuracy not guaranteed)
    ERROR = "error"


OK = 0
UNDEFINED = 1
IVPARAM = 2
NOT_IMPL = 5
ABORT = 8
SYSBUSY = 13
NOTOK = 26
EDM_BUSY = 786
TMC_NO_FULL_CORRECTION = 1283
TMC_ACCURACY_GUARANTEE = 1284
TMC_ANGLE_OK = 1285
TMC_ANGLE_ERROR = 1290
TMC_DIST_ERROR = 1292
TMC_BUSY = 1293
TMC_SIGNAL_ERROR = 1294
MOT_BUSY = 1793
COM_CANT_DECODE = 3074
COM_CANT_SEND = 3075
COM_TIMEDOUT = 3077
COM_CANT_DECODE_REQ = 3080
COM_PROC_UNAVAIL = 3081
COM_FAILED = 3085
COM_TR_ID_MISMATCH = 3093
COM_SRVR_RX_CHECKSUM_ERROR = 3101
COM_CLNT_RX_CHECKSUM_ERROR = 3102
COM_NO_CHECKSUM = 3110
AUT_TIMEOUT = 8704
AUT_ANGLE_ERROR = 8706
AUT_MOTOR_ERROR = 8707
AUT_NO_TARGET = 8710
AUT_MULTIPLE_TARGETS = 8711

#: Names of the codes this project meets (GeoCOM reference manual names without the ``GRC_`` prefix).
RETURN_CODES: dict[int, str] = {
    OK: "OK",
    UNDEFINED: "UNDEFINED",
    IVPARAM: "IVPARAM",
    3: "IVRESULT",
    4: "FATAL",
    NOT_IMPL: "NOT_IMPL",
    6: "TIME_OUT",
    7: "SET_INCOMPL",
    ABORT: "ABORT",
    9: "NOMEMORY",
    10: "NOTINIT",
    12: "SHUT_DOWN",
    SYSBUSY: "SYSBUSY",
    14: "HWFAILURE",
    16: "LOW_POWER",
    18: "BATT_EMPTY",
    21: "OUT_OF_TEMP",
    22: "INSTRUMENT_TILT",
    25: "SLEEP_MODE",
    NOTOK: "NOTOK",
    27: "NA",
    EDM_BUSY: "EDM_BUSY",
    770: "EDM_NOSIGNAL",
    TMC_NO_FULL_CORRECTION: "TMC_NO_FULL_CORRECTION",
    TMC_ACCURACY_GUARANTEE: "TMC_ACCURACY_GUARANTEE",
    TMC_ANGLE_OK: "TMC_ANGLE_OK",
    1288: "TMC_ANGLE_NO_FULL_CORRECTION",
    1289: "TMC_ANGLE_ACCURACY_GUARANTEE",
    TMC_ANGLE_ERROR: "TMC_ANGLE_ERROR",
    1291: "TMC_DIST_PPM",
    TMC_DIST_ERROR: "TMC_DIST_ERROR",
    TMC_BUSY: "TMC_BUSY",
    TMC_SIGNAL_ERROR: "TMC_SIGNAL_ERROR",
    MOT_BUSY: "MOT_BUSY",
    3072: "COM_ERO",
    3073: "COM_CANT_ENCODE",
    COM_CANT_DECODE: "COM_CANT_DECODE",
    COM_CANT_SEND: "COM_CANT_SEND",
    3076: "COM_CANT_RECV",
    COM_TIMEDOUT: "COM_TIMEDOUT",
    3078: "COM_WRONG_FORMAT",
    3079: "COM_VER_MISMATCH",
    COM_CANT_DECODE_REQ: "COM_CANT_DECODE_REQ",
    COM_PROC_UNAVAIL: "COM_PROC_UNAVAIL",
    3082: "COM_CANT_ENCODE_REP",
    3083: "COM_SYSTEM_ERR",
    COM_FAILED: "COM_FAILED",
    COM_TR_ID_MISMATCH: "COM_TR_ID_MISMATCH",
    3094: "COM_NOT_GEOCOM",
    COM_SRVR_RX_CHECKSUM_ERROR: "COM_SRVR_RX_CHECKSUM_ERROR",
    COM_CLNT_RX_CHECKSUM_ERROR: "COM_CLNT_RX_CHECKSUM_ERROR",
    COM_NO_CHECKSUM: "COM_NO_CHECKSUM",
    AUT_TIMEOUT: "AUT_TIMEOUT",
    8705: "AUT_DETENT_ERROR",
    AUT_ANGLE_ERROR: "AUT_ANGLE_ERROR",
    AUT_MOTOR_ERROR: "AUT_MOTOR_ERROR",
    8708: "AUT_INCACC",
    8709: "AUT_DEV_ERROR",
    AUT_NO_TARGET: "AUT_NO_TARGET",
    AUT_MULTIPLE_TARGETS: "AUT_MULTIPLE_TARGETS",
    8712: "AUT_BAD_ENVIRONMENT",
    8714: "AUT_NOT_ENABLED",
    8716: "AUT_ACCURACY",
}

#: Codes whose result is still usable (coordinates valid, accuracy or correction caveat).
WARNING_CODES: frozenset[int] = frozenset({TMC_NO_FULL_CORRECTION, TMC_ACCURACY_GUARANTEE})
#: Error codes that mean "busy, retry later" (raised as DeviceBusy by the driver).
BUSY_CODES: frozenset[int] = frozenset({SYSBUSY, EDM_BUSY, TMC_BUSY, MOT_BUSY})


def code_name(code: int) -> str:
    """The GeoCOM name of ``code`` (``"GRC_<n>"`` for codes outside :data:`RETURN_CODES`)."""
    return RETURN_CODES.get(code, f"GRC_{code}")


def classify(code: int) -> Severity:
    """OK for 0, WARNING for :data:`WARNING_CODES` (1283, 1284), ERROR for everything else."""
    if code == OK:
        return Severity.OK
    if code in WARNING_CODES:
        return Severity.WARNING
    return Severity.ERROR


# --------------------------------------------------------------------------------------------------
# CRC
# --------------------------------------------------------------------------------------------------

def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC_TABLE = _crc_table()


def crc16_arc(data: bytes | str) -> int:
    """CRC-16/ARC (poly 0x8005 reflected, init 0, no final xor): ``crc16_arc(b"123456789") == 0xBB3D``."""
    if isinstance(data, str):
        data = data.encode("ascii")
    crc = 0
    for byte in data:
        crc = _CRC_TABLE[(crc ^ byte) & 0xFF] ^ (crc >> 8)
    return crc


# --------------------------------------------------------------------------------------------------
# Values
# --------------------------------------------------------------------------------------------------

Value = int | float | str | bool | enum.Enum

_INT_RE = re.compile(r"[+-]?[0-9]{1,15}")
_FLOAT_RE = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]{1,3})?")
_STR_RE = re.compile(r'"[^"\r\n]*"')
_TOKEN_RE = re.compile(_FLOAT_RE.pattern + r'|"[^"\r\n]*"' + r"|'[0-9A-Fa-f]{1,16}'", re.ASCII)


def format_float(value: float, digits: int = DEFAULT_DIGITS) -> str:
    """Fixed-point text with at most ``digits`` decimals, trailing zeros stripped (``1.5``, ``2.0``)."""
    if not math.isfinite(value):
        raise ValueError(f"GeoCOM cannot carry a non-finite number: {value!r}")
    if not 0 <= digits <= 17:
        raise ValueError(f"digits must be 0..17, got {digits}")
    text = f"{value:.{digits}f}"
    text = text.rstrip("0") if "." in text else text + "."
    if text.endswith("."):
        text += "0"
    if text in ("-0.0", "-0"):
        text = "0.0"
    return text


def format_value(value: Value, digits: int = DEFAULT_DIGITS) -> str:
    """One parameter as it appears on the wire: ints and bools as decimal, floats fixed-point,
    strings double-quoted (no quotes, CR, LF or non-ASCII inside), int-valued enums by value."""
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, enum.Enum):
        if not isinstance(value.value, int):
            raise TypeError(f"enum parameter {value!r} has a non-integer value")
        return f"{int(value.value):d}"
    if isinstance(value, int):
        return f"{value:d}"
    if isinstance(value, float):
        return format_float(value, digits)
    if isinstance(value, str):
        if not value.isascii() or any(c in value for c in '"\r\n'):
            raise ValueError(f"GeoCOM string parameter must be ASCII without quotes or line breaks: {value!r}")
        return f'"{value}"'
    raise TypeError(f"unsupported GeoCOM parameter type {type(value).__name__}")


def parse_int(token: str) -> int:
    """A decimal integer parameter, or :class:`ProtocolError`."""
    if not _INT_RE.fullmatch(token):
        raise ProtocolError(f"expected an integer, got {token!r}")
    return int(token)


def parse_float(token: str) -> float:
    """A decimal (fixed or exponent notation) parameter, or :class:`ProtocolError`."""
    if not _FLOAT_RE.fullmatch(token):
        raise ProtocolError(f"expected a number, got {token!r}")
    value = float(token)
    if not math.isfinite(value):
        raise ProtocolError(f"number out of range: {token!r}")
    return value


def parse_str(token: str) -> str:
    """A double-quoted string parameter (quotes removed), or :class:`ProtocolError`."""
    if not _STR_RE.fullmatch(token):
        raise ProtocolError(f"expected a quoted string, got {token!r}")
    return token[1:-1]


def split_params(text: str) -> tuple[str, ...]:
    """Split a parameter list on commas outside double quotes; empty text -> ``()``. Every token must be a
    decimal number, a double-quoted string or a single-quoted hex value (``'1F'``), else ProtocolError."""
    if text == "":
        return ()
    tokens: list[str] = []
    current: list[str] = []
    quoted = False
    for ch in text:
        if ch == '"':
            quoted = not quoted
            current.append(ch)
        elif ch == "," and not quoted:
            tokens.append("".join(current))
            current = []
        else:
            current.append(ch)
    if quoted:
        raise ProtocolError(f"unterminated string in parameters {text!r}")
    tokens.append("".join(current))
    for token in tokens:
        if not _TOKEN_RE.fullmatch(token):
            raise ProtocolError(f"parameter {token[:40]!r} is not a number, quoted string or hex byte in {text[:80]!r}")
    return tuple(tokens)


# --------------------------------------------------------------------------------------------------
# Frames
# --------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Request:
    """``%R1Q`` frame. ``params`` are the raw wire tokens (strings keep their quotes); ``trid`` is None
    when the frame omitted it (the instrument then answers with id 0); ``crc`` is None without checksum."""

    rpc: int
    params: tuple[str, ...] = ()
    trid: int | None = 0
    crc: int | None = None


@dataclass(frozen=True)
class Reply:
    """``%R1P`` frame: ``com_rc`` is the communication layer's code, ``rc`` the RPC's own return code."""

    rc: int
    params: tuple[str, ...] = ()
    trid: int = 0
    com_rc: int = 0
    crc: int | None = None

    @property
    def code(self) -> int:
        """The code that decides the outcome: ``com_rc`` when the COM layer failed, else ``rc``."""
        return self.com_rc if self.com_rc != OK else self.rc


def _check_trid(trid: int) -> None:
    if not 0 <= trid < MAX_TRID:
        raise ValueError(f"transaction id must be 0..{MAX_TRID - 1}, got {trid}")


def _with_crc(head: str, body: str, checksum: bool) -> str:
    frame = f"{head}:{body}"
    if checksum:
        return f"{head},{crc16_arc(frame)}:{body}"
    return frame


def encode_request(rpc: int, params: Iterable[Value] = (), *, trid: int | None = 0, checksum: bool = False,
                   digits: int = DEFAULT_DIGITS) -> bytes:
    """``%R1Q,<rpc>,<trid>[,<crc>]:<params>\\r\\n``. ``trid=None`` omits the id (not allowed with a CRC)."""
    if not 0 <= rpc <= 99999:
        raise ValueError(f"RPC number must be 0..99999, got {rpc}")
    body = ",".join(format_value(p, digits) for p in params)
    if trid is None:
        if checksum:
            raise ValueError("a checksummed request needs a transaction id")
        head = f"%R1Q,{rpc}"
    else:
        _check_trid(trid)
        head = f"%R1Q,{rpc},{trid}"
    return _with_crc(head, body, checksum).encode("ascii") + TERMINATOR


def encode_reply(rc: int, params: Iterable[Value] = (), *, trid: int = 0, com_rc: int = OK,
                 checksum: bool = False, digits: int = DEFAULT_DIGITS) -> bytes:
    """``%R1P,<com_rc>,<trid>[,<crc>]:<rc>,<params>\\r\\n``."""
    _check_trid(trid)
    for name, code in (("rc", rc), ("com_rc", com_rc)):
        if not 0 <= code <= 99999:
            raise ValueError(f"{name} must be 0..99999, got {code}")
    body = ",".join([f"{rc:d}", *(format_value(p, digits) for p in params)])
    return _with_crc(f"%R1P,{com_rc},{trid}", body, checksum).encode("ascii") + TERMINATOR


def encode_request_frame(request: Request) -> bytes:
    """Re-encode a :class:`Request` from its raw tokens (a CRC is recomputed when ``request.crc`` is set)."""
    head = f"%R1Q,{request.rpc}" if request.trid is None else f"%R1Q,{request.rpc},{request.trid}"
    return _with_crc(head, ",".join(request.params), request.crc is not None).encode("ascii") + TERMINATOR


def encode_reply_frame(reply: Reply) -> bytes:
    """Re-encode a :class:`Reply` from its raw tokens (a CRC is recomputed when ``reply.crc`` is set)."""
    body = ",".join([str(reply.rc), *reply.params])
    return _with_crc(f"%R1P,{reply.com_rc},{reply.trid}", body, reply.crc is not None).encode("ascii") + TERMINATOR


_REQ_RE = re.compile(r"%R1Q,([0-9]{1,5})(?:,([0-9]{1,5})(?:(,)([0-9]{1,5}))?)?:(.*)", re.ASCII | re.DOTALL)
_REP_RE = re.compile(r"%R1P,([0-9]{1,5}),([0-9]{1,5})(?:(,)([0-9]{1,5}))?:([0-9]{1,5})(?:,(.*))?",
                     re.ASCII | re.DOTALL)


def _line_text(line: bytes | str) -> str:
    if isinstance(line, (bytes, bytearray, memoryview)):
        try:
            text = bytes(line).decode("ascii")
        except UnicodeDecodeError as exc:
            raise ProtocolError(f"non-ASCII bytes in GeoCOM frame {bytes(line)[:80]!r}") from exc
    elif isinstance(line, str):
        if not line.isascii():
            raise ProtocolError(f"non-ASCII characters in GeoCOM frame {line[:80]!r}")
        text = line
    else:
        raise TypeError(f"expected bytes or str, got {type(line).__name__}")
    text = text.lstrip("\n").rstrip("\r\n")
    if "\r" in text or "\n" in text:
        raise ProtocolError(f"line break inside GeoCOM frame {text[:80]!r}")
    return text


def _verify_crc(text: str, m: re.Match[str], comma_group: int, crc_group: int, trid: int | None) -> int | None:
    if m.group(crc_group) is None:
        return None
    crc = int(m.group(crc_group))
    start = m.start(comma_group)
    end = m.end(crc_group)
    expected = crc16_arc(text[:start] + text[end:])
    if crc != expected:
        raise ChecksumError(f"CRC mismatch in {text[:80]!r}: field {crc}, computed {expected}", trid)
    return crc


def decode_request(line: bytes | str, *, require_crc: bool = False) -> Request:
    """Parse one request line (terminator optional). Raises :class:`ProtocolError`
    (:class:`ChecksumError` for a wrong or, with ``require_crc``, missing CRC)."""
    text = _line_text(line)
    m = _REQ_RE.fullmatch(text)
    if m is None:
        raise ProtocolError(f"not a GeoCOM request: {text[:80]!r}")
    rpc = int(m.group(1))
    trid = None if m.group(2) is None else int(m.group(2))
    if trid is not None and trid >= MAX_TRID:
        raise ProtocolError(f"transaction id {trid} out of range in {text[:80]!r}")
    crc = _verify_crc(text, m, 3, 4, trid)
    if require_crc and crc is None:
        raise ChecksumError(f"request without CRC: {text[:80]!r}", trid)
    return Request(rpc=rpc, params=split_params(m.group(5)), trid=trid, crc=crc)


def decode_reply(line: bytes | str, *, require_crc: bool = False) -> Reply:
    """Parse one reply line (terminator optional). Raises :class:`ProtocolError`."""
    text = _line_text(line)
    m = _REP_RE.fullmatch(text)
    if m is None:
        raise ProtocolError(f"not a GeoCOM reply: {text[:80]!r}")
    trid = int(m.group(2))
    if trid >= MAX_TRID:
        raise ProtocolError(f"transaction id {trid} out of range in {text[:80]!r}")
    crc = _verify_crc(text, m, 3, 4, trid)
    if require_crc and crc is None:
        raise ChecksumError(f"reply without CRC: {text[:80]!r}", trid)
    params = () if m.group(6) is None else split_params(m.group(6))
    return Reply(rc=int(m.group(5)), params=params, trid=trid, com_rc=int(m.group(1)), crc=crc)


def split_line(buffer: bytes | bytearray) -> tuple[int, bytes | None]:
    """Cut the first complete line off ``buffer``: ``(bytes consumed, line without CR/LF)``, or
    ``(0, None)`` when no LF has arrived yet ("need more"). Lines end with LF; a CR before it is dropped,
    so CR LF and bare LF both work. Raises :class:`ProtocolError` when more than
    :data:`MAX_LINE_BYTES` arrive without a line end (the caller should drop its buffer)."""
    end = buffer.find(b"\n")
    if end < 0:
        if len(buffer) > MAX_LINE_BYTES:
            raise ProtocolError(f"no line end within {MAX_LINE_BYTES} bytes")
        return 0, None
    line = bytes(buffer[:end])
    if line.endswith(b"\r"):
        line = line[:-1]
    return end + 1, line


def next_trid(trid: int) -> int:
    """The transaction id after ``trid`` (wraps at 2**15)."""
    return (trid + 1) % MAX_TRID


# --------------------------------------------------------------------------------------------------
# Polar convention of the instrument
# --------------------------------------------------------------------------------------------------

def polar_from_delta(d_e: float, d_n: float, d_h: float) -> tuple[float, float, float]:
    """(Hz, V, slope distance) of the vector (dE, dN, dH) from the instrument's tilting axis.

    Hz is in [0, 2*pi), clockwise from +N towards +E; V is the zenith angle in [0, pi]; units follow the
    input (metres in, metres out)."""
    horizontal = math.hypot(d_e, d_n)
    hz = math.atan2(d_e, d_n) % (2 * math.pi)
    if hz >= 2 * math.pi:      # a tiny negative angle rounds up to exactly 2 pi
        hz = 0.0
    v = math.atan2(horizontal, d_h)
    return hz, v, math.sqrt(horizontal * horizontal + d_h * d_h)


def delta_from_polar(hz: float, v: float, distance: float) -> tuple[float, float, float]:
    """Inverse of :func:`polar_from_delta`: (dE, dN, dH) = d * (sin V sin Hz, sin V cos Hz, cos V)."""
    s = math.sin(v)
    return distance * s * math.sin(hz), distance * s * math.cos(hz), distance * math.cos(v)
