"""LED-sphere layouts: class-I geodesic subdivision of an icosahedron (10 f^2 + 2 vertices)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from estimation.camera import PinholeCamera

if TYPE_CHECKING:
    from rig.config import RigConfig


def _icosahedron() -> tuple[np.ndarray, np.ndarray]:
    t = (1.0 + 5 ** 0.5) / 2.0
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t],
                  [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                  [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
                  [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    return v / np.linalg.norm(v, axis=1, keepdims=True), f


def geodesic_directions(frequency: int) -> npt.NDArray[np.float64]:
    """Unit vectors of a class-I geodesic sphere of the given frequency (10 f^2 + 2 points)."""
    if frequency < 1:
        raise ValueError(f"geodesic frequency must be >= 1, got {frequency}")
    v, faces = _icosahedron()
    pts = []
    for a, b, c in faces:
        for i in range(frequency + 1):
            for j in range(frequency + 1 - i):
                k = frequency - i - j
                pts.append((i * v[a] + j * v[b] + k * v[c]) / frequency)
    p = np.asarray(pts)
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    # merge the points shared by neighbouring faces
    key = np.round(p * 1e6).astype(np.int64)
    _, idx = np.unique(key, axis=0, return_index=True)
    out = p[np.sort(idx)]
    expected = 10 * frequency ** 2 + 2
    if len(out) != expected:  # pragma: no cover - a geometry bug, not user input
        raise RuntimeError(f"geodesic frequency {frequency}: {len(out)} points, expected {expected}")
    return out


def led_layout(frequency: int, radius_mm: float, min_elevation_deg: float = -90.0
               ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """LED positions (N, 3) in mm and unit directions (N, 3) from the sphere centre, ordered by index.

    LEDs below ``min_elevation_deg`` (floor, camera stand) are left out.
    """
    d = geodesic_directions(frequency)
    keep = d[:, 2] >= np.sin(np.radians(min_elevation_deg)) - 1e-12
    d = d[keep]
    order = np.lexsort((np.arctan2(d[:, 1], d[:, 0]), -d[:, 2]))  # top to bottom, then by azimuth
    d = d[order]
    return d * radius_mm, d


@dataclass
class RigGeometry:
    led_positions_mm: np.ndarray
    led_directions: np.ndarray
    camera: PinholeCamera
    key_led: int
    targets: dict[str, tuple[float, float, float]]


def rig_geometry(config: "RigConfig") -> RigGeometry:
    s, c = config.sphere, config.camera
    pos, dirs = led_layout(s.geodesic_frequency, s.radius_mm, s.min_elevation_deg)
    cam = PinholeCamera.looking_at(width_px=c.width_px, height_px=c.height_px, fx_px=c.fx_px,
                                   position_mm=c.position_mm, target_mm=c.look_at_mm, up=c.up)
    from rig.acquire.patterns import nearest_led
    key = nearest_led(dirs, config.estimation.key_light_direction)
    targets = {t.name: t.xyz_mm for t in config.targets}
    targets["key_led"] = tuple(float(v) for v in pos[key])
    return RigGeometry(pos, dirs, cam, key, targets)


def geometry_to_dict(g: RigGeometry) -> dict:
    """The manifest's ``geometry`` block (docs/session-format.md)."""
    c = g.camera
    return {"led_positions_mm": g.led_positions_mm.tolist(), "led_directions": g.led_directions.tolist(),
            "key_led": g.key_led,
            "camera": {"model": "pinhole", "width_px": c.width_px, "height_px": c.height_px,
                       "fx_px": c.fx_px, "fy_px": c.fy_px, "cx_px": c.cx_px, "cy_px": c.cy_px,
                       "rotation": [list(r) for r in c.rotation], "center_mm": list(c.center_mm)}}


def camera_from_dict(d: dict) -> PinholeCamera:
    return PinholeCamera(int(d["width_px"]), int(d["height_px"]), float(d["fx_px"]), float(d["fy_px"]),
                         float(d["cx_px"]), float(d["cy_px"]), tuple(tuple(map(float, r)) for r in d["rotation"]),
                         tuple(map(float, d["center_mm"])))
