"""ASCII trigger box of the ESPER TriggerBox kind: sans-IO codec and driver.

The dialogue (``docs/protocols/trigger-boxes.md``): the host sends one newline-terminated ASCII command, the
box answers one newline-terminated line. Commands::

    m<d>        set mode d (0 = camera-trigger mode, the one sssrig uses)      -> tenFour
    s<bbbbbb>   enable outputs 1..6, one '0'/'1' per output ("s111111")       -> tenFour
    b<ms>       bulb (exposure) time in whole milliseconds, 1..9999999        -> tenFour
    S           fire the enabled outputs for the bulb time                     -> tenFour
    ?           identify                                  -> id:<maker>,<model>,<firmware>,<serial>
    c           shot counter (shots fired since power-up)                      -> count:<n>

A refused command is answered ``err:<code>`` (:data:`ERROR_NAMES`). ``tenFour`` to ``S`` means the outputs
fired; a box may send it at the start or at the end of the exposure, so the driver waits up to
``timeout_s + exposure_s`` for it. Replies may end in ``\\r\\n``; empty lines are ignored.

The codec (:func:`encode_command`, :func:`parse_command`, :func:`encode_reply`, :func:`parse_reply`,
:func:`split_line`) never touches a port and is shared by the driver and ``simulators.trigger``.
"""
from __future__ import annotations

import re
import threading
import time
from dataclasses import dataclass
from typing import Union

import serial

from ..contracts import DeviceIdentity
from ..errors import ConnectionLost, DeviceBusy, DeviceRejected, DeviceTimeout, LimitError, ProtocolError
from ..transport import ByteTransport, open_transport, write_all
from .exposure import check_exposure_range, exposure_ms

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


