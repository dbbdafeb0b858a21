"""The runner on the simulated rig (drivers over real ptys / TCP): resume, retries, interlock, pause/abort,
a device unplugged mid-sequence, and the sphere dark after every failure path (read from the simulator)."""
import dataclasses
import io
import json
import os
import signal
import threading
import time
import tomllib

import pytest

from drivers.camera.folder import FolderCamera
from drivers.errors import ConnectionLost, DeviceRejected, DeviceTimeout
from drivers.led_sphere.codec import NackCode
from rig.config import default_config_text, parse_config
from rig.acquire.factory import open_devices, start_simulators
from rig.acquire.geometry import rig_geometry
from rig.acquire.plan import build_plan
from rig.acquire.runner import Aborted, FaultStop, ProgressBar, RunControl, run_plan, signal_handlers
from rig.files.session import Session

SMALL = {"sphere": {"geodesic_frequency": 3, "watchdog_s": 1.5},
         "trigger": {"timeout_s": 0.3},
         "camera": {"width_px": 24, "height_px": 24, "fx_px": 400.0, "key_exposure_s": 0.1},
         "scene": {"tessellation": 2}}
FAST = dict(retries=1, retry_delay_s=0.05, lost_poll_s=0.1, hold_poll_s=0.05, drain_timeout_s=0.2)


def small_config():
    data = tomllib.loads(default_config_text())
    for section, fields in SMALL.items():
        data[section].update(fields)
    return parse_config(data, "small.toml")


def wait_for(cond, timeout_s=60.0, what="condition"):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    cfg = small_config()
    geo = rig_geometry(cfg)
    sim = start_simulators(cfg, geo, tmp_path_factory.mktemp("sim"))
    yield cfg, geo, sim
    sim.close()


class Env:
    def __init__(self, cfg, geo, sim, tmp_path):
        self.cfg, self.geo, self.sim, self.tmp = cfg, geo, sim, tmp_path
        self.model = sim.servers["sphere"].device
        self.devices = open_devices(cfg, geo, sim)
        self.n = 0

    def session(self, steps):
        self.n += 1
        return Session.create(self.tmp, f"s{self.n}", config=self.cfg.to_dict(), devices={},
                              plan=[s.to_dict() for s in steps])

    def run(self, steps, session, **kw):
        opts = {**FAST, "watchdog_s": self.cfg.sphere.watchdog_s, **kw}
        reopen = opts.pop("reopen", lambda: open_devices(self.cfg, self.geo, self.sim))
        return run_plan(steps, self.devices, session, led_directions=self.geo.led_directions,
                        pattern_peak=self.cfg.sphere.pattern_peak, fetch_timeout_s=10.0, reopen=reopen, **opts)

    def dark(self):
        return not self.model.lit


@pytest.fixture
def env(rig, tmp_path):
    cfg, geo, sim = rig
    for srv in sim.servers.values():
        srv.faults.clear()
    sim.servers["sphere"].device.reset()
    e = Env(cfg, geo, sim, tmp_path)
    yield e
    for srv in sim.servers.values():
        srv.faults.clear()
    e.model.force_over_temperature = False
    e.devices.close()


def plan(env, estimate=("gradients", "single-image")):
    return build_plan(env.cfg, env.geo.led_directions, estimate=estimate)


def at(steps, kind, frame_no):
    """The step of ``kind`` in the ``frame_no``-th frame (0-based)."""
    fetches = [s for s in steps if s.kind == "fetch"]
    return next(s for s in steps if s.kind == kind and s.frame == fetches[frame_no].frame)


def events(session, type_=None):
    return [e for e in session.events() if type_ is None or e["type"] == type_]


class Crash(Exception):
    pass


