"""Shutter release through a serial port's modem-control lines.

RTS drives the camera's *focus* (half-press) contact and DTR its *shutter* contact through opto-isolators
(wiring: ``docs/protocols/trigger-boxes.md``). :meth:`SerialRelease.fire` asserts RTS, waits
``focus_lead_s``, asserts DTR for the exposure (camera in bulb mode), then releases DTR and RTS - always,
also when interrupted. There is no answer from the camera: the lines are write-only.

pyserial asserts RTS and DTR when it opens a port, which would fire a camera wired this way, so
:func:`open_serial_release` opens with both lines low. A pty cannot drive modem lines (``ENOTTY``); test on
``loop://``, which mirrors RTS->CTS and DTR->DSR.
"""
from __future__ import annotations

import threading
import time
from typing import Any, Callable

import serial

from ..contracts import DeviceIdentity
from ..errors import ConnectionLost
from .exposure import check_exposure_range, exposure_ms


class SerialRelease:
    """Trigger on an injected, already-open pyserial port; the constructor does no I/O.

    ``sleep`` is injectable so tests can observe the lines in each phase.
    """

    def __init__(self, port: Any, *, focus_lead_s: float = 0.1, min_exposure_s: float = 0.001,
                 max_exposure_s: float = 60.0, sleep: Callable[[float], None] = time.sleep,
                 name: str = "serial-release") -> None:
        if focus_lead_s < 0:
            raise ValueError(f"focus_lead_s must be >= 0, got {focus_lead_s}")
        check_exposure_range(min_exposure_s, max_exposure_s)
        self._port = port
        self.focus_lead_s = focus_lead_s
        self.min_exposure_s = min_exposure_s
        self.max_exposure_s = max_exposure_s
        self._sleep = sleep
        self.name = name
        self._lock = threading.Lock()
        self._closed = False

    @property
    def port(self) -> Any:
        """The pyserial port whose RTS/DTR lines this release drives."""
        return self._port

    def _set(self, line: str, value: bool) -> None:
        try:
            setattr(self._port, line, value)
        except (serial.SerialException, OSError) as exc:
            raise ConnectionLost(f"{self.name}: cannot set {line.upper()}={int(value)} ({exc}); the transport "
                                 "must support modem lines (a pty does not: use a serial port or loop://)"
                                 ) from exc

    def identify(self) -> DeviceIdentity:
        return DeviceIdentity(kind="trigger", model="serial-release", firmware="",
                              serial_number=str(getattr(self._port, "port", "") or ""),
                              extra={"focus_line": "RTS", "shutter_line": "DTR",
                                     "focus_lead_s": self.focus_lead_s})

    def release(self) -> None:
        """De-assert both lines (safe state). Idempotent."""
        self._set("dtr", False)
        self._set("rts", False)

    def fire(self, exposure_s: float) -> None:
        """RTS high, ``focus_lead_s``, DTR high for ``exposure_s`` (whole ms), then DTR and RTS low."""
        ms = exposure_ms(exposure_s, min_exposure_s=self.min_exposure_s, max_exposure_s=self.max_exposure_s)
        with self._lock:
            if self._closed:
                raise ConnectionLost(f"{self.name}: trigger is closed")
            try:
                self._set("rts", True)
                if self.focus_lead_s:
                    self._sleep(self.focus_lead_s)
                self._set("dtr", True)
                self._sleep(ms / 1000.0)
            finally:
                # Release on every exit path; a failure here must not hide the original exception.
                for line in ("dtr", "rts"):
                    try:
                        self._set(line, False)
                    except ConnectionLost:
                        pass

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                self.release()
            except ConnectionLost:
                pass
            try:
                self._port.close()
            except (serial.SerialException, OSError):
                pass

    def __enter__(self) -> "SerialRelease":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_serial_release(url: str, **kwargs: Any) -> SerialRelease:
    """Open ``url`` (a serial device or ``loop://``) with RTS and DTR low from the start, and wrap it."""
    try:
        port = serial.serial_for_url(url, do_not_open=True)
        port.rts = False
        port.dtr = False
        port.open()
    except (serial.SerialException, OSError, ValueError) as exc:
        raise ConnectionLost(f"cannot open serial release {url!r}: {exc}") from exc
    if "name" not in kwargs:
        kwargs["name"] = f"serial-release {url}"
    return SerialRelease(port, **kwargs)

