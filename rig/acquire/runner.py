"""Run a capture plan on devices into a session; the sphere is left dark on every exit path.

What the runner guarantees (docs/capture-and-resume.md):

- **resume**: steps whose ``frame``/``survey`` is already journalled are skipped, and so is every step that
  only serves them (:attr:`rig.acquire.plan.Step.serves`); frames a crash left unjournalled are moved aside first
  (:meth:`Session.recover`). Setup steps (pattern uploads, polarization) are re-run when still needed.
- **timeouts**: every step has a deadline (``Step.timeout_s``). Waits (frame fetch, settle, holds) are bounded
  by it; a device call in progress is bounded by its driver's own timeout, and the deadline is checked after it
  (:class:`StepTimeout`).
- **retries**: idempotent steps are retried up to ``retries`` times after a timeout, a garbled reply or a busy
  device; a frame (select -> settle -> trigger -> fetch) is retried as a whole, since nothing of it is journalled
  before its fetch commits. Refusals (``DeviceRejected``), limit and config errors are not retried.
- **a device lost** (retries exhausted, or the transport gone): the run pauses (``lost`` event), switches the
  sphere off if it can, and polls until every device identifies again (reopening them through ``reopen``),
  then re-establishes the sphere's state and continues (``reconnected``); after ``lost_timeout_s`` it aborts
  with :class:`DeviceLost`.
- **interlock**: before lighting a pattern and after every lit exposure the sphere's status is read; while it
  reports over-temperature the run holds with the sphere dark (``hold`` ... ``release``), and a frame the
  interlock may have cut is taken again.
- **pause / abort** (:class:`RunControl`; :func:`signal_handlers` maps them to signals): the first Ctrl-C pauses
  at the next checkpoint, the second aborts at once; SIGTERM aborts at once. A pause either waits for
  :meth:`RunControl.resume` (``pause_mode="wait"``) or ends the run as ``paused`` (``"stop"``), resumable with
  ``rig resume``. Journal writes are never cut by a signal (:meth:`RunControl.critical`).
- **safe exit**: on every exit (success, pause, exception, abort, signal, device lost) the sphere gets
  ``all_off`` and the journal a ``stop`` event recording whether the sphere confirmed it. The sphere's own
  watchdog (armed to ``watchdog_s``) darkens it if the host dies (``kill -9``) or the cable is pulled.
"""
from __future__ import annotations

import contextlib
import inspect
import logging
import signal
import sys
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Sequence, TextIO

import numpy as np

from drivers.contracts import Camera, LightSource, Polarization, PositionFeed, Trigger
from drivers.errors import (ConnectionLost, DeviceBusy, DeviceError, DeviceRejected, DeviceTimeout,
                            ProtocolError, RigError)

from rig.acquire.plan import Step, pattern_for
from rig.files.session import Session, now_iso

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------- errors
class StepTimeout(DeviceTimeout):
    """A plan step ran past its ``timeout_s``."""


class Interlocked(DeviceError):
    """The sphere's over-temperature interlock cut a frame, or held the run longer than allowed."""


class DeviceLost(ConnectionLost):
    """A device stopped answering and did not come back within ``lost_timeout_s``."""


class Aborted(RigError):
    """The run was aborted (second Ctrl-C, SIGTERM, :meth:`RunControl.abort`)."""

    def __init__(self, reason: str, signum: int | None = None) -> None:
        super().__init__(reason)
        self.reason = reason
        self.signum = signum


RETRYABLE = (DeviceTimeout, ProtocolError, DeviceBusy)
OVER_TEMPERATURE, LED_FAULT = 0x01, 0x04          # LightStatus.fault_flags bits (docs/protocols/led-sphere-*.md)
FAULT_NAMES = {OVER_TEMPERATURE: "over_temperature", LED_FAULT: "led_fault"}