def test_interrupted_run_resumes_only_missing_steps(env):
    steps = plan(env)
    s = env.session(steps)
    crash_at = at(steps, "trigger", 3).index

    def crash(i, n, step):
        if i == crash_at:
            raise Crash("power cut")
    with pytest.raises(Crash):
        env.run(steps, s, progress=crash)
    assert env.dark()
    assert events(s, "stop")[-1]["status"] == "aborted" and "Crash" in events(s, "stop")[-1]["reason"]
    first = {f.file: f.sha256 for f in s.frames()}
    assert len(first) == 3 and len(events(s, "survey")) == 2

    ran = []
    result = env.run(steps, s, progress=lambda i, n, step: ran.append(step))
    assert result.status == "complete" and env.dark()
    frames = s.frames()
    assert [f.pattern for f in frames] == ["ambient", "full", "x", "y", "z", "key"]
    assert {f.file: f.sha256 for f in frames[:3]} == first          # nothing re-taken or overwritten
    assert s.verify() == [] and len(events(s, "survey")) == 2       # surveys not repeated
    assert [st.params["pattern"] for st in ran if st.kind == "upload"] == ["y", "z", "key"]
    assert {st.frame for st in ran if st.kind == "fetch"} == {"y/cross", "z/cross", "key/cross"}
    assert result.steps_skipped > 0


def test_interlock_holds_while_over_temperature_then_continues(env):
    steps = plan(env, ("gradients",))
    s = env.session(steps)
    env.model.force_over_temperature = True
    seen = {}

    def watcher():
        wait_for(lambda: events(s, "hold"), what="hold event")
        seen["dark_during_hold"] = env.dark()
        seen["frames_during_hold"] = len(s.frames())
        time.sleep(0.3)                     # several status polls while still hot
        seen["still_holding"] = not events(s, "release")
        env.model.force_over_temperature = False      # it cools

    t = threading.Thread(target=watcher)
    t.start()
    result = env.run(steps, s)
    t.join()
    assert result.status == "complete" and result.holds == 1
    assert seen == {"dark_during_hold": True, "frames_during_hold": 1, "still_holding": True}
    kinds = [e["type"] for e in events(s)]
    assert kinds.index("hold") < kinds.index("release")
    assert [f.pattern for f in s.frames()] == ["ambient", "full", "x", "y", "z"]   # ambient came before
    assert env.dark()


def test_led_fault_bit_pauses_the_capture_with_a_journal_event(env):
    """The sphere's LED-fault status bit (issue 18: it used to be ignored) is journalled as a ``fault`` event and
    pauses the run before the frame it may have spoilt is journalled; the resumed run (the operator checked the
    LEDs: accept_faults) completes with every frame."""
    steps = plan(env, ("gradients",))
    s = env.session(steps)
    fault_at = at(steps, "trigger", 2).index

    def fault(i, n, step):
        if i == fault_at:
            env.model.led_fault = True
    try:
        result = env.run(steps, s, progress=fault, control=RunControl(pause_mode="stop"))
        assert result.status == "paused" and "LED fault" in result.reason
        (f,) = events(s, "fault")
        assert f["fault"] == "led_fault" and f["fault_flags"] & 0x04 and f["action"] == "pause"
        before = sum(1 for st in steps[:fault_at] if st.kind == "fetch")
        assert f["step"] == fault_at and len(s.frames()) == before and env.dark()
        assert s.status() == "paused" and events(s, "pause")
        again = env.run(steps, s, control=RunControl(pause_mode="stop"))     # still faulty: pauses again
        assert again.status == "paused" and len(s.frames()) == before
        done = env.run(steps, s, control=RunControl(pause_mode="stop"), accept_faults=0x04)
        assert done.status == "complete" and len(s.frames()) == 5
    finally:
        env.model.led_fault = False


@pytest.mark.parametrize("action", ["abort", "continue"])
def test_led_fault_action_is_configurable(env, action):
    steps = plan(env, ("gradients",))
    s = env.session(steps)
    env.model.led_fault = True
    try:
        if action == "abort":
            with pytest.raises(FaultStop):
                env.run(steps, s, on_led_fault="abort")
            assert s.status() == "aborted" and [f.pattern for f in s.frames()] == ["ambient"]   # dark: no check
        else:
            assert env.run(steps, s, on_led_fault="continue").status == "complete"
            assert len(s.frames()) == 5
        assert [e["action"] for e in events(s, "fault")] == [action] and env.dark()
    finally:
        env.model.led_fault = False


