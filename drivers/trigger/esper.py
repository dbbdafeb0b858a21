"""ASCII trigger box of the ESPER TriggerBox kind: the driver (its sans-IO codec: :mod:`drivers.trigger.esper_codec`).

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
:func:`split_line`, in :mod:`drivers.trigger.esper_codec`, re-exported here) never touches a port and is shared by
the driver and ``simulators.trigger``.
"""
from __future__ import annotations

import threading
import time

import serial

from ..contracts import DeviceIdentity
from ..errors import ConnectionLost, DeviceBusy, DeviceRejected, DeviceTimeout, ProtocolError
from ..transport import ByteTransport, open_transport, write_all
from .exposure import check_exposure_range
from .esper_codec import (ACK, Ack, BAUDRATE, BULB_MAX_MS, Command, ERROR_NAMES, ERR_BAD_ARGUMENT, ERR_BUSY,
                          ERR_NO_BULB, ERR_NO_OUTPUTS, ERR_UNKNOWN_COMMAND, EnableOutputs, ErrorReply, Fire,
                          GetCount, Identify, Identity, MAX_LINE, OUTPUT_COUNT, Reply, SetBulb, SetMode, ShotCount,
                          TERMINATOR, bulb_ms_for, command_error_code, decode_reply, encode_command, encode_reply,
                          parse_command, parse_reply, split_line)

__all__ = ['ACK', 'Ack', 'BAUDRATE', 'BULB_MAX_MS', 'Command', 'ERROR_NAMES', 'ERR_BAD_ARGUMENT', 'ERR_BUSY',
           'ERR_NO_BULB', 'ERR_NO_OUTPUTS', 'ERR_UNKNOWN_COMMAND', 'EnableOutputs', 'ErrorReply', 'EsperTrigger',
           'Fire', 'GetCount', 'Identify', 'Identity', 'MAX_LINE', 'OUTPUT_COUNT', 'Reply', 'SetBulb', 'SetMode',
           'ShotCount', 'TERMINATOR', 'bulb_ms_for', 'command_error_code', 'decode_reply', 'encode_command',
           'encode_reply', 'open_esper_trigger', 'parse_command', 'parse_reply', 'split_line']


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
