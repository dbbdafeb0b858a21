"""Run a capture plan on devices into a session; the LEDs are switched off on every exit path."""
from __future__ import annotations

import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from drivers.contracts import Camera, LightSource, Polarization, PositionFeed, Trigger

from .patterns import pattern_rgb16
from .plan import Step
from .session import Session, now_iso


@dataclass
class Devices:
    light: LightSource
    trigger: Trigger
    camera: Camera
    feed: PositionFeed | None = None

    def close(self) -> None:
        for dev in (self.light, self.trigger, self.camera, self.feed):
            if dev is not None:
                try:
                    dev.close()
                except Exception:
                    pass


@dataclass
class RunResult:
    seconds_by_kind: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    steps_run: int = 0
    steps_skipped: int = 0


def run_plan(steps: list[Step], devices: Devices, session: Session, *, led_directions: np.ndarray,
             pattern_peak: float, settle_s: float = 0.0, fetch_timeout_s: float = 30.0,
             progress: Callable[[int, int, Step], None] | None = None) -> RunResult:
    """Execute ``steps`` in order, skipping those the session already completed (resume).

    Every frame goes to the session atomically and into its journal. On any exit (success, exception,
    KeyboardInterrupt) the sphere is switched off; the session's journal gets a ``stop`` event.
    """
    done = session.completed_steps()
    result = RunResult()
    status, reason = "aborted", None
    try:
        for step in steps:
            if progress:
                progress(step.index, len(steps), step)
            if step.index in done and step.kind in ("capture", "survey"):
                result.steps_skipped += 1
                continue
            t0 = time.perf_counter()
            _run_step(step, devices, session, led_directions, pattern_peak, settle_s, fetch_timeout_s)
            result.seconds_by_kind[step.kind] += time.perf_counter() - t0
            result.steps_run += 1
        status = "complete"
    except BaseException as exc:
        reason = f"{type(exc).__name__}: {exc}"
        raise
    finally:
        try:
            devices.light.all_off()
        finally:
            session.stop(status, reason)
    return result


def _run_step(step: Step, d: Devices, session: Session, led_directions: np.ndarray,
              peak: float, settle_s: float, fetch_timeout_s: float) -> None:
    p = step.params
    if step.kind == "upload":
        d.light.upload_pattern(p["slot"], pattern_rgb16(p["pattern"], led_directions, peak=peak,
                                                        key_led=p.get("key_led")))
    elif step.kind == "polarization":
        d.light.set_polarization(Polarization[p["state"].upper()])
    elif step.kind == "survey":
        if d.feed is None:
            raise RuntimeError(f"step {step.index}: survey of {p['target']!r} needs a position feed")
        pt = d.feed.measure(p["target"])
        session.add_survey(step.index, pt.name, pt.xyz_mm, pt.warning)
    elif step.kind == "capture":
        if p["slot"] is None:
            d.light.all_off()
        else:
            d.light.select_slot(p["slot"])
        if settle_s:
            time.sleep(settle_s)
        d.camera.arm()
        t_trigger = now_iso()
        d.trigger.fire(p["exposure_s"])
        frame = d.camera.fetch(fetch_timeout_s)
        if frame.path is None:
            raise RuntimeError(f"step {step.index}: the camera returned a frame without a file")
        session.add_frame(step.index, frame.path, pattern=p["pattern"], polarization=p["polarization"],
                          exposure_s=p["exposure_s"], t_trigger=t_trigger)
    elif step.kind == "all_off":
        d.light.all_off()
    else:
        raise ValueError(f"step {step.index}: unknown step kind {step.kind!r}")
