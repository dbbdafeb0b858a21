"""Driver of the LED sphere speaking the binary serial protocol of :mod:`.codec`.

:class:`LedSphereSerial` satisfies :class:`drivers.contracts.LightSource` over an injected, already-open
pyserial-like transport (a serial port, a pty, ``socket://``); its constructor does no I/O.
:func:`open_led_sphere_serial` opens the transport by URL and lets the driver :meth:`~LedSphereSerial.reconnect`.

Transactions. Each request gets a fresh sequence number; the reply must echo it, so a late reply to an
earlier, timed-out attempt is recognised and discarded. Every read is bounded by ``timeout_s`` per attempt.
Bytes that do not form a valid frame are skipped (the codec resynchronises on the next SOF); if the line goes
idle for :data:`IDLE_GAP_S` with only part of a frame buffered, that partial frame is abandoned (the host's
inter-byte timeout), so a false SOF in line noise cannot hold back a real reply behind it. An attempt that
ends without a valid reply raises :class:`~drivers.errors.ProtocolError` if bytes arrived (garbage, bad CRC)
and :class:`~drivers.errors.DeviceTimeout` if nothing did.

Retries. Up to ``retries`` more attempts are made after a timeout, a garbled reply or a ``BAD_CRC`` NACK,
but only for idempotent commands. Every command of this protocol is idempotent: IDENTIFY and STATUS only
read; SELECT_SLOT, SET_POLARIZATION, ALL_OFF and WATCHDOG set a state to an absolute value; UPLOAD_PATTERN
writes absolute values to an absolute LED range of one slot, so repeating a chunk (or the whole upload)
leaves the slot exactly as one successful write would. Other NACKs are not retried: they raise
:class:`~drivers.errors.DeviceRejected` carrying the device's code (``BUSY`` raises
:class:`~drivers.errors.DeviceBusy`, which the caller may retry later). A lost transport raises
:class:`~drivers.errors.ConnectionLost` and is never retried here: the sphere may have gone dark through its
watchdog meanwhile, so the caller decides whether to :meth:`~LedSphereSerial.reconnect` and re-establish state.
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, TypeVar

import numpy as np
import numpy.typing as npt
import serial

from ..contracts import DeviceIdentity, LightStatus, Polarization
from ..errors import (ConnectionLost, DeviceBusy, DeviceError, DeviceRejected, DeviceTimeout, LimitError,
                      ProtocolError)
from ..transport import ByteTransport, open_transport, write_all
from . import codec

try:
    from termios import error as _TermiosError   # pyserial's posix reset_input_buffer raises it on a dead pty
except ImportError:  # pragma: no cover - non-posix
    class _TermiosError(Exception):  # type: ignore[no-redef]
        pass

log = logging.getLogger(__name__)
_PORT_ERRORS = (serial.SerialException, OSError, _TermiosError)

POLL_S = 0.01           # port read timeout while waiting for a reply (granularity of deadlines)
IDLE_GAP_S = 0.05       # line idle this long with a partial frame buffered: abandon that partial frame
BAUDRATE = 115200
KIND = "led_sphere"

_R = TypeVar("_R")


@dataclass(frozen=True)
class PatternLoad:
    """What a pattern would draw, by the driver's current model (see :meth:`LedSphereSerial.check_pattern`)."""

    current_a: float     # sum over LEDs and channels of value/65535 * led_current_a_per_channel
    mean_duty: float     # mean over LEDs and channels of value/65535
    peak_value: int      # largest channel value


