"""Calibration captures through the same plans and runner as object captures.

A calibration step describes what it needs as a list of :class:`Shot` (one frame: a pattern — every LED
``full``, one LED ``key``, or the sphere dark ``ambient`` — a polarizer state and an exposure, optionally after
an operator action such as "place the mirror ball") and :class:`Survey` items (a total-station target).
:func:`build_plan` turns them into ``rig.plan.Step`` rows (upload, polarization, checkpoint, select, trigger,
fetch, survey, all_off) that ``rig.runner.run_plan`` executes into a session folder, exactly as ``rig capture``
does; frames are then read back from the session with ``drivers.camera.raw.load_linear``.

Operator actions are ``checkpoint`` steps whose params carry ``operator`` (what to do); :func:`capture` passes
them to an ``operator`` callback from the runner's progress hook before the checkpoint runs. On a real rig the
CLI prints the instruction and waits for Enter; in simulation the callback moves the simulated target
(:class:`rig.calibration.simworld.SimulatedCalibrationWorld`).
"""
from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import math
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np
import numpy.typing as npt

from drivers.errors import LimitError

from ..config import RigConfig
from ..geometry import RigGeometry, geometry_to_dict, rig_geometry
from ..plan import Step, pattern_current_a, pattern_for
from ..session import FrameRecord, Session, validate_session_name
from .context import CalibrationFailed

FloatArray = npt.NDArray[np.float64]
LIT_PATTERNS = ("full", "key", "x", "y", "z", "x_c", "y_c", "z_c")

__all__ = ["Shot", "Survey", "Captured", "build_plan", "capture", "exposure_ms", "design_value_per_radiance",
           "displayed_drive", "exposure_and_peak", "design_irradiance", "exposure_for", "LIT_PATTERNS"]


@dataclass(frozen=True)
class Shot:
    """One calibration frame. ``label`` names it in the session (letters, digits, '_')."""

    label: str
    exposure_s: float
    pattern: str = "full"             # "full" | "key" (one LED: ``led``) | a gradient | "ambient" (sphere dark)
    led: int | None = None
    polarization: str = "cross"       # "cross" | "parallel" | "none"
    operator: dict[str, Any] | None = None   # an action before this frame: {"say": "...", "target": ..., ...}

    def __post_init__(self) -> None:
        if self.pattern not in LIT_PATTERNS + ("ambient",):
            raise ValueError(f"shot {self.label!r}: pattern {self.pattern!r}, expected one of "
                             + ", ".join(LIT_PATTERNS + ("ambient",)))
        if (self.pattern == "key") != (self.led is not None):
            raise ValueError(f"shot {self.label!r}: pattern 'key' needs an LED index (and only it)")
        if self.polarization not in ("cross", "parallel", "none"):
            raise ValueError(f"shot {self.label!r}: polarization {self.polarization!r}")
        if not (self.exposure_s > 0 and math.isfinite(self.exposure_s)):
            raise ValueError(f"shot {self.label!r}: exposure_s must be > 0, got {self.exposure_s!r}")


@dataclass(frozen=True)
class Survey:
    """Measure a named total-station target (its position goes into the session journal)."""

    target: str
    operator: dict[str, Any] | None = None


def exposure_ms(seconds: float, config: RigConfig) -> float:
    """An exposure rounded to the trigger's whole milliseconds and clamped to its limits."""
    t = max(config.trigger.min_exposure_s, min(config.trigger.max_exposure_s, float(seconds)))
    return max(0.001, round(t * 1000.0) / 1000.0)


def design_value_per_radiance(config: RigConfig, exposure_s: float) -> float:
    """Frame value (white level = 1) per unit radiance of the camera's design response."""
    c = config.camera
    return c.gain_dn_per_unit * exposure_s / (c.white_level_dn - c.black_level_dn)


def displayed_drive(config: RigConfig, peak: float | None = None) -> float:
    """The drive level (0..1) every lit LED of a calibration pattern shows: the capture's pattern peak
    (``peak``, default ``[sphere] pattern_peak``) in 16 bits."""
    return round((config.sphere.pattern_peak if peak is None else peak) * 65535) / 65535