class EsperTrigger:
    """Driver for an ESPER-style ASCII trigger box on an injected, already-open byte transport.

    The constructor does no I/O. The first :meth:`fire` sends ``m<mode>`` and ``s<outputs>`` once (or call
    :meth:`configure` explicitly); every :meth:`fire` then sends ``b<ms>`` and ``S``. :meth:`fire` returns
    once the exposure is over (``wait_for_exposure=True``), at least ``exposure_s`` after ``S`` was sent.
    A garbled reply raises :class:`ProtocolError`; stale input is flushed before every command, so the
    next command resynchronises.
    """

    def __init__(self, port: ByteTransport, *, timeout_s: float = 1.0, min_exposure_s: float = 0.001,
                 max_exposure_s: float = 60.0, outputs: tuple[bool, ...] = (True,) * OUTPUT_COUNT,
                 mode: int = 0, wait_for_exposure: bool = True, name: str = "esper") -> None:
        if len(outputs) != OUTPUT_COUNT:
            raise ValueError(f"outputs: expected {OUTPUT_COUNT} flags, got {len(outputs)}")
        check_exposure_range(min_exposure_s, max_exposure_s)
        self._port = port
        self.timeout_s = timeout_s
        self.min_exposure_s = min_exposure_s
        self.max_exposure_s = max_exposure_s
        self.outputs = tuple(bool(o) for o in outputs)
        self.mode = mode
        self.wait_for_exposure = wait_for_exposure
        self.name = name
        self._configured = False
        self._busy_until = float("-inf")
        self._lock = threading.RLock()
        self._closed = False

    # -- transport helpers ------------------------------------------------------------------------------
    def _read_line(self, timeout_s: float, what: str) -> bytes:
        buf = bytearray()
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                chunk = self._port.read(1)
            except (serial.SerialException, OSError) as exc:
                raise ConnectionLost(f"{self.name}: transport lost while reading {what}: {exc}") from exc
            if chunk:
                buf += chunk
                n, line = split_line(bytes(buf))
                if line is not None:
                    if line not in (b"", b"\r"):
                        return line
                    del buf[:n]                       # empty line: skip
            if time.monotonic() >= deadline:          # also ends a stream of bytes that never forms a reply
                raise DeviceTimeout(f"{self.name}: no reply to {what} within {timeout_s:.3g} s"
                                    f" ({len(buf)} bytes of a partial line: {bytes(buf[:32])!r})")

    def _transact(self, cmd: Command, *, timeout_s: float | None = None) -> Reply:
        if self._closed:
            raise ConnectionLost(f"{self.name}: trigger is closed")
        frame = encode_command(cmd)
        what = repr(frame.rstrip(TERMINATOR).decode())
        try:
            self._port.reset_input_buffer()
        except (serial.SerialException, OSError) as exc:
            raise ConnectionLost(f"{self.name}: transport lost before {what}: {exc}") from exc
        write_all(self._port, frame, what=f"{self.name} command {what}")
        line = self._read_line(self.timeout_s if timeout_s is None else timeout_s, what)
        try:
            reply = parse_reply(line)
        except ProtocolError as exc:
            raise ProtocolError(f"{self.name}: garbled reply to {what}: {exc}") from None
        if isinstance(reply, ErrorReply):
            cls = DeviceBusy if reply.code == ERR_BUSY else DeviceRejected
            raise cls(f"{self.name}: box refused {what}", reply.code, name=reply.name)
        return reply

    def _expect_ack(self, cmd: Command, *, timeout_s: float | None = None) -> None:
        reply = self._transact(cmd, timeout_s=timeout_s)
        if not isinstance(reply, Ack):
            raise ProtocolError(f"{self.name}: expected tenFour to {encode_command(cmd)!r}, got {reply!r}")

    # -- verbs ------------------------------------------------------------------------------------------
    def identify(self) -> DeviceIdentity:
        with self._lock:
            reply = self._transact(Identify())
        if not isinstance(reply, Identity):
            raise ProtocolError(f"{self.name}: expected an id: line to '?', got {reply!r}")
        return DeviceIdentity(kind="trigger", model=f"{reply.maker} {reply.model}", firmware=reply.firmware,
                              serial_number=reply.serial,
                              extra={"protocol": "esper-ascii", "outputs": OUTPUT_COUNT})

    def shot_count(self) -> int:
        """Shots fired since the box powered up (``c``)."""
        with self._lock:
            reply = self._transact(GetCount())
        if not isinstance(reply, ShotCount):
            raise ProtocolError(f"{self.name}: expected count: to 'c', got {reply!r}")
        return reply.count

    def set_mode(self, mode: int) -> None:
        with self._lock:
            self._expect_ack(SetMode(mode))
            self.mode = mode

    def enable_outputs(self, outputs: tuple[bool, ...]) -> None:
        with self._lock:
            self._expect_ack(EnableOutputs(tuple(bool(o) for o in outputs)))
            self.outputs = tuple(bool(o) for o in outputs)

    def configure(self) -> None:
        """Send the mode and the enabled outputs (done once, lazily, by the first :meth:`fire`)."""
        with self._lock:
            self._expect_ack(SetMode(self.mode))
            self._expect_ack(EnableOutputs(self.outputs))
            self._configured = True

    def fire(self, exposure_s: float) -> None:
        """Open the shutter for ``exposure_s`` (rounded to whole ms); return once the exposure is over.

        A box that answers ``S`` with NO_OUTPUTS lost its configuration (power-cycled): it is configured again
        and ``S`` sent once more. BUSY while our own previous exposure may still be running on the box (it started
        when the box answered, which is after we timed it from) is waited out once; any other BUSY raises
        :class:`DeviceBusy`."""
        ms = bulb_ms_for(exposure_s, min_exposure_s=self.min_exposure_s, max_exposure_s=self.max_exposure_s)
        with self._lock:
            if not self._configured:
                self.configure()
            self._expect_ack(SetBulb(ms))
            t_fire = time.monotonic()
            try:
                self._expect_ack(Fire(), timeout_s=self.timeout_s + ms / 1000.0)
            except DeviceRejected as exc:
                own = exc.code == ERR_BUSY and time.monotonic() < self._busy_until + 0.05
                if exc.code != ERR_NO_OUTPUTS and not own:
                    raise
                if own:
                    time.sleep(max(0.0, self._busy_until - time.monotonic()) + 0.002)
                else:
                    self.configure()
                t_fire = time.monotonic()
                self._expect_ack(Fire(), timeout_s=self.timeout_s + ms / 1000.0)
            self._busy_until = time.monotonic() + ms / 1000.0      # the latest our exposure can end on the box
            if self.wait_for_exposure:
                remaining = t_fire + ms / 1000.0 - time.monotonic()
                if remaining > 0:
                    time.sleep(remaining)

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                self._port.close()
            except (serial.SerialException, OSError):
                pass

    def __enter__(self) -> "EsperTrigger":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_esper_trigger(url: str, timeout_s: float = 1.0, **kwargs: object) -> EsperTrigger:
    """Open ``url`` (device path, pty, ``socket://host:port``) at 115200 baud and wrap it in an
    :class:`EsperTrigger`; extra keyword arguments go to the driver. No command is sent yet."""
    port = open_transport(url, baudrate=BAUDRATE, timeout_s=timeout_s)
    return EsperTrigger(port, timeout_s=timeout_s, name=f"esper {url}", **kwargs)  # type: ignore[arg-type]
