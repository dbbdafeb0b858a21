"""Transports chosen by URL.

Every byte-stream device is opened through :func:`open_transport`, which hands the URL to
``serial.serial_for_url`` (pyserial 3.5): a device path (``/dev/ttyUSB0``, a pty's slave path),
``socket://host:port`` (raw TCP), ``loop://`` (in-memory loopback, mirrors RTS->CTS and DTR->DSR),
``spy://`` (hexdump wrapper) or ``rfc2217://``. The config therefore chooses real hardware, a simulator
on a pty or on loopback TCP with no code change.
"""
from __future__ import annotations

import termios
import time
from typing import Protocol, runtime_checkable

import serial

from .errors import ConnectionLost, DeviceTimeout

# pyserial on a pty whose other end is gone raises termios.error, which is not an OSError
_PORT_ERRORS = (serial.SerialException, OSError, termios.error)


@runtime_checkable
class ByteTransport(Protocol):
    """The slice of a pyserial port that drivers use."""

    timeout: float | None

    def write(self, data: bytes) -> int | None: ...
    def read(self, size: int = 1) -> bytes: ...
    def reset_input_buffer(self) -> None: ...
    def close(self) -> None: ...


def open_transport(url: str, *, baudrate: int = 115200, timeout_s: float = 1.0) -> serial.SerialBase:
    """Open a byte transport for ``url``; raise :class:`ConnectionLost` naming the URL if it cannot open."""
    try:
        port = serial.serial_for_url(url, baudrate=baudrate, timeout=timeout_s, write_timeout=timeout_s)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise ConnectionLost(f"cannot open transport {url!r}: {exc}") from exc
    return port


def read_exact(port: ByteTransport, size: int, *, timeout_s: float, what: str) -> bytes:
    """Read exactly ``size`` bytes or raise :class:`DeviceTimeout` after ``timeout_s`` seconds."""
    buf = bytearray()
    deadline = time.monotonic() + timeout_s
    while len(buf) < size:
        try:
            chunk = port.read(size - len(buf))
        except _PORT_ERRORS as exc:
            raise ConnectionLost(f"transport lost while reading {what}: {exc}") from exc
        if chunk:
            buf += chunk
        elif time.monotonic() >= deadline:
            raise DeviceTimeout(f"timed out after {timeout_s:.3g} s waiting for {what} "
                                f"({len(buf)} of {size} bytes received)")
    return bytes(buf)


def write_all(port: ByteTransport, data: bytes, *, what: str) -> None:
    """Write ``data``; a failing port becomes :class:`ConnectionLost`."""
    try:
        port.write(data)
        flush = getattr(port, "flush", None)
        if flush is not None:
            flush()
    except _PORT_ERRORS as exc:
        raise ConnectionLost(f"transport lost while writing {what}: {exc}") from exc