def design_irradiance(config: RigConfig, point_mm: npt.ArrayLike, normal: npt.ArrayLike,
                      leds: Sequence[int] | None = None, geometry: RigGeometry | None = None,
                      peak: float | None = None) -> float:
    """Irradiance (grey, design units) on a surface at ``point_mm`` facing ``normal`` from the design LEDs
    (all of them, or ``leds``) at the patterns' peak drive (``peak``, default ``[sphere] pattern_peak``)."""
    geo = geometry or rig_geometry(config)
    pos = geo.led_positions_mm if leds is None else geo.led_positions_mm[list(leds)]
    d = pos - np.asarray(point_mm, float)
    dist = np.linalg.norm(d, axis=1)
    cos = np.maximum(d @ np.asarray(normal, float), 0.0) / dist
    inten = float(np.mean(config.sphere.led_intensity)) * displayed_drive(config, peak)
    return float(np.sum(inten * cos / dist ** 2))


def exposure_for(config: RigConfig, radiance: float, fraction: float) -> float:
    """Exposure (s, whole ms) that brings ``radiance`` to ``fraction`` of full scale with the design response."""
    if not radiance > 0:
        raise ValueError("exposure_for: the predicted radiance is zero (target unlit?)")
    per_s = design_value_per_radiance(config, 1.0) * radiance
    return exposure_ms(fraction / per_s, config)


def exposure_and_peak(config: RigConfig, radiance_at_full_drive: float, fraction: float) -> tuple[float, float]:
    """(exposure_s, pattern peak) bringing a radiance (at drive 1.0) to at most ``fraction`` of full scale: the
    exposure rounded *down* to the trigger's whole milliseconds; when even the shortest exposure would
    overexpose (mirror-ball highlights are that bright), the LEDs are dimmed instead."""
    if not radiance_at_full_drive > 0:
        raise ValueError("exposure_and_peak: the predicted radiance is zero (target unlit?)")
    peak = config.sphere.pattern_peak
    t = fraction / (design_value_per_radiance(config, 1.0) * radiance_at_full_drive * displayed_drive(config, peak))
    t_min = max(config.trigger.min_exposure_s, 0.001)
    t_ms = max(t_min, min(config.trigger.max_exposure_s, np.floor(t * 1000.0) / 1000.0))
    if t_ms > t:
        peak = max(peak * t / t_ms, 1.0 / 65535)
    return float(t_ms), displayed_drive(config, peak)