class FaultStop(RigError):
    """The sphere reported a fault whose configured action stops the run (``[runner] on_led_fault`` ...)."""

    def __init__(self, message: str, action: str, bits: int) -> None:
        super().__init__(message)
        self.action, self.bits = action, bits


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
    status: str = "aborted"                 # complete | paused | aborted
    reason: str | None = None
    seconds_by_kind: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    steps_run: int = 0
    steps_skipped: int = 0
    retries: int = 0
    holds: int = 0
    reconnects: int = 0
    pauses: int = 0
    lights_off: bool = False

    def to_dict(self) -> dict[str, Any]:
        return {"status": self.status, "reason": self.reason, "steps_run": self.steps_run,
                "steps_skipped": self.steps_skipped, "retries": self.retries, "holds": self.holds,
                "reconnects": self.reconnects, "pauses": self.pauses, "lights_off": self.lights_off,
                "seconds_by_kind": {k: round(v, 4) for k, v in self.seconds_by_kind.items()}}


# ------------------------------------------------------------------------------------------- control
class RunControl:
    """Pause / resume / abort requests for a running plan, from any thread or a signal handler.

    ``pause_mode``: ``"wait"`` (a paused run waits for :meth:`resume` or an abort) or ``"stop"`` (a paused run
    ends with status ``paused``; continue it with ``rig resume``).
    """

    def __init__(self, pause_mode: str = "wait") -> None:
        if pause_mode not in ("wait", "stop"):
            raise ValueError(f"pause_mode {pause_mode!r}: expected 'wait' or 'stop'")
        self.pause_mode = pause_mode
        self.state = "running"              # running | pausing | paused | aborting
        self.pause_reason: str | None = None
        self.abort_reason: str | None = None
        self.abort_signum: int | None = None
        self._resume = threading.Event()
        self._critical = 0
        self._deferred: BaseException | None = None
        self.closing = False                # the run is cleaning up: an abort is recorded, never raised
        self.notify: Callable[[str], None] = lambda msg: None

    @property
    def pause_requested(self) -> bool:
        return self.state in ("pausing", "paused")

    @property
    def abort_requested(self) -> bool:
        return self.state == "aborting"

    def request_pause(self, reason: str = "pause requested") -> None:
        if self.state == "running":
            self.pause_reason = reason
            self._resume.clear()
            self.state = "pausing"

    def resume(self) -> None:
        if self.state in ("pausing", "paused"):
            self.state = "running"
            self._resume.set()

    def abort(self, reason: str = "abort requested", signum: int | None = None) -> None:
        if self.state != "aborting":
            self.abort_reason, self.abort_signum = reason, signum
            self.state = "aborting"
        self._resume.set()

    def wait_resumed(self, timeout_s: float) -> bool:
        """Block up to ``timeout_s`` while paused; True once resumed or aborted."""
        return self._resume.wait(timeout_s)

    @contextlib.contextmanager
    def critical(self, *, discard: bool = False) -> Iterator[None]:
        """No signal-raised abort inside: it is deferred to the end of the outermost critical section
        (or dropped with ``discard``; the abort request itself stays recorded)."""
        self._critical += 1
        try:
            yield
        finally:
            self._critical -= 1
            if self._critical == 0 and self._deferred is not None:
                exc, self._deferred = self._deferred, None
                if not discard:
                    raise exc

    def interrupt(self, reason: str, signum: int | None = None) -> None:
        """Abort now: raise :class:`Aborted` in the running code (deferred inside a critical section)."""
        self.abort(reason, signum)
        if self.closing:
            return
        exc = Aborted(reason, signum)
        if self._critical:
            self._deferred = exc
        else:
            raise exc

    def on_sigint(self) -> None:
        if self.state in ("pausing", "paused"):
            self.notify("second Ctrl-C: aborting")
            self.interrupt("SIGINT (second Ctrl-C)", signal.SIGINT)
        elif self.state == "running":
            self.request_pause("SIGINT (Ctrl-C)")
            self.notify("Ctrl-C: pausing at the next checkpoint (Ctrl-C again to abort)")


