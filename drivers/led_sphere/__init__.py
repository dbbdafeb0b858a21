"""LED sphere (``contracts.LightSource``) on a serial or TCP byte transport.

* :mod:`.codec` - sans-IO codec of the binary protocol (``docs/protocols/led-sphere-serial.md``), shared with
  ``simulators.led_sphere``.
* :mod:`.driver` - :class:`LedSphereSerial` (an injected, already-open transport) and
  :func:`open_led_sphere_serial` (opens one by URL).

Every ``upload_pattern`` is checked against the configured current and duty limits before anything is sent
(:class:`~drivers.errors.LimitError`).
"""
from __future__ import annotations

from .driver import LedSphereSerial, open_led_sphere_serial

__all__ = ["LedSphereSerial", "open_led_sphere_serial"]
