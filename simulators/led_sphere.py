"""Simulated LED sphere speaking the binary serial protocol (``docs/protocols/led-sphere-serial.md``).

:class:`LedSphereModel` is sans-IO (``receive(bytes) -> bytes``, ``reset()``) and shares
:mod:`drivers.led_sphere.codec` with the driver; serve it with ``simulators.serve.serve(model, "pty")``.
It keeps the pattern slots, the selected slot, the polarizer state, a first-order thermal model, the
watchdog and the fault bits, and calls ``on_light_change(led_rgb, polarization)`` whenever what the LEDs
emit changes. Time comes from ``clock`` and is evaluated lazily on every ``receive``/``poll``: a watchdog
that expired between two frames trips at its deadline (the thermal model is integrated piecewise), so the
model needs no thread. :class:`Ticker` calls :meth:`LedSphereModel.poll` periodically so that a silent host
still sees the sphere go dark on time (the callback fires within one tick of the deadline).

Fault hooks beyond ``serve.Faults`` (which garble the byte stream): :meth:`~LedSphereModel.nack_next`,
:meth:`~LedSphereModel.busy_for`, :meth:`~LedSphereModel.corrupt_next`, ``force_over_temperature`` and
``led_fault``.

Run alone: ``python -m simulators.led_sphere --url pty|tcp://127.0.0.1:PORT --leds N`` prints the URL to open
(a pty path or ``socket://host:port``) and serves until Ctrl-C.
"""
from __future__ import annotations

import argparse
import collections
import logging
import math
import threading
import time
from typing import Callable, Sequence

import numpy as np
import numpy.typing as npt

from drivers.contracts import Polarization
from drivers.led_sphere import codec
from drivers.led_sphere.codec import FaultFlag, NackCode

log = logging.getLogger(__name__)

LightCallback = Callable[[npt.NDArray[np.float64], Polarization], None]