@contextlib.contextmanager
def signal_handlers(control: RunControl) -> Iterator[RunControl]:
    """SIGINT -> :meth:`RunControl.on_sigint`, SIGTERM -> abort now. Main thread only (a no-op elsewhere)."""
    if threading.current_thread() is not threading.main_thread():
        yield control
        return
    old_int = signal.signal(signal.SIGINT, lambda signum, frame: control.on_sigint())
    old_term = signal.signal(signal.SIGTERM, lambda signum, frame: control.interrupt("SIGTERM", signal.SIGTERM))
    try:
        yield control
    finally:
        signal.signal(signal.SIGINT, old_int)
        signal.signal(signal.SIGTERM, old_term)


# ------------------------------------------------------------------------------------------- progress
class ProgressBar:
    """A progress bar with ETA for :func:`run_plan`'s ``progress`` callback.

    ETA: each remaining step takes the mean measured duration of the steps of its kind run so far (its nominal
    duration until one has run), less the time already spent in the current step. Per kind, because kinds differ
    in how far they are from their nominal time (a simulated survey is instant, a simulated frame renders for
    seconds): one pace for all read 0:00 long before the end (issue 18). On a terminal one line is redrawn;
    otherwise a line is printed per frame.
    """

    def __init__(self, steps: Sequence[Step], stream: TextIO | None = None, *, width: int = 28,
                 tty: bool | None = None) -> None:
        self.steps = list(steps)
        self.stream = stream or sys.stderr
        self.width = width
        self.tty = self.stream.isatty() if tty is None else tty
        self.total_s = sum(s.nominal_s for s in self.steps) or 1.0
        self.n_frames = sum(1 for s in self.steps if s.kind == "fetch")
        self._t0: float | None = None
        self._nominal_run = 0.0
        self._last: int | None = None
        self._t_step: float | None = None                   # when the step in progress started
        self._measured: dict[str, list[float]] = {}         # kind -> measured durations of the steps run
        self.lines: list[str] = []
        self.on_close: Callable[[], None] | None = None     # e.g. give the terminal line back to rig.feedback

    def eta_s(self, index: int, now: float) -> float:
        mean = {k: sum(v) / len(v) for k, v in self._measured.items()}
        remaining = sum(mean.get(s.kind, s.nominal_s) for s in self.steps[index:])
        if self._t_step is not None and index == self._last:
            remaining -= min(now - self._t_step, mean.get(self.steps[index].kind, self.steps[index].nominal_s))
        return max(0.0, remaining)

    def render(self, index: int, step: Step, now: float) -> str:
        done_s = sum(s.nominal_s for s in self.steps[:index])
        frac = min(1.0, done_s / self.total_s)
        filled = int(round(frac * self.width))
        frames_done = sum(1 for s in self.steps[:index] if s.kind == "fetch")
        eta = self.eta_s(index, now)
        return (f"[{'#' * filled}{'.' * (self.width - filled)}] {100 * frac:3.0f}%  frame {frames_done}/"
                f"{self.n_frames}  step {index + 1}/{len(self.steps)} {step.kind:<12} "
                f"ETA {int(eta // 60)}:{int(eta % 60):02d}")

    def __call__(self, index: int, total: int, step: Step, *, skipped: bool = False) -> None:
        now = time.monotonic()
        if self._t0 is None and not skipped:
            self._t0 = now
        if self._last is not None and self._t_step is not None and self._last < index:
            self._nominal_run += self.steps[self._last].nominal_s
            self._measured.setdefault(self.steps[self._last].kind, []).append(now - self._t_step)
        self._last = None if skipped else index
        self._t_step = None if skipped else now
        line = self.render(index, step, now)
        self.lines.append(line)
        if self.tty:
            self.stream.write("\r" + line)
            self.stream.flush()
        elif step.kind == "fetch" and not skipped:
            self.stream.write(line + "\n")
            self.stream.flush()

    def close(self) -> None:
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()
        if self.on_close is not None:
            self.on_close()