def build_plan(items: Sequence[Shot | Survey], config: RigConfig, led_directions: npt.ArrayLike, *,
               pattern_peak: float | None = None) -> list[Step]:
    """Plan steps for ``items`` (in order). Patterns go through the sphere's slots round-robin (each ``key``
    LED and ``full`` is uploaded once per use of a slot); polarizer changes only where the state changes;
    an operator action becomes a ``checkpoint`` before its frame. Raises :class:`LimitError` when an exposure
    is longer than the sphere's watchdog allows."""
    dirs = np.asarray(led_directions, float)
    sph, cam = config.sphere, config.camera
    peak = sph.pattern_peak if pattern_peak is None else float(pattern_peak)
    rows: list[dict[str, Any]] = []
    labels: set[str] = set()

    def add(kind: str, reason: str, *, frame: str | None = None, timeout_s: float = 10.0, nominal_s: float = 0.0,
            **params: Any) -> dict[str, Any]:
        row = {"kind": kind, "reason": reason, "frame": frame, "timeout_s": timeout_s, "nominal_s": nominal_s,
               "params": params, "serves": []}
        rows.append(row)
        return row

    slot_content: dict[int, str] = {}
    slot_upload: dict[int, dict[str, Any]] = {}
    next_slot = 0
    polar: str | None = None
    for item in items:
        if item.operator:
            add("checkpoint", "operator: " + str(item.operator.get("say", "prepare the next target")),
                operator=dict(item.operator))
        if isinstance(item, Survey):
            add("survey", f"total-station position of target {item.target!r}", timeout_s=60.0, nominal_s=4.0,
                target=item.target)
            continue
        shot = item
        if shot.label in labels:
            raise ValueError(f"duplicate shot label {shot.label!r}")
        labels.add(shot.label)
        if sph.watchdog_s and shot.exposure_s + sph.settle_s + 0.5 >= sph.watchdog_s:
            raise LimitError(f"shot {shot.label!r}: exposure {shot.exposure_s:g} s does not fit the sphere's "
                             f"watchdog (sphere.watchdog_s={sph.watchdog_s:g} s): raise the watchdog or shorten it")
        if shot.polarization != polar:
            add("polarization", f"polarizers {shot.polarization} for the frames that follow", state=shot.polarization)
            polar = shot.polarization
        fid = f"{shot.label}/{shot.polarization}"
        upload = None
        if shot.pattern == "ambient":
            sel = add("select", "sphere dark", frame=fid, timeout_s=5.0, slot=None, pattern="ambient", current_a=0.0)
        else:
            key = f"key{shot.led}" if shot.pattern == "key" else shot.pattern
            slot = next((s for s, k in slot_content.items() if k == key), None)
            if slot is None:
                slot = next_slot % sph.slots
                next_slot += 1
                rgb = pattern_for(shot.pattern, dirs, peak=peak, key_led=shot.led, channels=("R", "G", "B"))
                upload = add("upload", f"load pattern {key} into slot {slot}", timeout_s=30.0, slot=slot,
                             pattern=shot.pattern, key_led=shot.led, channels="RGB",
                             current_a=round(pattern_current_a(rgb, sph.led_current_a_per_channel), 4))
                slot_content[slot] = key
                slot_upload[slot] = upload
            upload = slot_upload[slot]
            sel = add("select", f"light slot {slot} ({key})", frame=fid, timeout_s=5.0, slot=slot,
                      pattern=shot.pattern, current_a=upload["params"]["current_a"])
        group = [sel]
        if sph.settle_s > 0:
            group.append(add("settle", "LEDs and polarizers settle", frame=fid, timeout_s=sph.settle_s + 5.0,
                             seconds=sph.settle_s))
        group.append(add("trigger", f"expose {shot.exposure_s:g} s", frame=fid, timeout_s=shot.exposure_s + 10.0,
                         nominal_s=shot.exposure_s, exposure_s=shot.exposure_s))
        fetch = add("fetch", f"calibration frame {shot.label}", frame=fid, timeout_s=cam.fetch_timeout_s,
                    nominal_s=1.0, pattern=shot.label, polarization=shot.polarization, exposure_s=shot.exposure_s,
                    led=shot.led, lit=shot.pattern)
        group.append(fetch)
        fetch["_group"] = group
        if upload is not None:
            upload.setdefault("_fetches", []).append(fetch)
        add("checkpoint", "frame committed: a safe point to pause")
    add("all_off", "leave the sphere dark", timeout_s=5.0)
    for i, r in enumerate(rows):
        r["index"] = i
    for r in rows:
        if r["kind"] == "survey":
            r["serves"] = [r["index"]]
        if r["kind"] == "fetch":
            for g in r["_group"]:
                g["serves"] = [r["index"]]
        if r["kind"] == "upload":
            r["serves"] = [f["index"] for f in r.get("_fetches", [])]
    return [Step(r["index"], r["kind"], r["params"], r["reason"], tuple(r["serves"]), r["frame"],
                 round(float(r["nominal_s"]), 4), round(float(r["timeout_s"]), 4)) for r in rows]


@dataclass
class Captured:
    """A finished calibration capture: its session, the frames by label, the surveys by target."""

    session: Session
    frames: dict[str, FrameRecord]
    surveys: dict[str, tuple[float, float, float]]
    steps: list[Step]
    simulated: bool
    linearize: Callable[[npt.ArrayLike], FloatArray] | None = None
    pattern_peak: float = 1.0
    _cache: dict[str, FloatArray] = field(default_factory=dict, repr=False)

    def image(self, label: str) -> FloatArray:
        """Frame ``label`` as linear float64 RGB (H, W, 3), white level = 1 (black-corrected and linearized
        when a radiometry calibration is known)."""
        from drivers.camera.raw import load_linear

        if label not in self.frames:
            raise KeyError(f"{self.session.root}: no calibration frame {label!r}")
        if label not in self._cache:
            rgb, _ = load_linear(self.session.root / self.frames[label].file)
            img = np.asarray(rgb, np.float64)
            self._cache[label] = self.linearize(img) if self.linearize else img
        return self._cache[label]

    def exposure_s(self, label: str) -> float:
        return float(self.frames[label].exposure_s)


