"""Capture, resume and device checks: config -> devices (real or simulated) -> plan -> session -> runner.

Used by ``rig capture``, ``rig resume`` and ``rig devices`` (docs/capture-and-resume.md). A device whose URL is
``sim`` (or every device, with ``simulate=True``) gets its simulator started on a real transport by
:func:`rig.factory.start_simulators`; the drivers then talk to it over the wire as to hardware.
"""
from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import hashlib
import os
import tempfile
import time
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from drivers.errors import LimitError, RigError

from .config import RigConfig, parse_config
from .factory import ROLES, SimulatedRig, open_devices, skip_exposure_waits, start_simulators, uses_simulators
from .geometry import RigGeometry, geometry_to_dict, rig_geometry
from .plan import CaptureRequest, Step, budget, build_plan, steps_from_dicts
from .runner import Devices, RunControl, RunResult, run_plan
from .session import Session, SessionError, software_version, validate_session_name




def config_from_snapshot(snapshot: dict[str, Any], file: str) -> RigConfig:
    """Re-validate a manifest's config snapshot (``RigConfig.to_dict()``); errors name ``file`` and the field."""
    from . import schema

    data = {k: v for k, v in snapshot.items() if k != "name"}
    data["rig"] = {"name": snapshot.get("name")}
    # to_dict() writes every field of the dataclass; the schema refuses keys of another driver or shape: keep
    # the keys of the variant the snapshot names
    for section, tag in (("trigger", "driver"), ("camera", "driver"), ("object", "shape")):
        table = data.get(section)
        if not isinstance(table, dict):
            continue
        for model in schema.union_models(schema.RigFile, section):
            if table.get(tag) in typing.get_args(model.model_fields[tag].annotation):
                data[section] = {k: v for k, v in table.items() if k in model.model_fields}
    return parse_config(data, f"{file}: config")


def simulated(config: RigConfig) -> RigConfig:
    """The same rig with every device simulated (``url = "sim"``, camera folder ``"sim"``)."""
    r = dataclasses.replace
    return r(config, sphere=r(config.sphere, url="sim"), trigger=r(config.trigger, url="sim"),
             camera=r(config.camera, driver="folder", folder="sim"),
             total_station=r(config.total_station, url="sim"))


@dataclass
class Rig:
    config: RigConfig
    geometry: RigGeometry
    devices: Devices
    sim: SimulatedRig | None

    def url(self, role: str) -> str:
        if self.sim is not None and role in self.sim.urls:
            return self.sim.urls[role]
        c = self.config
        return {"sphere": c.sphere.url, "trigger": c.trigger.url, "camera": c.camera.folder,
                "total_station": c.total_station.url}[role]

    def identities(self) -> dict[str, dict[str, Any]]:
        out = {}
        for role, dev in zip(ROLES, (self.devices.light, self.devices.trigger, self.devices.camera,
                                     self.devices.feed)):
            if dev is None:
                continue
            ident = dataclasses.asdict(dev.identify())
            ident["url"] = self.url(role)
            out[role] = ident
        return out

    def reopen(self) -> Devices:
        return open_devices(self.config, self.geometry, self.sim)


@contextlib.contextmanager
def open_rig(config: RigConfig, *, sim_world: Any | None = None) -> Iterator[Rig]:
    """Start the simulators the config asks for, open every device; close all on exit (the sphere's driver
    switches it off on close).

    ``sim_world`` (a ``rig.calibration.simworld.SimulatedCalibrationWorld``, simulated rigs only): the simulators
    run that world's *true* rig instead of the design (LED positions and gains, camera pose, intrinsics and lens
    distortion, black pedestal, sensor nonlinearity, PSF; what ``rig calibrate --sim`` measures) and its camera
    renders the config's ``[scene]`` object through it. The drivers still aim from the design geometry."""
    geo = rig_geometry(config)
    with contextlib.ExitStack() as stack:
        sim = None
        if uses_simulators(config):
            work = stack.enter_context(tempfile.TemporaryDirectory(prefix="sssrig-sim-"))
            sim = start_simulators(config, geo if sim_world is None else sim_world.truth_geometry(), Path(work))
            stack.callback(sim.close)
            if sim_world is not None:
                _render_scene_in(sim_world, config, sim)
        elif sim_world is not None:
            raise ValueError("sim_world needs a simulated rig (device URLs 'sim'; see rig.capture.simulated)")
        devices = open_devices(config, geo, sim)
        stack.callback(devices.close)
        if sim_world is not None:
            skip_exposure_waits(devices, sim)           # the simulated camera renders at once
        yield Rig(config, geo, devices, sim)