class LedSphereModel:
    """Sans-IO model of the sphere's microcontroller.

    Thermal model: ``dT/dt = (ambient_c + thermal_c_per_a * current_a - T) / thermal_tau_s``. At
    ``over_temperature_c`` (or with ``force_over_temperature`` set) the sphere goes dark, sets fault bit 0 and
    refuses to light a non-dark slot (NACK ``OVER_TEMPERATURE``) until it cools ``hysteresis_c`` below the
    limit. Selecting (or uploading into the active slot) a pattern that draws more than ``max_current_a`` is
    refused with NACK ``OVER_POWER_LIMIT``. A device whose receive buffer holds part of a frame for longer
    than :attr:`INTERBYTE_TIMEOUT_S` abandons it before taking new bytes.
    """

    INTERBYTE_TIMEOUT_S = 0.1

    def __init__(self, led_count: int = 64, model: str = "SSS-LS1", firmware: str = "1.0.0", slots: int = 16,
                 on_light_change: LightCallback | None = None, clock: Callable[[], float] = time.monotonic, *,
                 serial_number: str = "SIM-0001", led_current_a_per_channel: float = 0.02,
                 max_current_a: float = 20.0, ambient_c: float = 25.0, over_temperature_c: float = 70.0,
                 hysteresis_c: float = 5.0, thermal_c_per_a: float = 2.5, thermal_tau_s: float = 30.0) -> None:
        if not 1 <= led_count <= 0xFFFF:
            raise ValueError(f"led_count must be 1..65535, got {led_count}")
        if not 1 <= slots <= 0xFE:
            raise ValueError(f"slots must be 1..254, got {slots}")
        codec.IdentifyReply(led_count, codec.CHANNELS, slots, model, firmware, serial_number)  # validates
        self.led_count = led_count
        self.model = model
        self.firmware = firmware
        self.serial_number = serial_number
        self.slot_count = slots
        self.on_light_change = on_light_change
        self.clock = clock
        self.led_current_a_per_channel = led_current_a_per_channel
        self.max_current_a = max_current_a
        self.ambient_c = ambient_c
        self.over_temperature_c = over_temperature_c
        self.hysteresis_c = hysteresis_c
        self.thermal_c_per_a = thermal_c_per_a
        self.thermal_tau_s = thermal_tau_s
        self._lock = threading.RLock()
        self._last_emitted = np.zeros((led_count, codec.CHANNELS))
        self._last_polarization = Polarization.NONE
        self._init_state()

    # ------------------------------------------------------------------------------------------ state
    def _init_state(self) -> None:
        self.slots = np.zeros((self.slot_count, self.led_count, codec.CHANNELS), np.uint16)
        self.active_slot: int | None = None
        self.polarization = Polarization.NONE
        self.temperature_c = float(self.ambient_c)
        self.watchdog_ms = 0
        self.force_over_temperature = False   # test hook: hold the over-temperature interlock tripped
        self.led_fault = False                # test hook: report fault bit 2
        self.bytes_received = 0
        self.frames_received = 0
        self.crc_errors = 0
        self.received: collections.deque[codec.Frame] = collections.deque(maxlen=4096)
        self._over_temperature = False
        self._watchdog_tripped = False
        self._watchdog_deadline: float | None = None
        self._rx = bytearray()
        self._last_rx = 0.0
        self._t = self.clock()
        self._nack_queue: collections.deque[int] = collections.deque()
        self._busy = 0
        self._corrupt = 0

    def reset(self) -> None:
        """Power-cycle: empty slots, dark, no polarizer, ambient temperature, watchdog off, hooks cleared."""
        with self._lock:
            self._init_state()
            self._notify_if_changed()

    # ----------------------------------------------------------------------------------------- hooks
    def nack_next(self, code: int, count: int = 1) -> None:
        """Answer the next ``count`` valid frames with NACK ``code`` without executing them."""
        with self._lock:
            self._nack_queue.extend([int(code)] * count)

    def busy_for(self, n: int) -> None:
        """Answer the next ``n`` valid frames with NACK ``BUSY`` without executing them."""
        with self._lock:
            self._busy = int(n)

    def corrupt_next(self, n: int = 1) -> None:
        """Flip a CRC bit in the next ``n`` replies (the commands are executed)."""
        with self._lock:
            self._corrupt = int(n)

    # ------------------------------------------------------------------------------------ observables
    @property
    def faults(self) -> int:
        with self._lock:
            f = 0
            if self._over_temperature:
                f |= FaultFlag.OVER_TEMPERATURE
            if self._watchdog_tripped:
                f |= FaultFlag.WATCHDOG_TRIPPED
            if self.led_fault:
                f |= FaultFlag.LED_FAULT
            return int(f)

    def emitted(self) -> npt.NDArray[np.float64]:
        """What the LEDs emit now: (N, 3) float in [0, 1]."""
        with self._lock:
            if self.active_slot is None:
                return np.zeros((self.led_count, codec.CHANNELS))
            return self.slots[self.active_slot].astype(np.float64) / codec.FULL_SCALE

    def pattern_current_a(self, rgb16: npt.NDArray[np.uint16]) -> float:
        return float(np.asarray(rgb16, np.float64).sum() / codec.FULL_SCALE * self.led_current_a_per_channel)

    @property
    def current_a(self) -> float:
        with self._lock:
            return 0.0 if self.active_slot is None else self.pattern_current_a(self.slots[self.active_slot])

    @property
    def lit(self) -> bool:
        with self._lock:
            return self.active_slot is not None and bool(self.slots[self.active_slot].any())

    # ------------------------------------------------------------------------------------------- time
    def poll(self) -> None:
        """Advance the clock-driven state (watchdog, temperature) to ``clock()``."""
        with self._lock:
            self._advance(self.clock())

    def _advance(self, now: float) -> None:
        now = max(now, self._t)
        while True:
            deadline = self._watchdog_deadline
            trip = deadline is not None and deadline <= now
            target = max(self._t, deadline) if trip and deadline is not None else now
            self._heat(target - self._t)
            self._t = target
            if not trip:
                break
            self._watchdog_deadline = None
            self._watchdog_tripped = True
            log.info("LED sphere simulator: watchdog expired, going dark")
            self._darken()
        hot = self.force_over_temperature or self.temperature_c >= self.over_temperature_c
        if hot and not self._over_temperature:
            self._over_temperature = True
            log.info("LED sphere simulator: over-temperature (%.1f C), going dark", self.temperature_c)
            self._darken()
        elif self._over_temperature and not hot and \
                self.temperature_c < self.over_temperature_c - self.hysteresis_c:
            self._over_temperature = False

    def _heat(self, dt: float) -> None:
        if dt <= 0:
            return
        t_eq = self.ambient_c + self.thermal_c_per_a * self.current_a
        self.temperature_c = t_eq + (self.temperature_c - t_eq) * math.exp(-dt / self.thermal_tau_s)

    # ------------------------------------------------------------------------------------- the light
    def _darken(self) -> None:
        self.active_slot = None
        self._notify_if_changed()

    def _notify_if_changed(self) -> None:
        emitted = self.emitted()
        if self.polarization == self._last_polarization and np.array_equal(emitted, self._last_emitted):
            return
        self._last_emitted = emitted
        self._last_polarization = self.polarization
        if self.on_light_change is not None:
            try:
                self.on_light_change(emitted.copy(), self.polarization)
            except Exception:   # a broken observer must not kill the device
                log.exception("LED sphere simulator: on_light_change callback failed")

    # ----------------------------------------------------------------------------------------- bytes
    def receive(self, data: bytes) -> bytes:
        """Take bytes from the host; return the reply bytes (possibly several frames, possibly none)."""
        with self._lock:
            now = self.clock()
            self._advance(now)
            out = bytearray()
            if self._rx and now - self._last_rx > self.INTERBYTE_TIMEOUT_S:
                out += self._process(now, final=True)   # abandon a stale partial frame
            self._rx += data
            self._last_rx = now
            self.bytes_received += len(data)
            out += self._process(now, final=False)
            return bytes(out)

    def _process(self, now: float, *, final: bool) -> bytes:
        out = bytearray()

        def corrupt(c: codec.CorruptFrame) -> None:
            self.crc_errors += 1
            out.extend(codec.encode(c.seq, codec.Nack(c.cmd, NackCode.BAD_CRC)))

        while self._rx:
            consumed, frame = codec.decode(self._rx, final=final, on_corrupt=corrupt)
            del self._rx[:consumed]
            if frame is None:
                break
            out += self._handle(frame, now)
        return bytes(out)

    def _handle(self, frame: codec.Frame, now: float) -> bytes:
        self.frames_received += 1
        self.received.append(frame)
        if self.watchdog_ms:
            self._watchdog_deadline = now + self.watchdog_ms / 1000.0
        reply: codec.Reply
        if self._busy > 0:
            self._busy -= 1
            reply = codec.Nack(frame.cmd, NackCode.BUSY)
        elif self._nack_queue:
            reply = codec.Nack(frame.cmd, self._nack_queue.popleft())
        else:
            try:
                request = codec.parse_request(frame)
            except codec.MalformedMessage as exc:
                reply = codec.Nack(frame.cmd, exc.nack_code)
            else:
                reply = self._execute(request, frame.cmd, now)
        out = codec.encode(frame.seq, reply)
        if self._corrupt > 0:
            self._corrupt -= 1
            out = out[:-1] + bytes([out[-1] ^ 0x01])
        return out

    def _execute(self, req: codec.Request, cmd: int, now: float) -> codec.Reply:
        if isinstance(req, codec.Identify):
            return codec.IdentifyReply(self.led_count, codec.CHANNELS, self.slot_count, self.model,
                                       self.firmware, self.serial_number)
        if isinstance(req, codec.Status):
            return codec.StatusReply(
                temperature_centi_c=int(np.clip(round(self.temperature_c * 100), -32768, 32767)),
                current_ma=int(np.clip(round(self.current_a * 1000), 0, 0xFFFF)),
                faults=self.faults,
                active_slot=codec.DARK_SLOT if self.active_slot is None else self.active_slot,
                polarization=int(self.polarization), lit=self.lit)
        if isinstance(req, codec.UploadPattern):
            if req.slot >= self.slot_count:
                return codec.Nack(cmd, NackCode.BAD_SLOT)
            if req.offset + req.count > self.led_count:
                return codec.Nack(cmd, NackCode.BAD_ARGUMENT)
            new = self.slots[req.slot].copy()
            new[req.offset:req.offset + req.count] = req.to_array()
            if req.slot == self.active_slot and self.pattern_current_a(new) > self.max_current_a:
                return codec.Nack(cmd, NackCode.OVER_POWER_LIMIT)
            self.slots[req.slot] = new
            if req.slot == self.active_slot:
                self._notify_if_changed()
            return codec.UploadAck(req.slot, req.offset, req.count)
        if isinstance(req, codec.SelectSlot):
            if req.slot == codec.DARK_SLOT:
                self._darken()
                return codec.SelectAck(req.slot)
            if req.slot >= self.slot_count:
                return codec.Nack(cmd, NackCode.BAD_SLOT)
            pattern = self.slots[req.slot]
            if self.pattern_current_a(pattern) > self.max_current_a:
                return codec.Nack(cmd, NackCode.OVER_POWER_LIMIT)
            if self._over_temperature and pattern.any():
                return codec.Nack(cmd, NackCode.OVER_TEMPERATURE)
            self.active_slot = req.slot
            self._notify_if_changed()
            return codec.SelectAck(req.slot)
        if isinstance(req, codec.SetPolarization):
            try:
                self.polarization = Polarization(req.state)
            except ValueError:
                return codec.Nack(cmd, NackCode.BAD_ARGUMENT)
            self._notify_if_changed()
            return codec.PolarizationAck(req.state)
        if isinstance(req, codec.AllOff):
            self._watchdog_tripped = False
            self._darken()
            return codec.AllOffAck()
        if isinstance(req, codec.SetWatchdog):
            self.watchdog_ms = req.timeout_ms
            self._watchdog_tripped = False
            self._watchdog_deadline = now + req.timeout_ms / 1000.0 if req.timeout_ms else None
            return codec.WatchdogAck(req.timeout_ms)
        return codec.Nack(cmd, NackCode.UNKNOWN_COMMAND)   # pragma: no cover - parse_request covers all


