"""What a calibration step works with: the rig config, the calibration settings, the design geometry (with the
calibration targets), the calibration so far, and (simulated runs) the simulated world."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from drivers.errors import RigError
from estimation.camera import PinholeCamera

from rig.config import RigConfig
from rig.acquire.geometry import RigGeometry
from rig.files.camera_intrinsics import Intrinsics
from rig.config.calibration_settings import CalibrationSettings
from rig.files.calibration_store import Calibration

__all__ = ["StepContext", "StepOutput", "CalibrationFailed"]


class CalibrationFailed(RigError, ValueError):
    """A calibration step could not capture or compute its result (the message names the session)."""


@dataclass
class StepOutput:
    """A step's section of the calibration file (``result``, ``residuals``), the earlier sections and design
    values it used (``inputs``, recorded in the provenance) and a few human-readable summary lines."""

    result: dict[str, Any]
    residuals: dict[str, Any]
    inputs: dict[str, Any] = field(default_factory=dict)
    summary: list[str] = field(default_factory=list)


@dataclass
class StepContext:
    config: RigConfig
    settings: CalibrationSettings
    geometry: RigGeometry
    prior: Calibration | None = None
    world: Any | None = None                 # SimulatedCalibrationWorld in simulated runs
    say: Callable[[str], None] = lambda m: None
    used: dict[str, Any] = field(default_factory=dict)
    pattern_peak: float | None = None        # a step may dim its patterns (set by its ``shots``)

    # -- earlier calibrations, or the design values (recorded in ``used``) ----------------------------------
    def intrinsics(self) -> Intrinsics:
        if self.prior is not None and self.prior.has("intrinsics"):
            self.used["intrinsics"] = f"calibrated (revision {self.prior.section('intrinsics')['revision']})"
            return self.prior.intrinsics()
        self.used["intrinsics"] = "design (config [camera], no distortion)"
        return Intrinsics.from_pinhole(self.geometry.camera)

    def camera_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """(rotation rows = camera axes, centre mm) in the rig frame."""
        if self.prior is not None and self.prior.has("rig_frame"):
            r = self.prior.result("rig_frame")["camera"]
            self.used["camera_pose"] = f"calibrated (revision {self.prior.section('rig_frame')['revision']})"
            return np.asarray(r["rotation"], float), np.asarray(r["center_mm"], float)
        self.used["camera_pose"] = "design (config [camera] position_mm, look_at_mm)"
        return self.geometry.camera.R, self.geometry.camera.C

    def camera(self) -> PinholeCamera:
        R, C = self.camera_pose()
        return self.intrinsics().pinhole(R, C)

    def led_positions_mm(self) -> np.ndarray:
        if self.prior is not None and self.prior.has("rig_frame"):
            self.used["led_positions"] = "survey-refined (rig_frame)"
            return self.prior.led_positions_mm()
        self.used["led_positions"] = "design (geodesic layout of [sphere])"
        return np.asarray(self.geometry.led_positions_mm, float)

    def led_rig(self) -> Any:
        """LedRig from everything calibrated so far (design values where not)."""
        inten = np.asarray(self.config.sphere.led_intensity, float)
        if self.prior is None:
            from estimation.gradients import LedRig

            self.used["led_rig"] = "design"
            return LedRig.from_positions(self.geometry.led_positions_mm, np.broadcast_to(inten, (len(
                self.geometry.led_positions_mm), 3)))
        self.used["led_rig"] = {k: self.prior.has(k) for k in ("rig_frame", "led_directions", "gains")}
        return self.prior.led_rig(self.geometry.led_positions_mm, inten)
