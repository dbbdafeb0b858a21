"""Write frames and an LED calibration into a capture folder (docs/capture-folder.md), for folders made by programs.

The benchmarks' and test data's renderers (``benchmarks/gradients_cases.py``, ``benchmarks/relief_reference.py``,
``tests/data/make_relief_capture.py``) write their captures through :func:`write_frames_and_leds`, so the frame
file names and the ``[[frames]]`` / ``[leds]`` entries are spelt once, as :func:`.reading.load_capture` reads them.
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["write_frames_and_leds"]


def write_frames_and_leds(folder: Path, frames: Mapping[tuple[str, str], ArrayLike], exposure_s: float,
                          leds_position_intensity: ArrayLike) -> list[str]:
    """Write each ``(pattern, polarization)`` frame as ``frames/<pattern>_<polarization>.exr`` (sorted), the LED
    calibration (N, 6: position mm, RGB intensity) as ``leds.npy``; return the ``capture.toml`` lines of the
    ``[[frames]]`` entries (exposure ``exposure_s``) and of ``[leds]``."""
    from rig.files.imageio import write_exr

    folder = Path(folder)
    lines: list[str] = []
    for (pattern, pol), img in sorted(frames.items()):
        write_exr(folder / f"frames/{pattern}_{pol}.exr", np.asarray(img))
        lines += ["[[frames]]", f'file = "frames/{pattern}_{pol}.exr"', f'pattern = "{pattern}"',
                  f'polarization = "{pol}"', f"exposure_s = {exposure_s}", ""]
    np.save(folder / "leds.npy", np.asarray(leds_position_intensity))
    return lines + ["[leds]", 'file = "leds.npy"', ""]