def _render_scene_in(world: Any, config: RigConfig, sim: SimulatedRig) -> None:
    """Make the simulated camera of ``sim`` render the ``[scene]`` object in ``world``'s true rig."""
    from simulators.scene import SphereObject
    from simulators.targets import TranslucentSphereTarget

    sc = config.scene
    world.world.target = TranslucentSphereTarget(SphereObject(sc.center_mm, sc.radius_mm, sc.sigma_s_prime_per_mm,
                                                              sc.sigma_a_per_mm, sc.eta,
                                                              tessellation=sc.tessellation))
    world.attach(sim)
    sim.truth = {**sim.truth, "rig": world.truth_dict()}


def calibration_record(path: str | os.PathLike[str], config: RigConfig | None = None) -> dict[str, Any]:
    """The manifest's ``calibration`` field for the calibration file at ``path``: absolute ``file``, ``rig``,
    ``revision``, ``sha256`` of its bytes. The file is validated (``CalibrationError`` naming the file and field)
    and must belong to ``config``'s rig."""
    from .calibration.store import CalibrationError, load_calibration

    p = Path(path).resolve()
    cal = load_calibration(p)
    rig_name = cal.doc.get("rig")
    if config is not None and rig_name != config.name:
        raise CalibrationError(p, "rig", f"the rig being captured ({config.name!r}, [rig] name of "
                               f"{config.source or 'the config'})", rig_name)
    return {"file": str(p), "rig": rig_name, "revision": int(cal.doc["revision"]),
            "sha256": hashlib.sha256(p.read_bytes()).hexdigest(),
            "sections": sorted(cal.doc["steps"])}


def default_session_name(prefix: str = "capture") -> str:
    return f"{prefix}-{_dt.datetime.now().strftime('%Y%m%d-%H%M%S')}"


@dataclass
class Outcome:
    session: Session
    result: RunResult
    steps: list[Step]
    notes: list[str] = dataclasses.field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        frames = self.session.frames()
        return {"session": str(self.session.root), **self.result.to_dict(),
                "frames": len(frames), "frames_planned": sum(1 for s in self.steps if s.kind == "fetch"),
                "notes": self.notes}


def runner_options(cfg: RigConfig) -> dict[str, Any]:
    """:func:`rig.runner.run_plan` options from the config's ``[sphere]`` watchdog and ``[runner]`` table."""
    r = cfg.runner
    return {"watchdog_s": cfg.sphere.watchdog_s or None, "retries": r.retries, "busy_timeout_s": r.busy_timeout_s,
            "on_led_fault": r.on_led_fault, "on_over_temperature": r.on_over_temperature,
            "lost_timeout_s": r.lost_timeout_s, "max_hold_s": r.max_hold_s}


def _run(session: Session, steps: list[Step], rig: Rig, led_directions: np.ndarray, *,
         control: RunControl | None, progress: Callable[..., None] | None, say: Callable[[str], None],
         run_options: dict[str, Any] | None) -> RunResult:
    cfg = rig.config
    opts = {**runner_options(cfg), **(run_options or {})}
    return run_plan(steps, rig.devices, session, led_directions=led_directions,
                    pattern_peak=cfg.sphere.pattern_peak, fetch_timeout_s=cfg.camera.fetch_timeout_s,
                    progress=progress, control=control, reopen=rig.reopen, say=say, **opts)


