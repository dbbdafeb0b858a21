"""Lighting patterns of the sphere as (N, 3) uint16 arrays.

Spherical gradients after Ma et al. 2007: over LED directions w, constant P_c = 1, gradients
P_i = (w_i + 1)/2 and complements P~_i = (1 - w_i)/2 for i in x, y, z (shared/reference/science.md §3).
"""
from __future__ import annotations

import numpy as np
import numpy.typing as npt

FULL_SCALE = 65535
GRADIENT_PATTERNS = ("full", "x", "y", "z", "x_c", "y_c", "z_c")


def pattern_values(name: str, directions: npt.ArrayLike, *, key_led: int | None = None
                   ) -> npt.NDArray[np.float64]:
    """Per-LED relative value in [0, 1] (N,) of a named pattern."""
    d = np.asarray(directions, float)
    axes = {"x": 0, "y": 1, "z": 2}
    if name == "full":
        return np.ones(len(d))
    if name == "dark":
        return np.zeros(len(d))
    if name in axes:
        return (d[:, axes[name]] + 1.0) / 2.0
    if name.endswith("_c") and name[:-2] in axes:
        return (1.0 - d[:, axes[name[:-2]]]) / 2.0
    if name == "key":
        if key_led is None or not 0 <= key_led < len(d):
            raise ValueError(f"pattern 'key' needs a key LED index in [0, {len(d)}), got {key_led}")
        v = np.zeros(len(d))
        v[key_led] = 1.0
        return v
    raise ValueError(f"unknown pattern {name!r}: expected one of dark, key, "
                     + ", ".join(GRADIENT_PATTERNS))


def pattern_rgb16(name: str, directions: npt.ArrayLike, *, peak: float = 1.0,
                  key_led: int | None = None) -> npt.NDArray[np.uint16]:
    """The (N, 3) uint16 pattern uploaded to the sphere (white: equal R, G, B)."""
    v = pattern_values(name, directions, key_led=key_led) * peak
    q = np.round(np.clip(v, 0.0, 1.0) * FULL_SCALE).astype(np.uint16)
    return np.repeat(q[:, None], 3, axis=1)


def nearest_led(directions: npt.ArrayLike, wanted: npt.ArrayLike) -> int:
    w = np.asarray(wanted, float)
    w = w / np.linalg.norm(w)
    return int(np.argmax(np.asarray(directions, float) @ w))