class Ticker:
    """A daemon thread calling ``model.poll()`` every ``period_s`` (watchdog and over-temperature trips on
    time while the host is silent). Use as a context manager or ``start()`` / ``close()``."""

    def __init__(self, model: LedSphereModel, period_s: float = 0.01) -> None:
        self.model = model
        self.period_s = period_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="led-sphere-ticker", daemon=True)

    def start(self) -> "Ticker":
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self.model.poll()

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=1.0)

    def __enter__(self) -> "Ticker":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m simulators.led_sphere --url pty|tcp://127.0.0.1:PORT --leds N``: serve until Ctrl-C."""
    from simulators.serve import serve

    parser = argparse.ArgumentParser(prog="python -m simulators.led_sphere",
                                     description="Serve a simulated LED sphere (binary serial protocol).")
    parser.add_argument("--url", default="pty", help="'pty' (new pseudo-terminal) or tcp://HOST:PORT (port 0 = any)")
    parser.add_argument("--leds", type=int, default=64, help="number of LEDs (default 64)")
    parser.add_argument("--slots", type=int, default=16, help="pattern slots (default 16)")
    parser.add_argument("--model", default="SSS-LS1")
    parser.add_argument("--firmware", default="1.0.0")
    parser.add_argument("-v", "--verbose", action="store_true", help="log light changes and faults")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING)

    def report(rgb: npt.NDArray[np.float64], pol: Polarization) -> None:
        log.info("light: %d LEDs lit, mean %.3f, polarization %s", int((rgb > 0).any(axis=1).sum()),
                 float(rgb.mean()), pol.name)

    model = LedSphereModel(led_count=args.leds, slots=args.slots, model=args.model, firmware=args.firmware,
                           on_light_change=report)
    try:
        server = serve(model, args.url)
    except (ValueError, OSError) as exc:
        parser.error(str(exc))
    with server, Ticker(model):
        print(server.url, flush=True)
        try:
            while True:
                time.sleep(0.2)
        except KeyboardInterrupt:
            pass
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