def test_over_temperature_can_pause_instead_of_holding(env):
    steps = plan(env, ("gradients",))
    s = env.session(steps)
    env.model.force_over_temperature = True
    try:
        result = env.run(steps, s, on_over_temperature="pause", control=RunControl(pause_mode="stop"))
    finally:
        env.model.force_over_temperature = False
    assert result.status == "paused" and "over-temperature" in result.reason
    (f,) = events(s, "fault")
    assert f["fault"] == "over_temperature" and f["action"] == "pause" and not events(s, "hold")
    assert env.run(steps, s).status == "complete" and len(s.frames()) == 5


@pytest.mark.parametrize("n_busy", [1, 3, 6])
def test_busy_sphere_is_asked_again_on_the_same_connection(env, n_busy):
    """A BUSY reply is asked again with backoff on the same connection: no device is reopened however many
    BUSY replies come (issue 18: three of them used to drop and reopen every device)."""
    steps = plan(env, ("gradients",))
    s = env.session(steps)
    busy_at = at(steps, "select", 2).index
    opened = []

    def busy(i, n, step):
        if i == busy_at and not events(s, "busy"):
            env.model.busy_for(n_busy)
    result = env.run(steps, s, progress=busy, reopen=lambda: opened.append(1))
    assert result.status == "complete" and result.reconnects == 0 and not opened
    got = events(s, "busy")
    assert len(got) == n_busy and result.retries == n_busy
    assert all(r["step"] == busy_at and "BUSY" in r["error"] for r in got)
    assert [r["wait_s"] for r in got] == [min(1.0, 0.05 * 2 ** k) for k in range(n_busy)]   # backoff
    assert not events(s, "lost") and len(s.frames()) == 5


@pytest.mark.parametrize("role", ["trigger", "sphere"])
def test_device_unplugged_mid_sequence_pauses_reconnects_resumes(env, role):
    steps = plan(env, ("gradients",))
    s = env.session(steps)
    faults = env.sim.servers[role].faults
    pull_at = at(steps, "select" if role == "trigger" else "trigger", 2).index
    seen = {}

    def pull(i, n, step):
        if i == pull_at and "pulled" not in seen:
            seen["pulled"] = True
            faults.unplugged = True

    def watcher():
        wait_for(lambda: events(s, "lost"), what="lost event")
        # the trigger's loss: the runner switches the sphere off; the sphere's: its own watchdog does
        wait_for(env.dark, timeout_s=20, what="sphere dark")
        seen["dark"] = True
        seen["frames_while_lost"] = len(s.frames())
        faults.unplugged = False          # plugged back in

    t = threading.Thread(target=watcher)
    t.start()
    result = env.run(steps, s, progress=pull, lost_timeout_s=120.0)
    t.join()
    assert seen["dark"] and seen["frames_while_lost"] == 2
    assert result.status == "complete" and result.reconnects >= 1
    kinds = [e["type"] for e in events(s)]
    assert kinds.index("lost") < kinds.index("reconnected") < len(kinds) - 1
    assert [f.pattern for f in s.frames()] == ["ambient", "full", "x", "y", "z"] and s.verify() == []
    assert env.dark()


def test_total_station_dropping_its_tcp_client_is_reconnected(env):
    steps = plan(env, ("gradients",))
    s = env.session(steps)
    survey = next(st for st in steps if st.kind == "survey").index
    cut = []

    def drop(i, n, step):
        if i == survey and not cut:
            cut.append(i)
            env.sim.servers["total_station"].disconnect()      # the server closes the socket: link gone
    result = env.run(steps, s, progress=drop)
    assert result.status == "complete" and result.reconnects == 1
    lost, = events(s, "lost")
    assert lost["step"] == survey and "ConnectionLost" in lost["error"]
    assert [e["step"] for e in events(s, "reconnected")] == [survey]
    assert list(s.surveys()) == ["object_top"] and len(s.frames()) == 5