def capture(config: RigConfig, request: CaptureRequest, *, sessions_dir: str | Path, name: str | None = None,
            control: RunControl | None = None, progress_factory: Callable[[list[Step]], Any] | None = None,
            say: Callable[[str], None] | None = None, run_options: dict[str, Any] | None = None,
            calibration: str | os.PathLike[str] | None = None, sim_world: Any | None = None) -> Outcome:
    """Plan ``request`` on ``config``'s rig, create the session, run the plan.

    ``calibration``: a calibration file (``rig calibrate``) to record in the manifest (path, revision, SHA-256;
    :func:`calibration_record`): ``rig estimate session`` then uses it. ``sim_world``: see :func:`open_rig`.

    Refuses before touching a device if the name is invalid or taken, the calibration file is invalid or of
    another rig, or the plan has problems (current over the limit, a watchdog shorter than an exposure...:
    :func:`rig.plan.budget`)."""
    say = say or (lambda m: None)
    name = validate_session_name(name or default_session_name())
    if (Path(sessions_dir) / name).exists():
        raise SessionError(f"{Path(sessions_dir) / name}: a session with this name exists; choose another "
                           "name or `rig resume` it")
    cal_record = calibration_record(calibration, config) if calibration is not None else None
    geo = rig_geometry(config)
    steps = build_plan(config, geo.led_directions, request=request)
    problems = budget(steps, config)["problems"]
    if problems:
        raise LimitError("the plan cannot run safely: " + "; ".join(problems))
    with open_rig(config, sim_world=sim_world) as rig:
        ids = rig.identities()
        truth = rig.sim.truth if rig.sim is not None and "camera" in rig.sim.urls else None
        session = Session.create(sessions_dir, name, config=config.to_dict(), devices=ids,
                                 plan=[s.to_dict() for s in steps], geometry=geometry_to_dict(rig.geometry),
                                 truth=truth, request=request.resolved(config).to_dict(), calibration=cal_record)
        if cal_record is not None:
            say(f"calibration {cal_record['file']} (revision {cal_record['revision']})")
        say(f"session {session.root}")
        progress = progress_factory(steps) if progress_factory else None
        with session.lock():
            try:
                result = _run(session, steps, rig, rig.geometry.led_directions, control=control,
                              progress=progress, say=say, run_options=run_options)
            finally:
                if progress is not None and hasattr(progress, "close"):
                    progress.close()
    return Outcome(session, result, steps)


def resume(root: str | Path, *, simulate: bool = False, control: RunControl | None = None,
           progress_factory: Callable[[list[Step]], Any] | None = None, say: Callable[[str], None] | None = None,
           run_options: dict[str, Any] | None = None, accept_faults: Any = ()) -> Outcome:
    """Continue a session: only the steps without a journalled frame or survey run (and the setup they need).

    The plan, config and LED geometry come from the session's manifest, so the resumed frames are taken exactly
    as planned. A session already complete is left alone. ``accept_faults`` (e.g. ``["led_fault"]``): sphere
    faults the operator has checked; they are journalled but no longer pause the run."""
    from .runner import FAULT_NAMES

    say = say or (lambda m: None)
    mask = 0
    for name in accept_faults or ():
        bits = [b for b, n in FAULT_NAMES.items() if n == name]
        if not bits:
            raise ValueError(f"accept_faults: unknown fault {name!r}; expected one of {', '.join(FAULT_NAMES.values())}")
        mask |= bits[0]
    if mask:
        run_options = {**(run_options or {}), "accept_faults": mask}
    session = Session.open(root)
    with session.lock():
        m = session.manifest
        steps = steps_from_dicts(m["plan"])
        if session.status() == "complete":
            return Outcome(session, RunResult(status="complete", reason="already complete", lights_off=True),
                           steps, ["the session was already complete: nothing to do"])
        config = config_from_snapshot(m["config"], str(session.root / "manifest.json"))
        if simulate:
            config = simulated(config)
        done = session.completed_steps()
        missing = [s.index for s in steps if s.kind in ("fetch", "survey") and s.index not in done]
        notes = []
        with open_rig(config) as rig:
            ids = rig.identities()
            for role, ident in ids.items():
                old = m.get("devices", {}).get(role)
                if old and (old.get("model"), old.get("serial_number")) != (ident["model"], ident["serial_number"]):
                    notes.append(f"{role}: was {old.get('model')} #{old.get('serial_number')}, now "
                                 f"{ident['model']} #{ident['serial_number']}")
            session.append_event({"type": "restart", "software_version": software_version(), "devices": ids,
                                  "missing_steps": missing, "device_changes": notes})
            say(f"resuming {session.root}: {len(missing)} frame/survey step(s) missing")
            for n in notes:
                say(f"note: device changed since the session started: {n}")
            dirs = np.asarray(m["geometry"]["led_directions"], float) if m.get("geometry") else \
                rig.geometry.led_directions
            progress = progress_factory(steps) if progress_factory else None
            try:
                result = _run(session, steps, rig, dirs, control=control, progress=progress, say=say,
                              run_options=run_options)
            finally:
                if progress is not None and hasattr(progress, "close"):
                    progress.close()
    return Outcome(session, result, steps, notes)