def _session_name(prefix: str, sessions_dir: Path) -> str:
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    name = validate_session_name(f"{prefix}-{stamp}")
    n = 2
    while (sessions_dir / name).exists():
        name = validate_session_name(f"{prefix}-{stamp}-{n}")
        n += 1
    return name


@contextlib.contextmanager
def _rig(config: RigConfig, geometry: RigGeometry, world: Any | None) -> Iterator[tuple[Any, Any]]:
    """Open the devices (starting the simulators first when the config asks for them)."""
    from ..factory import open_devices, skip_exposure_waits, start_simulators, uses_simulators

    with contextlib.ExitStack() as stack:
        sim = None
        if uses_simulators(config):
            if world is None:
                raise ValueError("a simulated rig needs a SimulatedCalibrationWorld (what the targets really are)")
            work = stack.enter_context(tempfile.TemporaryDirectory(prefix="sssrig-calsim-"))
            sim = start_simulators(config, world.truth_geometry(), Path(work))
            stack.callback(sim.close)
            world.attach(sim)
        devices = open_devices(config, geometry, sim)
        stack.callback(devices.close)
        if sim is not None:
            skip_exposure_waits(devices, sim)     # the simulated camera renders at once
        yield devices, sim


def capture(config: RigConfig, step_name: str, items: Sequence[Shot | Survey], *, sessions_dir: str | Path,
            geometry: RigGeometry, world: Any | None = None,
            operator: Callable[[dict[str, Any]], None] | None = None, say: Callable[[str], None] | None = None,
            linearize: Callable[[npt.ArrayLike], FloatArray] | None = None,
            pattern_peak: float | None = None) -> Captured:
    """Plan ``items``, open the rig (simulated when ``config`` says ``sim``), run the plan into a new session
    ``calib-<step>-<time>`` under ``sessions_dir``, and return the frames and surveys.

    ``geometry``: the design geometry, whose ``targets`` include every calibration target to aim at.
    ``operator``: called with a checkpoint's ``operator`` params before it (real rig: tell the operator and
    wait); in simulation ``world.operate`` is used when no operator is given. ``pattern_peak``: the drive of
    every lit LED in this capture (default ``[sphere] pattern_peak``)."""
    from ..runner import run_plan

    say = say or (lambda m: None)
    sessions_dir = Path(sessions_dir)
    peak = config.sphere.pattern_peak if pattern_peak is None else float(pattern_peak)
    steps = build_plan(items, config, geometry.led_directions, pattern_peak=peak)
    act = operator or (world.operate if world is not None else None)

    def progress(index: int, total: int, step: Step, skipped: bool = False) -> None:
        if not skipped and step.kind == "checkpoint" and "operator" in step.params:
            op = step.params["operator"]
            if act is None:
                raise RuntimeError(f"step {index}: an operator action is needed ({op.get('say')}) but no operator "
                                   "callback was given")
            act(op)

    name = _session_name(f"calib-{step_name}", sessions_dir)
    with _rig(config, geometry, world) as (devices, sim):
        ids = {role: dataclasses.asdict(dev.identify())
               for role, dev in (("sphere", devices.light), ("trigger", devices.trigger), ("camera", devices.camera),
                                 ("total_station", devices.feed)) if dev is not None}
        truth = world.truth_dict() if (world is not None and sim is not None) else None
        session = Session.create(sessions_dir, name, config=config.to_dict(), devices=ids,
                                 plan=[s.to_dict() for s in steps], geometry=geometry_to_dict(geometry), truth=truth,
                                 request={"calibration": step_name})
        say(f"calibration session {session.root}")
        with session.lock():
            result = run_plan(steps, devices, session, led_directions=geometry.led_directions,
                              pattern_peak=peak, fetch_timeout_s=config.camera.fetch_timeout_s,
                              progress=progress, say=say, watchdog_s=config.sphere.watchdog_s or None)
        if result.status != "complete":
            raise CalibrationFailed(f"{session.root}: calibration capture {result.status} ({result.reason}); "
                                    "run the step again")
    by_step = {s.index: s for s in steps}
    frames = {by_step[r.step].params["pattern"]: r for r in session.frames() if r.step in by_step}
    surveys = {k: tuple(float(x) for x in v["xyz_mm"]) for k, v in session.surveys().items()}
    return Captured(session, frames, surveys, steps, sim is not None, linearize, pattern_peak=peak)
