"""Simulated trigger boxes: the ESPER-style ASCII box (a sans-IO stream model for ``serve.py``) and a fake
USB HID trigger box at the driver's ``HidTransport`` seam.

Both decode the same wire format as the drivers (``drivers.trigger.esper`` / ``drivers.trigger.hid_box``
codecs) and call ``on_fire(exposure_s)`` *synchronously, before answering* the fire command, so when the
driver's ``fire()`` returns the simulated camera has been told.

Run one on a pty or a loopback TCP port for manual tests::

    python -m simulators.trigger --url pty
    python -m simulators.trigger --url tcp://127.0.0.1:5025
"""
from __future__ import annotations

import argparse
import collections
import sys
import threading
import time
from typing import Callable

from drivers.errors import ConnectionLost, ProtocolError
from drivers.trigger import esper_codec as ec
from drivers.trigger import hid_box_codec as hc

from .serve import Faults, serve

OnFire = Callable[[float], None]


class EsperTriggerModel:
    """Sans-IO model of an ESPER-style trigger box (``receive(bytes) -> bytes``, ``reset()``).

    Power-up state: mode 0, all outputs disabled, no bulb time, shot counter 0. Only mode 0 is simulated
    (``m<d>`` with d != 0 is answered ``err:2``). ``S`` counts a shot, calls ``on_fire(bulb_ms / 1000)`` and
    answers ``tenFour`` at the start of the exposure; the box is then busy for the bulb time on ``clock``, and
    an ``S`` meanwhile is answered ``err:4`` (BUSY) without firing. ``S`` while every output is disabled is
    answered ``err:5`` (NO_OUTPUTS) and fires nothing (``docs/protocols/trigger-boxes.md``).

    Fault hooks (cleared by :meth:`reset`): ``error_next`` answers the next command ``err:<code>`` without
    executing it; ``busy_next`` answers the next N ``S`` BUSY; ``garble_next`` replaces the next reply by these
    bytes; ``fire_without_camera`` acknowledges and counts ``S`` without telling the camera (an unplugged
    release cable). ``busy_during_exposure = False`` drops the BUSY window (a host that does not wait for its
    exposures, as the calibration's simulated world). Byte-level faults (mute, latency, split, corrupt, garbage)
    come from ``serve.Faults``.
    """

    def __init__(self, on_fire: OnFire | None = None, *, maker: str = "ESPER", model: str = "TriggerBox",
                 firmware: str = "1.0.0", serial: str = "TB-0001",
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.on_fire = on_fire
        self.clock = clock
        self.busy_during_exposure = True
        self.identity = ec.Identity(maker, model, firmware, serial)
        ec.encode_reply(self.identity)   # validate the fields now, not on the first '?'
        self.reset()

    def reset(self) -> None:
        self._buf = bytearray()
        self.mode = 0
        self.enabled: tuple[bool, ...] = (False,) * ec.OUTPUT_COUNT
        self.bulb_ms: int | None = None
        self.shots = 0
        self.fired: list[float] = []          # exposure_s of every shot that reached the camera
        self.commands: list[bytes] = []       # every command line received, for tests
        self.callback_errors: list[BaseException] = []
        self.error_next: int | None = None
        self.busy_next = 0
        self.garble_next: bytes | None = None
        self.fire_without_camera = False
        self.busy_until = float("-inf")

    def receive(self, data: bytes) -> bytes:
        self._buf += data
        out = bytearray()
        while True:
            end = self._buf.find(ec.TERMINATOR)
            if end < 0:
                if len(self._buf) > ec.MAX_LINE:      # a flood without newline: drop it, complain once
                    self._buf.clear()
                    out += ec.encode_reply(ec.ErrorReply(ec.ERR_UNKNOWN_COMMAND))
                return bytes(out)
            line = bytes(self._buf[:end]).rstrip(b"\r")
            del self._buf[:end + 1]
            if not line:
                continue
            self.commands.append(line)
            reply = self._handle(line)
            if self.garble_next is not None:
                reply, self.garble_next = self.garble_next, None
            out += reply

    def _handle(self, line: bytes) -> bytes:
        if self.error_next is not None:
            code, self.error_next = self.error_next, None
            return ec.encode_reply(ec.ErrorReply(code))
        try:
            cmd = ec.parse_command(line)
        except ProtocolError:
            return ec.encode_reply(ec.ErrorReply(ec.command_error_code(line)))
        if isinstance(cmd, ec.SetMode):
            if cmd.mode != 0:
                return ec.encode_reply(ec.ErrorReply(ec.ERR_BAD_ARGUMENT))
            self.mode = cmd.mode
        elif isinstance(cmd, ec.EnableOutputs):
            self.enabled = cmd.enabled
        elif isinstance(cmd, ec.SetBulb):
            self.bulb_ms = cmd.ms
        elif isinstance(cmd, ec.Identify):
            return ec.encode_reply(self.identity)
        elif isinstance(cmd, ec.GetCount):
            return ec.encode_reply(ec.ShotCount(self.shots))
        elif isinstance(cmd, ec.Fire):
            if self.bulb_ms is None:
                return ec.encode_reply(ec.ErrorReply(ec.ERR_NO_BULB))
            if self.busy_next > 0 or (self.busy_during_exposure and self.clock() < self.busy_until):
                self.busy_next = max(0, self.busy_next - 1)
                return ec.encode_reply(ec.ErrorReply(ec.ERR_BUSY))
            if not any(self.enabled):
                return ec.encode_reply(ec.ErrorReply(ec.ERR_NO_OUTPUTS))
            self.shots += 1
            self.busy_until = self.clock() + self.bulb_ms / 1000.0
            if not self.fire_without_camera:
                exposure_s = self.bulb_ms / 1000.0
                self.fired.append(exposure_s)
                if self.on_fire is not None:
                    try:
                        self.on_fire(exposure_s)
                    except Exception as exc:  # noqa: BLE001 - a camera-side bug must not kill the server
                        self.callback_errors.append(exc)
        return ec.encode_reply(ec.Ack())


def start_esper_simulator(url: str = "pty", on_fire: OnFire | None = None, faults: Faults | None = None):
    """Serve a new :class:`EsperTriggerModel` on ``url`` (``pty`` or ``tcp://127.0.0.1:0``).

    Returns ``(server, model)``; ``server.url`` is what ``open_esper_trigger`` opens; close the server.
    """
    model = EsperTriggerModel(on_fire)
    return serve(model, url, faults), model


# ------------------------------------------------------------------------------------------ fake HID box
class FakeHidTriggerBox:
    """A fake HID trigger box implementing ``drivers.trigger.hid_box.HidTransport``.

    It decodes output reports with the driver's codec, keeps the box's state, and queues one input report
    per command. FIRE answers at once with ``busy`` set; the box stays busy for the bulb time on ``clock``.
    A malformed output report is ignored (as firmware would) and kept in ``bad_reports``.

    Fault hooks (cleared by :meth:`reset`): ``mute`` (no answers), ``stale_next`` (queue that many reports
    with a wrong sequence number before the next answer), ``garble_next`` (replace the next answer by these
    bytes), ``error_next`` (answer the next command with this result code), ``stuck_busy``, ``unplugged``
    (every call raises ``ConnectionLost``, like the hidapi wrapper when the cable is pulled).
    """

    def __init__(self, on_fire: OnFire | None = None, *, firmware: tuple[int, int] = (1, 0),
                 clock: Callable[[], float] = time.monotonic, manufacturer: str = "sssrig",
                 product: str = "SimTrigger HID", serial: str = "HID-0001") -> None:
        self.on_fire = on_fire
        self.firmware = firmware
        self.clock = clock
        self.manufacturer, self.product, self.serial = manufacturer, product, serial
        self._lock = threading.Lock()
        self._ready = threading.Condition(self._lock)
        self.reset()

    def reset(self) -> None:
        self._queue: collections.deque[bytes] = collections.deque()
        self.enabled_mask = 0
        self.bulb_ms = 0
        self.shots = 0
        self.busy_until = float("-inf")
        self.fired: list[float] = []
        self.received: list[hc.OutputReport] = []
        self.bad_reports: list[bytes] = []
        self.callback_errors: list[BaseException] = []
        self.closed = False
        self.unplugged = False
        self.mute = False
        self.stale_next = 0
        self.garble_next: bytes | None = None
        self.error_next: int | None = None
        self.stuck_busy = False

    def _busy(self) -> bool:
        return self.stuck_busy or self.clock() < self.busy_until

    def _status(self, seq: int, result: int = hc.RESULT_OK) -> bytes:
        return hc.encode_status(hc.StatusReport(seq, result, self.shots & hc.U32_MAX, self._busy(),
                                                self.enabled_mask, self.bulb_ms, self.firmware))

    def _execute(self, rep: hc.OutputReport) -> int:
        if rep.command == hc.CMD_GET_STATUS:
            return hc.RESULT_OK
        if rep.command == hc.CMD_ENABLE:
            if rep.arg & ~hc.ALL_OUTPUTS:
                return hc.RESULT_BAD_ARGUMENT
            self.enabled_mask = rep.arg
            return hc.RESULT_OK
        if rep.command == hc.CMD_SET_BULB:
            if rep.arg == 0:
                return hc.RESULT_BAD_ARGUMENT
            self.bulb_ms = rep.arg
            return hc.RESULT_OK
        if rep.command == hc.CMD_FIRE:
            if self.bulb_ms == 0:
                return hc.RESULT_NO_BULB
            if self._busy():
                return hc.RESULT_BUSY
            self.shots += 1
            exposure_s = self.bulb_ms / 1000.0
            self.busy_until = self.clock() + exposure_s
            if self.enabled_mask:
                self.fired.append(exposure_s)
                if self.on_fire is not None:
                    try:
                        self.on_fire(exposure_s)
                    except Exception as exc:  # noqa: BLE001
                        self.callback_errors.append(exc)
            return hc.RESULT_OK
        return hc.RESULT_UNKNOWN_COMMAND

    # -- HidTransport -----------------------------------------------------------------------------------
    def write(self, data: bytes) -> int:
        data = bytes(data)
        with self._lock:
            if self.closed or self.unplugged:
                raise ConnectionLost("fake HID trigger box: device is gone")
            try:
                rep = hc.decode_output(data)
            except ProtocolError:
                self.bad_reports.append(data)
                return len(data)
            self.received.append(rep)
            if self.error_next is not None:
                result, self.error_next = self.error_next, None
            else:
                result = self._execute(rep)
            if not self.mute:
                for k in range(self.stale_next):
                    self._queue.append(self._status((rep.seq - 1 - k) & 0xFF))
                self.stale_next = 0
                answer = self._status(rep.seq, result)
                if self.garble_next is not None:
                    answer, self.garble_next = self.garble_next, None
                self._queue.append(answer)
                self._ready.notify_all()
            return len(data)

    def read(self, n: int, timeout_ms: int) -> bytes:
        with self._lock:
            if self.closed or self.unplugged:
                raise ConnectionLost("fake HID trigger box: device is gone")
            if not self._queue:
                self._ready.wait(timeout_ms / 1000.0)
            if not self._queue:
                return b""
            return self._queue.popleft()[:n]

    def close(self) -> None:
        with self._lock:
            self.closed = True


# ------------------------------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m simulators.trigger",
                                     description="Serve a simulated ESPER-style trigger box.")
    parser.add_argument("--url", default="pty", help="'pty' or 'tcp://127.0.0.1:PORT' (default: pty)")
    parser.add_argument("--latency-s", type=float, default=0.0, help="delay before each reply")
    parser.add_argument("--quiet", action="store_true", help="do not log fires to stderr")
    args = parser.parse_args(argv)

    def log_fire(exposure_s: float) -> None:
        if not args.quiet:
            print(f"fire {exposure_s:.3f} s", file=sys.stderr, flush=True)

    try:
        server, _model = start_esper_simulator(args.url, log_fire, Faults(latency_s=args.latency_s))
    except (ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(server.url, flush=True)
    try:
        while True:
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    finally:
        server.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