class LedSphereSerial:
    """An LED sphere on a byte transport (``contracts.LightSource`` plus :meth:`set_watchdog`).

    ``port``: an open pyserial-like transport; the driver sets its read ``timeout`` to :data:`POLL_S` on
    first use. Limits: a pattern is refused with :class:`LimitError`, before anything is sent, if its
    estimated current exceeds ``max_total_current_a``, its mean duty exceeds ``max_mean_duty`` or any value
    exceeds ``max_led_value``; current model: each channel of each LED draws ``led_current_a_per_channel``
    at full scale, linearly in its value. ``led_count_hint`` lets shapes be checked before :meth:`identify`
    (the device's answer wins). ``reopen`` (set by :func:`open_led_sphere_serial`) opens a fresh transport for
    :meth:`reconnect`.
    """

    def __init__(self, port: ByteTransport, *, led_count_hint: int | None = None, max_total_current_a: float,
                 max_led_value: int = codec.FULL_SCALE, max_mean_duty: float,
                 led_current_a_per_channel: float = 0.02, timeout_s: float = 0.5, retries: int = 2,
                 reopen: Callable[[], ByteTransport] | None = None) -> None:
        if not max_total_current_a > 0:
            raise ValueError(f"max_total_current_a must be > 0 A, got {max_total_current_a}")
        if not 0 < max_mean_duty <= 1:
            raise ValueError(f"max_mean_duty must be in (0, 1], got {max_mean_duty}")
        if not 0 <= int(max_led_value) <= codec.FULL_SCALE:
            raise ValueError(f"max_led_value must be in [0, {codec.FULL_SCALE}], got {max_led_value}")
        if not led_current_a_per_channel > 0:
            raise ValueError(f"led_current_a_per_channel must be > 0 A, got {led_current_a_per_channel}")
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s}")
        if int(retries) != retries or retries < 0:
            raise ValueError(f"retries must be an integer >= 0, got {retries}")
        if led_count_hint is not None and not 0 < led_count_hint <= 0xFFFF:
            raise ValueError(f"led_count_hint must be in [1, 65535], got {led_count_hint}")
        self._port = port
        self._reopen = reopen
        self.led_count_hint = led_count_hint
        self.max_total_current_a = float(max_total_current_a)
        self.max_led_value = int(max_led_value)
        self.max_mean_duty = float(max_mean_duty)
        self.led_current_a_per_channel = float(led_current_a_per_channel)
        self.timeout_s = float(timeout_s)
        self.retries = int(retries)
        self._lock = threading.RLock()
        self._seq = 0
        self._port_ready = False
        self._closed = False
        self._identity: DeviceIdentity | None = None
        self._led_count: int | None = None
        self._slot_count: int | None = None

    # ------------------------------------------------------------------------------------- properties
    @property
    def led_count(self) -> int:
        """LED count reported by :meth:`identify`; before that ``led_count_hint``, or 0 if neither is known."""
        if self._led_count is not None:
            return self._led_count
        return self.led_count_hint or 0

    @property
    def slot_count(self) -> int | None:
        """Number of pattern slots reported by :meth:`identify` (None before)."""
        return self._slot_count

    # ------------------------------------------------------------------------------------------ verbs
    def identify(self) -> DeviceIdentity:
        reply = self._transact(codec.Identify(), codec.IdentifyReply, what="IDENTIFY")
        if reply.channels != codec.CHANNELS:
            raise ProtocolError(f"LED sphere reports {reply.channels} channels per LED; this driver speaks "
                                f"(R, G, B) = {codec.CHANNELS}")
        if reply.led_count == 0:
            raise ProtocolError("LED sphere reports 0 LEDs")
        if self.led_count_hint is not None and self.led_count_hint != reply.led_count:
            log.warning("LED sphere reports %d LEDs, configured hint was %d; using the device's count",
                        reply.led_count, self.led_count_hint)
        self._led_count = reply.led_count
        self._slot_count = reply.slot_count
        self._identity = DeviceIdentity(
            kind=KIND, model=reply.model, firmware=reply.firmware, serial_number=reply.serial_number,
            extra={"led_count": reply.led_count, "channels": reply.channels, "slot_count": reply.slot_count,
                   "protocol": "led-sphere-serial/1"})
        return self._identity

    def check_pattern(self, rgb16: npt.NDArray[np.uint16]) -> PatternLoad:
        """Validate ``rgb16`` against dtype, shape and the safety limits without any I/O.

        ``ValueError`` for a wrong dtype or shape (expected ``(led_count, 3)`` uint16), :class:`LimitError`
        for a value, current or duty over its limit. Returns the estimated load.
        """
        a = np.asarray(rgb16)
        n = self._led_count or self.led_count_hint
        expected = f"({n if n else 'led_count'}, {codec.CHANNELS})"
        if a.dtype != np.uint16:
            raise ValueError(f"pattern must be a {expected} uint16 array, got dtype {a.dtype}")
        if a.ndim != 2 or a.shape[1] != codec.CHANNELS or (n and a.shape[0] != n) or a.shape[0] == 0:
            raise ValueError(f"pattern must have shape {expected}, got {a.shape}")
        peak = int(a.max())
        if peak > self.max_led_value:
            raise LimitError(f"pattern value {peak} exceeds max_led_value={self.max_led_value}")
        duty = a.astype(np.float64) / codec.FULL_SCALE
        current_a = float(duty.sum()) * self.led_current_a_per_channel
        mean_duty = float(duty.mean())
        if current_a > self.max_total_current_a:
            raise LimitError(f"pattern would draw an estimated {current_a:.3f} A, over max_total_current_a="
                             f"{self.max_total_current_a:g} A (model: {self.led_current_a_per_channel:g} A "
                             f"per channel at full scale)")
        if mean_duty > self.max_mean_duty:
            raise LimitError(f"pattern mean duty {mean_duty:.4f} exceeds max_mean_duty={self.max_mean_duty:g}")
        return PatternLoad(current_a=current_a, mean_duty=mean_duty, peak_value=peak)

    def upload_pattern(self, slot: int, rgb16: npt.NDArray[np.uint16]) -> None:
        """Store a (led_count, 3) uint16 pattern in ``slot``, in frames of at most
        :data:`codec.MAX_UPLOAD_LEDS` LEDs. Checked by :meth:`check_pattern` before anything is sent; if
        the LED count is not known yet (no :meth:`identify`, no hint), IDENTIFY is sent first."""
        self._check_slot_number(slot)
        self.check_pattern(rgb16)
        if self._led_count is None and self.led_count_hint is None:
            self.identify()
            self.check_pattern(rgb16)   # now against the real LED count
        self._check_slot_range(slot)
        a = np.asarray(rgb16)
        for offset in range(0, a.shape[0], codec.MAX_UPLOAD_LEDS):
            chunk = a[offset:offset + codec.MAX_UPLOAD_LEDS]
            request = codec.UploadPattern.from_array(slot, offset, chunk)
            ack = self._transact(request, codec.UploadAck,
                                 what=f"UPLOAD_PATTERN slot {slot} LEDs {offset}..{offset + len(chunk) - 1}")
            if (ack.slot, ack.offset, ack.count) != (slot, offset, len(chunk)):
                raise ProtocolError(f"UPLOAD_PATTERN acknowledged slot {ack.slot} offset {ack.offset} count "
                                    f"{ack.count}, sent slot {slot} offset {offset} count {len(chunk)}")

    def select_slot(self, slot: int) -> None:
        """Light the pattern stored in ``slot`` (the device refuses it if over its own limits)."""
        self._check_slot_number(slot)
        self._check_slot_range(slot)
        ack = self._transact(codec.SelectSlot(slot), codec.SelectAck, what=f"SELECT_SLOT {slot}")
        if ack.slot != slot:
            raise ProtocolError(f"SELECT_SLOT acknowledged slot {ack.slot}, sent {slot}")

    def set_polarization(self, state: Polarization) -> None:
        try:
            pol = Polarization(state)
        except ValueError as exc:
            raise ValueError(f"polarization must be one of {[p.name for p in Polarization]}, got {state!r}"
                             ) from exc
        ack = self._transact(codec.SetPolarization(int(pol)), codec.PolarizationAck,
                             what=f"SET_POLARIZATION {pol.name}")
        if ack.state != pol:
            raise ProtocolError(f"SET_POLARIZATION acknowledged {ack.state}, sent {int(pol)}")

    def all_off(self) -> None:
        """Darken every LED (and clear a latched watchdog fault). Idempotent."""
        self._transact(codec.AllOff(), codec.AllOffAck, what="ALL_OFF")

    def status(self) -> LightStatus:
        r = self._transact(codec.Status(), codec.StatusReply, what="STATUS")
        try:
            pol = Polarization(r.polarization)
        except ValueError as exc:
            raise ProtocolError(f"STATUS reports unknown polarization {r.polarization}") from exc
        return LightStatus(temperature_c=r.temperature_centi_c / 100.0, current_a=r.current_ma / 1000.0,
                           fault_flags=r.faults,
                           active_slot=None if r.active_slot == codec.DARK_SLOT else r.active_slot,
                           polarization=pol, lit=r.lit)

    def set_watchdog(self, timeout_s: float | None) -> None:
        """Arm the device watchdog: if no valid frame arrives for ``timeout_s`` the sphere goes dark and
        sets fault bit 1. ``None`` or 0 disables it. Resolution 1 ms, range 0.001..65.535 s."""
        ms = 0 if not timeout_s else int(round(float(timeout_s) * 1000))
        if timeout_s and not 1 <= ms <= 0xFFFF:
            raise ValueError(f"watchdog timeout must be 0 (off) or 0.001..65.535 s, got {timeout_s}")
        ack = self._transact(codec.SetWatchdog(ms), codec.WatchdogAck, what=f"WATCHDOG {ms} ms")
        if ack.timeout_ms != ms:
            raise ProtocolError(f"WATCHDOG acknowledged {ack.timeout_ms} ms, sent {ms} ms")

    def reconnect(self) -> None:
        """Close the transport and open a fresh one (only for drivers made by :func:`open_led_sphere_serial`).
        Device state is not re-established: call :meth:`status` and re-select as needed."""
        if self._reopen is None:
            raise ConnectionLost("this LED sphere driver was given an open transport and cannot reopen it")
        with self._lock:
            try:
                self._port.close()
            except _PORT_ERRORS:
                pass
            self._port = self._reopen()
            self._port_ready = False
            self._closed = False

    def close(self) -> None:
        """Try :meth:`all_off`, then close the transport. Safe to call more than once."""
        with self._lock:
            if self._closed:
                return
            try:
                self.all_off()
            except DeviceError as exc:
                log.warning("LED sphere: all_off on close failed: %s", exc)
            finally:
                self._closed = True
                try:
                    self._port.close()
                except _PORT_ERRORS as exc:
                    log.warning("LED sphere: closing the transport failed: %s", exc)

    def __enter__(self) -> "LedSphereSerial":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # -------------------------------------------------------------------------------------- internals
    def _check_slot_number(self, slot: int) -> None:
        if isinstance(slot, bool) or not isinstance(slot, (int, np.integer)) or \
                not 0 <= slot < codec.DARK_SLOT:
            raise ValueError(f"slot must be an integer in [0, {codec.DARK_SLOT - 1}], got {slot!r}; "
                             f"use all_off() to darken the sphere")

    def _check_slot_range(self, slot: int) -> None:
        if self._slot_count is not None and slot >= self._slot_count:
            raise ValueError(f"slot {slot} out of range: the sphere has slots 0..{self._slot_count - 1}")

    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFF
        return self._seq

    def _transact(self, request: codec.Request, reply_type: type[_R], *, what: str,
                  idempotent: bool = True) -> _R:
        """Send ``request`` and return its ACK as ``reply_type``; retry only if ``idempotent``."""
        with self._lock:
            if self._closed:
                raise ConnectionLost(f"LED sphere driver is closed; cannot send {what}")
            if not self._port_ready:
                self._port.timeout = POLL_S
                self._port_ready = True
            attempts = 1 + (self.retries if idempotent else 0)
            failure: DeviceError | None = None
            for attempt in range(1, attempts + 1):
                seq = self._next_seq()
                frame = codec.encode(seq, request)
                self._flush_input()
                log.debug("LED sphere >> %s (seq %d, attempt %d/%d): %s", what, seq, attempt, attempts,
                          frame.hex(" "))
                try:
                    write_all(self._port, frame, what=what)
                except _TermiosError as exc:   # tcdrain on a dead pty; write_all maps only OSError
                    raise ConnectionLost(f"LED sphere transport lost while writing {what}: {exc}") from exc
                try:
                    reply_frame = self._await_reply(seq, request.CMD, what=f"{what} (attempt {attempt}/"
                                                                            f"{attempts})")
                except (DeviceTimeout, ProtocolError) as exc:
                    log.info("LED sphere: %s", exc)
                    failure = exc
                    continue
                reply = codec.parse_reply(reply_frame)   # a malformed but CRC-valid reply is not retried
                if isinstance(reply, codec.Nack):
                    name = codec.nack_name(reply.code)
                    if reply.code == codec.NackCode.BAD_CRC:
                        failure = DeviceRejected(f"LED sphere received {what} corrupted "
                                                 f"(attempt {attempt}/{attempts})", reply.code, name=name)
                        log.info("LED sphere: %s", failure)
                        continue
                    cls = DeviceBusy if reply.code == codec.NackCode.BUSY else DeviceRejected
                    raise cls(f"LED sphere refused {what}", reply.code, name=name)
                if not isinstance(reply, reply_type):
                    raise ProtocolError(f"LED sphere answered {what} with {type(reply).__name__}")
                return reply
            assert failure is not None
            raise failure

    def _flush_input(self) -> None:
        try:
            self._port.reset_input_buffer()
        except _PORT_ERRORS as exc:
            raise ConnectionLost(f"LED sphere transport lost: {exc}") from exc

    def _read_some(self) -> bytes:
        try:
            waiting = getattr(self._port, "in_waiting", 0) or 0
            return self._port.read(max(1, min(int(waiting), 4096)))
        except _PORT_ERRORS as exc:
            raise ConnectionLost(f"LED sphere transport lost while reading: {exc}") from exc

    def _await_reply(self, seq: int, cmd: int, *, what: str) -> codec.Frame:
        """Read until a frame with ``seq`` answering ``cmd`` arrives, or raise at the deadline."""
        deadline = time.monotonic() + self.timeout_s
        buf = bytearray()
        discarded = 0
        stale = 0
        ack_cmd = cmd | codec.ACK_FLAG

        def scan(final: bool) -> codec.Frame | None:
            nonlocal discarded, stale
            while buf:
                consumed, frame = codec.decode(buf, final=final)
                if frame is None:
                    discarded += consumed
                    del buf[:consumed]
                    return None
                discarded += consumed - (codec.OVERHEAD + len(frame.payload))
                del buf[:consumed]
                if frame.seq == seq and frame.cmd in (ack_cmd, codec.NACK):
                    log.debug("LED sphere << seq %d cmd 0x%02X: %s", frame.seq, frame.cmd, frame.payload.hex(" "))
                    return frame
                stale += 1
                log.info("LED sphere: discarded a stale frame (seq %d cmd 0x%02X) while waiting for seq %d",
                         frame.seq, frame.cmd, seq)
            return None

        last_rx = time.monotonic()
        while True:
            found = scan(final=False)
            if found is not None:
                return found
            now = time.monotonic()
            if now >= deadline:
                found = scan(final=True)
                if found is not None:
                    return found
                if discarded:
                    raise ProtocolError(f"no valid reply to {what} within {self.timeout_s:.3g} s: {discarded} "
                                        f"bytes of garbage or corrupt frames discarded")
                raise DeviceTimeout(f"LED sphere did not answer {what} within {self.timeout_s:.3g} s"
                                    + (f" ({stale} stale frames discarded)" if stale else ""))
            chunk = self._read_some()
            if chunk:
                buf += chunk
                last_rx = time.monotonic()
            elif buf and time.monotonic() - last_rx >= IDLE_GAP_S:
                found = scan(final=True)
                if found is not None:
                    return found


def open_led_sphere_serial(url: str, *, baudrate: int = BAUDRATE, **kwargs: Any) -> LedSphereSerial:
    """Open ``url`` (a device path, a pty, ``socket://host:port``...) with
    :func:`drivers.transport.open_transport` and return a :class:`LedSphereSerial` on it. ``kwargs`` go to
    the driver (``max_total_current_a``, ``max_mean_duty``, ``timeout_s``...). No bytes are exchanged; the
    driver can :meth:`~LedSphereSerial.reconnect` to the same URL. ``ConnectionLost`` if it cannot open."""

    write_timeout_s = float(kwargs.get("timeout_s", 0.5))

    def reopen() -> ByteTransport:
        return open_transport(url, baudrate=baudrate, timeout_s=write_timeout_s)

    return LedSphereSerial(reopen(), reopen=reopen, **kwargs)
