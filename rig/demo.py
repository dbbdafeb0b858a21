"""``rig demo``: a whole simulated light-stage session, then both estimators, compared with the truth.

The simulators start on real transports (ptys, loopback TCP), the drivers talk to them over the wire,
frames go to a session folder, and the estimators read only that folder (docs/session-format.md).
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

from rig.config import load_config
from rig.estimate.sessions import estimate_session, format_rows
from rig.acquire.factory import open_devices, start_simulators
from rig.acquire.geometry import geometry_to_dict, rig_geometry
from rig.acquire.plan import CaptureRequest, build_plan
from rig.acquire.runner import run_plan
from rig.files.session import Session


def run_demo(*, config_path: str | Path | None = None, sessions_dir: str | Path = "sessions",
             name: str | None = None, log: Callable[[str], None] | None = None) -> dict[str, Any]:
    say = log or (lambda m: None)
    timings: list[tuple[str, float]] = []

    def timed(label: str, fn, *a, **kw):
        t0 = time.perf_counter()
        out = fn(*a, **kw)
        timings.append((label, time.perf_counter() - t0))
        say(f"{label}: {timings[-1][1]:.2f} s")
        return out

    cfg = load_config(config_path)
    geo = rig_geometry(cfg)
    name = name or "demo-" + _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    with tempfile.TemporaryDirectory(prefix="sssrig-demo-") as work:
        sim = timed("start simulators", start_simulators, cfg, geo, Path(work))
        try:
            for role, url in sim.urls.items():
                say(f"  {role:<14} {url}")
            devices = timed("connect devices", open_devices, cfg, geo, sim)
            try:
                identities = {}
                for role, dev in (("sphere", devices.light), ("trigger", devices.trigger),
                                  ("camera", devices.camera), ("total_station", devices.feed)):
                    ident = dataclasses.asdict(dev.identify())
                    ident["url"] = sim.urls.get(role, "")
                    identities[role] = ident
                request = CaptureRequest()
                steps = build_plan(cfg, geo.led_directions, request=request)
                session = Session.create(sessions_dir, name, config=cfg.to_dict(), devices=identities,
                                         plan=[s.to_dict() for s in steps],
                                         geometry=geometry_to_dict(geo), truth=sim.truth,
                                         request=request.resolved(cfg).to_dict())
                say(f"session {session.root}")
                n_frames = sum(1 for s in steps if s.kind == "fetch")
                timed(f"capture ({n_frames} frames)", run_plan, steps, devices, session,
                      led_directions=geo.led_directions, pattern_peak=cfg.sphere.pattern_peak,
                      fetch_timeout_s=cfg.camera.fetch_timeout_s, watchdog_s=cfg.sphere.watchdog_s or None,
                      reopen=lambda: open_devices(cfg, geo, sim),
                      progress=lambda i, n, s: say(f"  step {i + 1}/{n}: {s.kind} "
                                                   f"{s.params.get('pattern', s.params.get('target', ''))}"))
            finally:
                devices.close()
        finally:
            sim.close()
    estimates = estimate_session(session.root, log=say)
    return {"session": str(session.root), "timings_s": dict(timings), **estimates}


def format_table(result: dict[str, Any]) -> str:
    lines = [format_rows(result)]
    for label, sec in result["timings_s"].items():
        lines.append(f"{label:<34} {sec:>8.2f} s")
    lines.append(f"session: {result['session']}")
    return "\n".join(lines)
