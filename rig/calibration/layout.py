"""Where the calibration targets are by design: camera-pose plates, surveyed LEDs, and the design geometry
(with every calibration target's approximate position, for aiming the total station)."""
from __future__ import annotations

import dataclasses
import re

import numpy as np
import numpy.typing as npt

from rig.config import RigConfig
from rig.acquire.geometry import RigGeometry, rig_geometry
from rig.config.calibration_settings import CalibrationSettings

FloatArray = npt.NDArray[np.float64]
POSE_TARGET = re.compile(r"^aruco_(\d+)$")
LED_TARGET = "led_{}"

__all__ = ["pose_targets", "survey_leds", "calibration_geometry", "LED_TARGET"]


def pose_targets(config: RigConfig, settings: CalibrationSettings) -> dict[str, tuple[float, float, float]]:
    """Design positions of the camera-pose plates, named ``aruco_<marker id>``.

    The rig config's ``[[targets]]`` of that name win; without any, ``pose_targets.count`` plates are laid out
    around the camera's look-at point on a square grid, at depths -depth..+depth along the view (alternating, so
    that the camera's pose is well conditioned), spread over ``fill`` of the half field of view."""
    named = {t.name: t.xyz_mm for t in config.targets if POSE_TARGET.match(t.name)}
    if named:
        return dict(named)
    p = settings.pose_targets
    geo = rig_geometry(config)
    cam = geo.camera
    look = np.asarray(config.camera.look_at_mm, float)
    dist = float(np.linalg.norm(look - cam.C))
    out = {}
    n = p.count
    cols = int(np.ceil(np.sqrt(n)))
    rows = int(np.ceil(n / cols))
    shift = (p.marker_mm + p.margin_mm) / 2          # the marker sits left of the reflector: centre the plate
    k = 0
    for r in range(rows):
        for c in range(cols):
            if k >= n:
                break
            fx = (c + 0.5) / cols * 2 - 1
            fy = (r + 0.5) / rows * 2 - 1
            depth = p.depth_mm * (1 if (r + c) % 2 else -1) * (0.5 + 0.5 * ((k * 0.618) % 1.0))
            d = dist + depth
            x = fx * p.fill * (cam.width_px / 2) / cam.fx_px * d
            y = fy * p.fill * (cam.height_px / 2) / cam.fy_px * d
            pt = cam.C + cam.R.T @ np.array([x + shift, y, d])
            out[f"aruco_{p.first_id + k}"] = tuple(float(v) for v in np.round(pt, 3))
            k += 1
    return out


def survey_leds(config: RigConfig, settings: CalibrationSettings, geometry: RigGeometry | None = None) -> list[int]:
    """LED indices carrying reflectors: ``led_survey.leds``, or ``count`` LEDs chosen by farthest-point
    sampling over the design directions (an even spread constrains the rigid fit best)."""
    s = settings.led_survey
    geo = geometry or rig_geometry(config)
    n = len(geo.led_directions)
    if s.leds:
        bad = [i for i in s.leds if not 0 <= i < n]
        if bad:
            raise ValueError(f"calibration.led_survey.leds: LED indices {bad} outside [0, {n})")
        return list(s.leds)
    d = geo.led_directions
    far = np.linalg.norm(geo.led_positions_mm - np.asarray(config.total_station.station_xyz_mm), axis=1)
    candidates = np.flatnonzero(far >= s.min_distance_mm)
    if len(candidates) < 3:
        raise ValueError(f"calibration.led_survey: only {len(candidates)} LEDs are >= {s.min_distance_mm:g} mm from "
                         "the total station; list the LEDs to survey (leds = [...]) or lower min_distance_mm")
    dc = d[candidates]
    chosen = [int(np.argmax(dc[:, 2]))]
    dmin = np.full(len(candidates), np.inf)
    while len(chosen) < min(s.count, len(candidates)):
        dmin = np.minimum(dmin, np.linalg.norm(dc - dc[chosen[-1]], axis=1))
        chosen.append(int(np.argmax(dmin)))
    return sorted(int(candidates[i]) for i in chosen)


def calibration_geometry(config: RigConfig, settings: CalibrationSettings) -> RigGeometry:
    """The design geometry whose ``targets`` also hold the pose plates and the surveyed LEDs (design
    positions; the total station's ATR fine-points onto the real reflectors)."""
    geo = rig_geometry(config)
    targets = dict(geo.targets)
    targets.update(pose_targets(config, settings))
    for i in survey_leds(config, settings, geo):
        targets[LED_TARGET.format(i)] = tuple(float(v) for v in geo.led_positions_mm[i])
    return dataclasses.replace(geo, targets=targets)
