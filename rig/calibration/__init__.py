"""Scripted calibration of the rig (issue 7; ``docs/calibration.md``).

One module per step, each with ``shots(ctx)`` (what to capture, as plan items run by ``rig.acquire.runner``),
``compute(ctx, captured)`` (the section of the calibration file) and ``compare(ctx, result)`` (recovered vs the
simulator's truth): :mod:`.intrinsics`, :mod:`.rig_frame`, :mod:`.led_directions`, :mod:`.gains`,
:mod:`.extinction`, :mod:`.radiometry`, :mod:`.seed_k`. :mod:`.run` runs them (``run_step``, ``run_all``),
:mod:`.store` reads and writes the versioned calibration file (``load_calibration``), :mod:`.cli` adds
``rig calibrate STEP``.
"""
from __future__ import annotations

STEP_NAMES = ("intrinsics", "rig-frame", "led-directions", "gains", "extinction", "radiometry", "seed-k")

__all__ = ["STEP_NAMES"]
