"""LED sphere over Modbus RTU / Modbus TCP (register map in ``registers.py``, protocol document in
``docs/protocols/led-sphere-modbus.md``)."""
from __future__ import annotations

from typing import Any

__all__ = ["LedSphereModbus", "open_led_sphere_modbus", "parse_modbus_url"]


def __getattr__(name: str) -> Any:
    # Lazy, so that ``python -m drivers.led_sphere_modbus.registers`` does not import the module twice.
    if name in __all__:
        from . import driver

        return getattr(driver, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