# ---------------------------------------------------------------------------------------------- devices
_FAULT_BITS = {0x01: "over_temperature", 0x02: "watchdog_tripped", 0x04: "led_fault"}


def _health(role: str, dev: Any) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if role == "sphere":
        st = dev.status()
        out = {"temperature_c": st.temperature_c, "current_a": st.current_a, "lit": st.lit,
               "active_slot": st.active_slot, "polarization": st.polarization.name.lower(),
               "faults": [name for bit, name in _FAULT_BITS.items() if st.fault_flags & bit]}
        out["ok"] = not (st.fault_flags & 0x05)
    elif role == "trigger":
        count = getattr(dev, "shot_count", None)
        if count is not None:
            out["shot_count"] = count()
        out["ok"] = True
    elif role == "camera":
        folder = Path(getattr(dev, "folder", ""))
        out = {"folder": str(folder), "exists": folder.is_dir(),
               "writable": folder.is_dir() and os.access(folder, os.W_OK)}
        out["ok"] = out["exists"]
    else:
        out["ok"] = True
    return out


def device_report(config: RigConfig) -> list[dict[str, Any]]:
    """Open, identify and read the health of each device on its own: one unreachable device does not keep the
    others from being checked. One row per role: ``ok``, ``identity``, ``health`` or ``error``, ``seconds``."""
    from .factory import open_device

    geo = rig_geometry(config)
    rows: list[dict[str, Any]] = []
    urls = {"sphere": config.sphere.url, "trigger": config.trigger.url, "camera": config.camera.folder,
            "total_station": config.total_station.url}
    with contextlib.ExitStack() as stack:
        sim = None
        if uses_simulators(config):
            work = stack.enter_context(tempfile.TemporaryDirectory(prefix="sssrig-sim-"))
            sim = start_simulators(config, geo, Path(work))
            stack.callback(sim.close)
        for role in ROLES:
            url = sim.urls.get(role, urls[role]) if sim is not None else urls[role]
            row: dict[str, Any] = {"role": role, "url": url, "ok": False}
            t0 = time.perf_counter()
            dev = None
            try:
                dev = open_device(role, config, geo, sim)
                row["identity"] = dataclasses.asdict(dev.identify())
                row["health"] = _health(role, dev)
                row["ok"] = bool(row["health"].get("ok"))
            except (RigError, OSError, ValueError) as exc:
                row["error"] = f"{type(exc).__name__}: {exc}"
            finally:
                if dev is not None:
                    with contextlib.suppress(Exception):
                        dev.close()
            row["seconds"] = round(time.perf_counter() - t0, 4)
            rows.append(row)
    return rows
