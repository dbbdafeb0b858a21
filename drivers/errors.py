"""Typed error hierarchy of the hardware layer.

Leaves also subclass the matching builtin, so ``except TimeoutError`` catches a device timeout and
``except ValueError`` catches a limit violation (the habit of bluesky/ophyd-async, see
``shared/reference/style.md``). Device error codes become exceptions at the driver boundary.
"""
from __future__ import annotations


class RigError(Exception):
    """Base of every error raised by sssrig's own code."""


class DeviceError(RigError):
    """Base of errors raised while talking to a device."""


class DeviceTimeout(DeviceError, TimeoutError):
    """A device did not answer within the read timeout."""


class ProtocolError(DeviceError):
    """Bytes on the wire do not form a valid frame (bad framing, bad CRC, unknown field)."""


class DeviceRejected(DeviceError):
    """The device answered but refused the command; ``code`` is the device's own error code."""

    def __init__(self, message: str, code: int, *, name: str | None = None) -> None:
        super().__init__(f"{message} (device code {code}{' ' + name if name else ''})")
        self.code = code
        self.name = name


class DeviceBusy(DeviceRejected):
    """The device refused because it is busy; retrying later may succeed."""


class ConnectionLost(DeviceError, ConnectionError):
    """The transport to the device went away (cable pulled, socket closed, pty gone)."""


class LimitError(RigError, ValueError):
    """A request exceeds a configured safety or range limit; nothing was sent to the device."""


class ConfigError(RigError, ValueError):
    """A configuration file is invalid. The message names the file, the field and what was expected."""

    def __init__(self, file: str, field: str, expected: str, got: object = None) -> None:
        got_part = "" if got is None else f", got {got!r}"
        super().__init__(f"{file}: field '{field}': expected {expected}{got_part}")
        self.file = file
        self.field = field
        self.expected = expected
