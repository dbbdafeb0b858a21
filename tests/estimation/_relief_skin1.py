"""The cached Monte Carlo capture tests/data/relief_skin1 (skin1 relief slab, 64 x 64 px of 0.2 mm, 128 spp; made by
tests/data/make_relief_capture.py), read once for the relief tests: frames, LED rig, albedo scale, true normals and
the orthographic view directions."""
from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from estimation.gradients import LedRig, albedo_scale_from_radiometry
from rig.files.imageio import read_image

DATA = Path(__file__).resolve().parents[1] / "data" / "relief_skin1"
ETA = 1.3
#: the slab's true reduced scattering and absorption per channel (/mm)
SSP, SA = np.array([0.74, 0.88, 1.01]), np.array([0.032, 0.17, 0.48])


def load_relief_skin1() -> dict[str, Any]:
    """{"frames": {(pattern, polarization): image}, "rig": LedRig, "scale": albedo scale, "true_normals": (H, W, 3),
    "view": (H, W, 3) float32 view directions (the camera looks along -y)}."""
    cfg = tomllib.loads((DATA / "capture.toml").read_text())
    frames = {(f["pattern"], f["polarization"]): read_image(DATA / f["file"])[0] for f in cfg["frames"]}
    leds = np.load(DATA / "leds.npy")
    rig = LedRig.from_positions(leds[:, :3], leds[:, 3:])
    v = cfg["radiometry"]["value_per_radiance_per_s"] * cfg["frames"][0]["exposure_s"]
    scale = albedo_scale_from_radiometry([v] * 3, rig, eta=ETA)
    true_n = np.load(DATA / "true_normals.npy").astype(float)
    view = np.broadcast_to([0.0, -1.0, 0.0], true_n.shape).astype(np.float32)
    return {"frames": frames, "rig": rig, "scale": scale, "true_normals": true_n, "view": view}