@pytest.mark.parametrize("mode", ["wait", "stop"])
def test_pause_at_checkpoint_then_resume(env, mode):
    steps = plan(env, ("gradients",))
    s = env.session(steps)
    control = RunControl(pause_mode=mode)
    ask_at = at(steps, "trigger", 1).index
    seen = {}

    def ask(i, n, step):
        if i == ask_at and "asked" not in seen:
            seen["asked"] = True
            control.request_pause("test")

    def resumer():
        wait_for(lambda: events(s, "pause"), what="pause event")
        seen["dark"], seen["frames"] = env.dark(), len(s.frames())
        control.resume()

    t = threading.Thread(target=resumer)
    t.start()
    result = env.run(steps, s, progress=ask, control=control)
    t.join()
    # the pause waited for the frame in progress: it came at the checkpoint after frame 2
    assert seen["dark"] and seen["frames"] == 2
    (p,) = events(s, "pause")
    assert steps[p["step"]].kind == "checkpoint"
    if mode == "wait":
        assert result.status == "complete" and len(events(s, "resume")) == 1
    else:
        assert result.status == "paused" and events(s, "stop")[-1]["status"] == "paused"
        assert s.status() == "paused" and len(s.frames()) == 2
        result = env.run(steps, s, control=RunControl())
        assert result.status == "complete"
    assert len(s.frames()) == 5 and env.dark()


def _drop_folder_gone(env, steps, s):
    os.rename(env.sim.drop_folder, str(env.sim.drop_folder) + ".away")


@pytest.mark.parametrize("path", ["refused", "exception", "trigger-lost", "sphere-lost", "abort",
                                  "sigint-twice", "sigterm"])
def test_sphere_dark_after_every_failure_path(env, path):
    steps = plan(env, ("gradients",))
    s = env.session(steps)
    control = RunControl(pause_mode="wait")
    trig = at(steps, "trigger", 2).index        # frame 3's pattern is lit at this step
    fetch = at(steps, "fetch", 2).index
    fired = set()

    def inject(i, n, step):
        if i in fired:
            return
        fired.add(i)
        if i == trig:
            if path == "refused":
                env.model.nack_next(NackCode.BAD_ARGUMENT)   # the post-exposure status is refused
            elif path == "exception":
                os.rename(env.sim.drop_folder, str(env.sim.drop_folder) + ".away")
            elif path == "trigger-lost":
                env.sim.servers["trigger"].faults.unplugged = True
            elif path == "sphere-lost":
                env.sim.servers["sphere"].faults.unplugged = True
            elif path == "abort":
                control.abort("operator abort")
            elif path in ("sigint-twice", "sigterm"):
                os.kill(os.getpid(), signal.SIGINT if path == "sigint-twice" else signal.SIGTERM)
        elif i == fetch and path == "sigint-twice":
            assert control.state == "pausing"
            os.kill(os.getpid(), signal.SIGINT)

    expected = {"refused": DeviceRejected, "exception": FileNotFoundError, "trigger-lost": ConnectionLost,
                "sphere-lost": ConnectionLost, "abort": Aborted, "sigint-twice": Aborted, "sigterm": Aborted}[path]
    try:
        with signal_handlers(control), pytest.raises(expected) as info:
            env.run(steps, s, progress=inject, control=control, lost_timeout_s=0.5)
    finally:
        away = str(env.sim.drop_folder) + ".away"
        if os.path.exists(away):
            os.rename(away, env.sim.drop_folder)
    assert env.model.frames_received > 0
    if path == "sphere-lost":
        wait_for(env.dark, timeout_s=20, what="the watchdog to darken the sphere")   # nobody could tell it
        assert events(s, "stop")[-1]["lights_off"] is False
    else:
        assert env.dark() and events(s, "stop")[-1]["lights_off"] is True
    stop = events(s, "stop")[-1]
    assert stop["status"] == "aborted" and len(s.frames()) == 2
    if path == "sigint-twice":
        assert info.value.signum == signal.SIGINT and "second Ctrl-C" in stop["reason"]
    if path == "sigterm":
        assert info.value.signum == signal.SIGTERM and stop["reason"] == "SIGTERM"