# --------------------------------------------------------------------------------------------- runner
@dataclass
class RunOptions:
    led_directions: np.ndarray
    pattern_peak: float
    fetch_timeout_s: float = 30.0
    watchdog_s: float | None = None          # arm the sphere's watchdog (if it has one) to this
    retries: int = 2                         # extra attempts of an idempotent step or a frame
    retry_delay_s: float = 0.2
    busy_timeout_s: float = 10.0             # a BUSY device is asked again (backoff 0.05 s doubling to 1 s) this long
    on_led_fault: str = "pause"              # the sphere's LED-fault bit: pause | abort | continue
    on_over_temperature: str = "hold"        # its over-temperature bit: hold (dark until cool) | pause | abort
    accept_faults: int = 0                   # fault bits the operator accepted (rig resume --accept-fault)
    hold_poll_s: float = 0.5                 # status polling while over-temperature
    max_hold_s: float = 1800.0
    lost_poll_s: float = 0.5                 # probing while a device is lost
    lost_timeout_s: float = 120.0
    max_lost_per_step: int = 3               # a step that keeps failing after reconnects gives up
    drain_timeout_s: float = 2.0             # wait for a frame an interrupted attempt may still deliver


def run_plan(steps: Sequence[Step], devices: Devices, session: Session, *, led_directions: Any,
             pattern_peak: float, fetch_timeout_s: float = 30.0, settle_s: float | None = None,
             progress: Callable[..., None] | None = None, control: RunControl | None = None,
             reopen: Callable[[], Devices] | None = None, say: Callable[[str], None] | None = None,
             **options: Any) -> RunResult:
    """Execute ``steps`` into ``session``, skipping what the session already holds (resume).

    ``reopen`` opens a fresh set of devices (used when one is lost); ``options`` are :class:`RunOptions`
    fields (``watchdog_s``, ``retries``, ``lost_timeout_s``...). ``settle_s`` is accepted for compatibility;
    settling is a plan step. Returns the :class:`RunResult` (``status`` ``complete`` or ``paused``); raises
    on abort (:class:`Aborted`) and on errors, after the sphere was switched off and ``stop`` journalled.
    """
    opts = RunOptions(np.asarray(led_directions, float), float(pattern_peak), float(fetch_timeout_s), **options)
    return _Runner(list(steps), devices, session, opts, control or RunControl(), progress, reopen,
                   say or (lambda m: None)).run()


