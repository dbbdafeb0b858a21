"""Device contracts: small typed Protocols named for what a device can do, plus their value types.

The runner and the calibration code talk to devices only through these contracts, so a driver for real
hardware, a driver talking to a simulator over a pty, and a driver over Modbus are interchangeable
(the habit of bluesky's ``protocols.py``; see ``shared/reference/style.md``).
"""
from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt


class Polarization(enum.IntEnum):
    """State of the sphere's switchable polarizer banks relative to the camera's analyzer."""

    NONE = 0       # no polarizer in the light path
    PARALLEL = 1   # LED polarizers parallel to the camera analyzer: diffuse/2 + specular
    CROSS = 2      # crossed: specular extinguished, diffuse/2 remains


@dataclass(frozen=True)
class DeviceIdentity:
    """What a device says it is. ``extra`` holds device-specific fields (LED count, serial number...)."""

    kind: str
    model: str
    firmware: str
    serial_number: str = ""
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class LightStatus:
    """Health of a light source."""

    temperature_c: float
    current_a: float
    fault_flags: int
    active_slot: int | None
    polarization: Polarization
    lit: bool

    @property
    def over_temperature(self) -> bool:
        return bool(self.fault_flags & 0x01)


@dataclass(frozen=True)
class RawFrame:
    """A linear camera frame: ``rgb`` is float32 (H, W, 3), black-subtracted and scaled so that the
    sensor's white level is 1.0; no gamma, no white balance, no auto-brightness."""

    rgb: npt.NDArray[np.float32]
    exposure_s: float
    path: str | None = None
    metadata: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class SurveyedPoint:
    """A target's coordinates in the rig frame (mm) as measured by the position feed."""

    name: str
    xyz_mm: tuple[float, float, float]
    warning: str | None = None   # e.g. "TMC_ACCURACY_GUARANTEE": usable, but say so


@runtime_checkable
class LightSource(Protocol):
    """An LED sphere with preloadable pattern slots and switchable polarizer banks."""

    @property
    def led_count(self) -> int: ...
    def identify(self) -> DeviceIdentity: ...
    def upload_pattern(self, slot: int, rgb16: npt.NDArray[np.uint16]) -> None:
        """Store a (led_count, 3) uint16 pattern in ``slot``; refuse it first if over the limits."""
    def select_slot(self, slot: int) -> None: ...
    def set_polarization(self, state: Polarization) -> None: ...
    def all_off(self) -> None:
        """Darken every LED. Idempotent; must be safe to call on any exit path."""
    def status(self) -> LightStatus: ...
    def close(self) -> None: ...


@runtime_checkable
class Trigger(Protocol):
    """Something that opens the camera's shutter for a given exposure."""

    def identify(self) -> DeviceIdentity: ...
    def fire(self, exposure_s: float) -> None: ...
    def close(self) -> None: ...


@runtime_checkable
class Camera(Protocol):
    """A source of linear RAW frames. ``arm`` before the trigger fires, ``fetch`` the frame after."""

    def identify(self) -> DeviceIdentity: ...
    def arm(self) -> None: ...
    def fetch(self, timeout_s: float) -> RawFrame: ...
    def close(self) -> None: ...


@runtime_checkable
class PositionFeed(Protocol):
    """A surveying instrument that returns named targets' coordinates in the rig frame."""

    def identify(self) -> DeviceIdentity: ...
    def measure(self, target: str) -> SurveyedPoint: ...
    def close(self) -> None: ...