def test_step_timeout_bounds_the_wait_for_a_frame(env, tmp_path):
    steps = [dataclasses.replace(st, timeout_s=0.3) if st.kind == "fetch" else st
             for st in plan(env, ("gradients",))]
    s = env.session(steps)
    empty = tmp_path / "nothing-arrives"
    empty.mkdir()
    env.devices.camera = FolderCamera(empty)       # frames go to the simulator's folder, not this one
    with pytest.raises(DeviceTimeout, match=r"within 0\.3 s"):
        env.run(steps, s, max_lost_per_step=0)
    retries = events(s, "retry")
    assert len(retries) == 1 and steps[retries[0]["step"]].kind == "fetch"
    assert env.dark() and s.frames() == []


def test_progress_bar_counts_frames_and_gives_an_eta():
    cfg = small_config()
    steps = build_plan(cfg, rig_geometry(cfg).led_directions, estimate=("gradients",))
    out = io.StringIO()
    bar = ProgressBar(steps, out, tty=False)
    for st in steps:
        bar(st.index, len(steps), st, skipped=st.index < 3)
    bar.close()
    lines = out.getvalue().splitlines()
    assert len(lines) == 5                          # one line per frame when not on a terminal
    assert "frame 4/5" in lines[-1] and "ETA " in lines[-1]
    pct = [int(line.split("]")[1].split("%")[0]) for line in lines]
    assert pct == sorted(pct) and pct[-1] < 100


def test_progress_eta_learns_each_step_kinds_pace():
    """The ETA prices each remaining step at the measured mean of its kind: surveys that are instant and frames
    that take 3x their nominal time (issue 18: one pace for all read 0:00 ten seconds early)."""
    cfg = small_config()
    steps = build_plan(cfg, rig_geometry(cfg).led_directions, estimate=("gradients", "single-image"))
    bar = ProgressBar(steps, io.StringIO(), tty=False)
    cost = [0.0 if st.kind == "survey" else 3.0 * st.nominal_s for st in steps]
    clock = [0.0]
    real = time.monotonic
    time.monotonic = lambda: clock[0]
    seen = []
    try:
        for st in steps:
            bar(st.index, len(steps), st)
            if st.kind == "fetch":
                seen.append((bar.eta_s(st.index, clock[0]), sum(cost[st.index:])))
            clock[0] += cost[st.index]
    finally:
        time.monotonic = real
    later = seen[len(seen) // 2:]
    assert all(0.6 * truth <= eta <= 1.6 * truth for eta, truth in later), seen


def test_control_defers_a_signal_abort_out_of_journal_writes():
    control = RunControl()
    with pytest.raises(Aborted, match="SIGTERM"):
        with control.critical():
            control.interrupt("SIGTERM", signal.SIGTERM)   # inside: nothing raised yet
            inside = True
    assert inside and control.abort_requested
    c2 = RunControl()
    with c2.critical(discard=True):
        c2.interrupt("late")
    assert c2.abort_requested
    c3 = RunControl()
    c3.on_sigint()
    assert c3.state == "pausing"
    with pytest.raises(Aborted):
        c3.on_sigint()


def test_session_lock_refuses_a_second_writer(tmp_path):
    from rig.files.session import SessionBusy
    s = Session.create(tmp_path, "x", config={}, devices={}, plan=[])
    with s.lock():
        with pytest.raises(SessionBusy):
            with Session.open(s.root).lock():
                pass
    with s.lock():
        pass
    json.loads((s.root / "manifest.json").read_text())