class _Runner:
    def __init__(self, steps: list[Step], devices: Devices, session: Session, opts: RunOptions,
                 control: RunControl, progress: Callable[..., None] | None,
                 reopen: Callable[[], Devices] | None, say: Callable[[str], None]) -> None:
        self.steps, self.d, self.session, self.opts = steps, devices, session, opts
        self.control, self.progress, self.reopen, self.say = control, progress, reopen, say
        self.result = RunResult()
        self.done: set[int] = set()
        self._deadline: float | None = None
        self._t_trigger: str | None = None
        self._lit = False
        self._restore = False
        self._closed = False           # the devices were closed by a failed reopen
        self._fired = False            # the trigger fired and the frame was not taken yet
        self.accepted = opts.accept_faults    # fault bits that no longer stop the run
        self._reported = 0                    # fault bits journalled in this run
        self._progress_takes_skipped = False
        if progress is not None:
            try:
                params = inspect.signature(progress).parameters
                self._progress_takes_skipped = "skipped" in params or any(
                    p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
            except (TypeError, ValueError):
                pass

    # -- journal -------------------------------------------------------------------------------------
    def event(self, type_: str, **fields: Any) -> None:
        with self.control.critical():
            self.session.append_event({"type": type_, **fields})

    # -- main loop -----------------------------------------------------------------------------------
    def run(self) -> RunResult:
        r = self.result
        try:
            with self.control.critical():
                moved = self.session.recover()
            if moved:
                self.say(f"moved {len(moved)} unjournalled file(s) to frames/orphans/")
            self.done = self.session.completed_steps()
            self._arm_watchdog()
            for unit in _units(self.steps):
                self._check_abort()
                if all(s.serves and set(s.serves) <= self.done for s in unit):
                    for s in unit:
                        self._progress(s, skipped=True)
                    r.steps_skipped += len(unit)
                    continue
                while True:
                    try:
                        self._run_unit(unit)
                        break
                    except FaultStop as exc:
                        if exc.action == "abort":
                            raise
                        self.control.request_pause(str(exc))
                        if not self._pause(unit[0]):
                            r.status, r.reason = "paused", str(exc)
                            return r
                        self.accepted |= exc.bits        # the operator resumed: this fault is known now
                if unit[-1].kind == "checkpoint" and self.control.pause_requested:
                    if not self._pause(unit[-1]):
                        r.status, r.reason = "paused", self.control.pause_reason
                        return r
            r.status, r.reason = "complete", None
            return r
        except BaseException as exc:
            r.status = "aborted"
            r.reason = exc.reason if isinstance(exc, Aborted) else f"{type(exc).__name__}: {exc}"
            raise
        finally:
            self.control.closing = True     # a Ctrl-C from now on is recorded, never raised into the cleanup
            with self.control.critical(discard=True):
                if self.control.abort_requested and r.status != "aborted":
                    r.status, r.reason = "aborted", self.control.abort_reason     # 2nd Ctrl-C during the exit
                r.lights_off = self._lights_off(disarm=True)
                if not r.lights_off:
                    self.say("WARNING: the sphere did not confirm all-off; its watchdog darkens it "
                             f"after {self.opts.watchdog_s or 'its configured'} s")
                self.session.append_event({"type": "stop", "status": r.status, "reason": r.reason,
                                           "lights_off": r.lights_off})

    def _progress(self, step: Step, *, skipped: bool = False) -> None:
        if self.progress is None:
            return
        if self._progress_takes_skipped:
            self.progress(step.index, len(self.steps), step, skipped=skipped)
        elif not skipped:       # a plain (index, total, step) callback sees the steps that run
            self.progress(step.index, len(self.steps), step)

    def _check_abort(self) -> None:
        if self.control.abort_requested:
            raise Aborted(self.control.abort_reason or "aborted", self.control.abort_signum)

    # -- units: one step, or the steps of one frame ------------------------------------------------------
    def _run_unit(self, unit: list[Step]) -> None:
        attempt = lost = 0
        busy_t0: float | None = None     # first BUSY of this unit: asked again on the same connection until
        busy_delay = 0.05                # busy_timeout_s, with backoff (no reconnect: the device answers)
        hold: str | None = None          # the interlock tripped: hold (inside the try, so its errors count)
        while True:
            self._fired = False
            step = unit[0]
            try:
                if hold is not None:
                    self._hold(step, hold)
                    hold = None
                if self._restore:
                    self._restore_state(unit[0].index)
                for step in unit:
                    self._check_abort()
                    self._progress(step)
                    t0 = time.perf_counter()
                    self._run_step(step)
                    self.result.seconds_by_kind[step.kind] += time.perf_counter() - t0
                    self.result.steps_run += 1
                return
            except Interlocked as exc:
                if hold is not None:       # held longer than max_hold_s
                    raise
                self._after_failure()
                self._over_temperature(step, str(exc))
                hold = str(exc)
            except DeviceBusy as exc:
                if step.kind == "trigger":
                    self._fired = False          # the box refused the shot: no frame is on its way
                self._after_failure()
                now = time.monotonic()
                busy_t0 = now if busy_t0 is None else busy_t0
                if now - busy_t0 > self.opts.busy_timeout_s:
                    raise
                self.result.retries += 1
                self.event("busy", step=step.index, error=str(exc), wait_s=round(busy_delay, 3),
                           busy_for_s=round(now - busy_t0, 3))
                self.say(f"step {step.index} ({step.kind}): device busy; asking again in {busy_delay:.2f} s")
                self._sleep(busy_delay)
                busy_delay = min(1.0, 2 * busy_delay)
            except (*RETRYABLE, ConnectionLost) as exc:
                self._after_failure()
                attempt += 1
                if not isinstance(exc, ConnectionLost) and attempt <= self.opts.retries:
                    self.result.retries += 1
                    self.event("retry", step=step.index, attempt=attempt, error=f"{type(exc).__name__}: {exc}")
                    self.say(f"step {step.index} ({step.kind}): {exc}; retry {attempt}/{self.opts.retries}")
                    self._sleep(self.opts.retry_delay_s)
                    continue
                lost += 1
                if lost > self.opts.max_lost_per_step:
                    raise
                self._device_lost(step, exc)
                attempt = 0
            except DeviceRejected as exc:
                if not _over_temperature_refusal(exc):
                    raise
                self._after_failure()
                self._over_temperature(step, str(exc))
                hold = str(exc)

    def _after_failure(self) -> None:
        self._deadline = None
        if self._fired:     # the camera may still deliver the interrupted frame: take it out of the way
            self._fired = False
            try:
                self.d.camera.fetch(self.opts.drain_timeout_s)
            except Exception:
                pass

    # -- one step ------------------------------------------------------------------------------------------
    def _remaining(self, default: float) -> float:
        if self._deadline is None:
            return default
        return max(0.0, min(default, self._deadline - time.monotonic()))

    def _check_deadline(self, step: Step) -> None:
        if self._deadline is not None and time.monotonic() > self._deadline:
            raise StepTimeout(f"step {step.index} ({step.kind}) exceeded its timeout of {step.timeout_s:g} s")

    def _sleep(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while True:
            self._check_abort()
            left = end - time.monotonic()
            if left <= 0:
                return
            time.sleep(min(left, 0.05))

    def _run_step(self, step: Step) -> None:
        """Run one step (``_fired`` tells whether the trigger fired and no frame was taken since)."""
        p, d = step.params, self.d
        self._deadline = time.monotonic() + step.timeout_s if step.timeout_s > 0 else None
        if step.kind == "upload":
            d.light.upload_pattern(p["slot"], pattern_for(p["pattern"], self.opts.led_directions,
                                                          peak=self.opts.pattern_peak, key_led=p.get("key_led"),
                                                          channels=tuple(p.get("channels", "RGB"))))
        elif step.kind == "polarization":
            d.light.set_polarization(Polarization[p["state"].upper()])
        elif step.kind == "survey":
            if d.feed is None:
                raise RigError(f"step {step.index}: survey of {p['target']!r} needs a position feed")
            pt = d.feed.measure(p["target"])
            self._check_deadline(step)
            with self.control.critical():
                self.session.add_survey(step.index, pt.name, pt.xyz_mm, pt.warning)
            self.done.add(step.index)
        elif step.kind == "select":
            if p["slot"] is None:
                d.light.all_off()
                self._lit = False
            else:
                self._interlock(step)
                d.light.select_slot(p["slot"])
                self._lit = True
        elif step.kind == "settle":
            self._sleep(self._remaining(float(p["seconds"])))
        elif step.kind == "trigger":
            d.camera.arm()
            self._t_trigger = now_iso()
            self._fired = True              # from here on a frame may be on its way
            d.trigger.fire(p["exposure_s"])
            if self._lit:
                st = d.light.status()
                self._check_faults(st, step)
                if st.over_temperature or not st.lit:
                    raise Interlocked(f"step {step.index}: the sphere went dark during the exposure "
                                      f"(over-temperature {st.over_temperature}, {st.temperature_c:.1f} C, "
                                      f"faults 0x{st.fault_flags:02X})")
        elif step.kind == "fetch":
            frame = d.camera.fetch(self._remaining(self.opts.fetch_timeout_s))
            if frame.path is None:
                raise RigError(f"step {step.index}: the camera returned a frame without a file")
            self._check_deadline(step)
            with self.control.critical():
                self.session.add_frame(step.index, frame.path, pattern=p["pattern"],
                                       polarization=p["polarization"], exposure_s=p["exposure_s"],
                                       t_trigger=self._t_trigger or now_iso())
            self.done.add(step.index)
            self._fired = False
            return
        elif step.kind == "all_off":
            d.light.all_off()
            self._lit = False
        elif step.kind == "checkpoint":
            pass
        else:
            raise ValueError(f"step {step.index}: unknown step kind {step.kind!r}")
        if step.kind not in ("survey", "fetch", "trigger"):
            self._check_deadline(step)
        self._deadline = None

    # -- safety ----------------------------------------------------------------------------------------
    def _arm_watchdog(self) -> None:
        arm = getattr(self.d.light, "set_watchdog", None)
        if self.opts.watchdog_s and arm is not None:
            arm(self.opts.watchdog_s)

    def _lights_off(self, *, disarm: bool = False) -> bool:
        """Switch the sphere off (best effort: the drivers retry); True if the sphere confirmed it."""
        self._lit = False
        if self._closed and self._reopen() is not None:
            return False
        try:
            self.d.light.all_off()
        except Exception as exc:   # noqa: BLE001 - cleanup must not raise; the watchdog is the fallback
            log.warning("all_off failed: %s", exc)
            return False
        if disarm and self.opts.watchdog_s:
            with contextlib.suppress(Exception):
                disarm_fn = getattr(self.d.light, "set_watchdog", None)
                if disarm_fn is not None:
                    disarm_fn(None)
        return True

    def _check_faults(self, st: Any, step: Step) -> None:
        """Journal a new LED-fault bit (``fault`` event) and act on it as configured: ``continue``, or stop the
        unit (:class:`FaultStop`) to pause or abort. The frame in progress is not journalled."""
        bits = st.fault_flags & LED_FAULT
        if not bits:
            return
        action = self.opts.on_led_fault
        new = bits & ~self._reported
        if new:
            self._reported |= new
            self.event("fault", step=step.index, fault="led_fault", fault_flags=st.fault_flags, action=action,
                       accepted=bool(bits & self.accepted))
            self.say(f"FAULT at step {step.index}: the sphere reports an LED fault (flags 0x{st.fault_flags:02X}); "
                     f"action: {action if not bits & self.accepted else 'continue (accepted)'}")
        if action == "continue" or bits & self.accepted == bits:
            return
        raise FaultStop(f"the sphere reports an LED fault (flags 0x{st.fault_flags:02X}) at step {step.index}; "
                        "check the LEDs, then resume (rig resume --accept-fault led_fault to go on regardless)",
                        action, bits)

    def _over_temperature(self, step: Step, why: str) -> None:
        """Journal the over-temperature bit (``fault`` event, once per run) and act: ``hold`` (the caller
        holds), or :class:`FaultStop` to pause or abort."""
        action = self.opts.on_over_temperature
        if not self._reported & OVER_TEMPERATURE:
            self._reported |= OVER_TEMPERATURE
            self.event("fault", step=step.index, fault="over_temperature", reason=why, action=action)
        if action != "hold":
            raise FaultStop(f"over-temperature at step {step.index}: {why}", action, OVER_TEMPERATURE)

    def _interlock(self, step: Step) -> None:
        st = self.d.light.status()
        self._check_faults(st, step)
        if st.over_temperature:         # the unit holds, then starts again from this select
            raise Interlocked(f"over-temperature ({st.temperature_c:.1f} C) before lighting step {step.index}")

    def _hold(self, step: Step, why: str) -> None:
        """Hold with the sphere dark while it reports over-temperature."""
        self.result.holds += 1
        self._lights_off()
        temp = None
        with contextlib.suppress(Exception):
            temp = self.d.light.status().temperature_c
        self.event("hold", step=step.index, reason=why, temperature_c=temp)
        self.say(f"HOLD at step {step.index}: {why}; waiting for the sphere to cool")
        t0 = time.monotonic()
        while True:
            self._sleep(self.opts.hold_poll_s)
            st = self.d.light.status()
            if not st.over_temperature:
                self.event("release", step=step.index, temperature_c=st.temperature_c,
                           held_s=round(time.monotonic() - t0, 3))
                self.say(f"released at {st.temperature_c:.1f} C after {time.monotonic() - t0:.1f} s")
                return
            if time.monotonic() - t0 > self.opts.max_hold_s:
                raise Interlocked(f"the sphere stayed over-temperature for more than {self.opts.max_hold_s:g} s "
                                  f"({st.temperature_c:.1f} C)")

    def _pause(self, step: Step) -> bool:
        """Pause at a checkpoint; True to continue (resumed), False to end the run as paused."""
        self.result.pauses += 1
        self._lights_off()
        reason = self.control.pause_reason or "pause requested"
        if self.control.state == "pausing":
            self.control.state = "paused"       # before the journal line: a resume may follow it at once
        self.event("pause", step=step.index, reason=reason)
        if self.control.pause_mode == "stop":
            self.say(f"paused at step {step.index} ({reason}); continue with `rig resume {self.session.root}`")
            return False
        self.say(f"paused at step {step.index} ({reason}): resume, or Ctrl-C to abort")
        while not self.control.wait_resumed(1.0):
            with contextlib.suppress(Exception):
                self.d.light.status()          # keep the sphere's watchdog fed
        self._check_abort()
        self.event("resume", step=step.index)
        self.say("resumed")
        return True

    def _probe(self) -> None:
        for dev in (self.d.light, self.d.trigger, self.d.camera, self.d.feed):
            if dev is not None:
                dev.identify()

    def _device_lost(self, step: Step, exc: BaseException) -> None:
        """Pause until every device answers again, reopening them; raise :class:`DeviceLost` on timeout."""
        self.result.reconnects += 1
        self.event("lost", step=step.index, error=f"{type(exc).__name__}: {exc}")
        self.say(f"device lost at step {step.index} ({exc}); paused, waiting up to "
                 f"{self.opts.lost_timeout_s:g} s for it to come back")
        self._lights_off()
        deadline = time.monotonic() + self.opts.lost_timeout_s
        last: BaseException = exc
        while True:
            self._check_abort()
            try:
                self._probe()
                break
            except (DeviceError, OSError) as e:
                last = e
            if time.monotonic() > deadline:
                raise DeviceLost(f"step {step.index}: device still not answering after "
                                 f"{self.opts.lost_timeout_s:g} s: {last}") from exc
            if self.reopen is not None:
                last = self._reopen() or last
            self._sleep(self.opts.lost_poll_s)
        self.event("reconnected", step=step.index)
        self.say(f"devices answer again; continuing at step {step.index}")
        self._arm_watchdog()
        self._restore = True

    def _reopen(self) -> BaseException | None:
        """Close every device and open them afresh (a device may serve one client at a time, so the old
        connection goes first). On failure the devices stay closed until the next attempt."""
        if not self._closed:
            self.d.close()
            self._closed = True
        try:
            fresh = self.reopen() if self.reopen is not None else None
        except (DeviceError, OSError) as e:
            return e
        if fresh is not None:
            self.d.light, self.d.trigger = fresh.light, fresh.trigger
            self.d.camera, self.d.feed = fresh.camera, fresh.feed
            self._closed = False
        return None

    def _restore_state(self, before: int) -> None:
        """Re-run the setup steps (uploads, polarization) before ``before`` that pending frames still need."""
        for s in self.steps[:before]:
            if s.kind in ("upload", "polarization") and not set(s.serves) <= self.done:
                self._run_step(s)
        self._restore = False


def _over_temperature_refusal(exc: DeviceRejected) -> bool:
    return "TEMPERATURE" in (exc.name or "").upper()


def _units(steps: Sequence[Step]) -> list[list[Step]]:
    """Group the steps of one frame (same ``frame``, consecutive); every other step is its own unit."""
    out: list[list[Step]] = []
    for s in steps:
        if s.frame is not None and out and out[-1][0].frame == s.frame:
            out[-1].append(s)
        else:
            out.append([s])
    return out


__all__ = ["Aborted", "DeviceLost", "Devices", "FaultStop", "Interlocked", "ProgressBar", "RunControl", "RunOptions",
           "RunResult", "StepTimeout", "run_plan", "signal_handlers"]
