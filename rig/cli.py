"""The ``rig`` command line."""
from __future__ import annotations

import argparse
import json
import os

# One BLAS thread unless the user says otherwise (before numpy is imported): the estimators' BLAS work is small
# dense algebra (QR of ~2600 x 130 systems, LED response tables), where OpenBLAS's second thread only spins. Measured
# on the 2-core test machine under load (benchmarks/meshes.py, the 100k-face scene): the single-image fit 2.7-3.9 s
# with one thread, 5.1-18 s with OpenBLAS's default two; the LED response table 2.6 s vs 12 s (benchmarks/gradients.py).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import signal  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from drivers.errors import RigError  # noqa: E402


def load_config(path: Path | None):
    """rig.config.load_config, imported on first use: the schema (pydantic) takes ~0.4 s to build, and every
    long command must say something on stderr within 2 s of its start (issue 18), also on a loaded machine."""
    from rig.config import load_config as _load
    return _load(path)


def _add_config(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=Path, default=None,
                   help="rig config TOML (default: the packaged simulated rig)")


def _add_request(p: argparse.ArgumentParser) -> None:
    p.add_argument("--estimate", nargs="+", default=["gradients", "single-image"],
                   choices=["gradients", "single-image", "specular"],
                   help="what to estimate: gradients (diffusion maps), single-image, specular (normals)")
    p.add_argument("--channels", default="RGB", help="colour channels to capture and process (e.g. RGB, G)")
    p.add_argument("--complements", action=argparse.BooleanOptionalAction, default=None,
                   help="gradients as x, y, z + complements (default: [estimation] complements)")
    p.add_argument("--roi", type=int, nargs=4, metavar=("X0", "Y0", "X1", "Y1"), default=None,
                   help="process only this pixel region of the frames (half-open; default: whole frame)")


def _cmd_demo(args: argparse.Namespace) -> int:
    from rig.demo import format_table, run_demo
    result = run_demo(config_path=args.config, sessions_dir=args.sessions, name=args.name, log=_say(args))
    if args.json:
        from rig.files.provenance import json_default
        print(json.dumps(result, indent=2, default=json_default))
    else:
        print(format_table(result))
    return 0


def _sim_alone(args: argparse.Namespace) -> int:
    """One device's simulator on a URL given by the user (its own module's command line)."""
    from rig.acquire.geometry import rig_geometry
    cfg = load_config(args.config)
    leds = str(len(rig_geometry(cfg).led_positions_mm))
    url = args.url or "pty"
    if args.device == "sphere":
        from simulators.led_sphere import main as sim_main
        return sim_main(["--url", url, "--leds", leds])
    if args.device == "sphere-modbus":
        from simulators.led_sphere_modbus import main as sim_main
        if url.startswith("tcp://"):
            return sim_main(["--tcp", url[len("tcp://"):], "--leds", leds])
        if url == "pty":
            return sim_main(["--rtu", "--leds", leds])
        raise SystemExit(f"rig sim: --url for sphere-modbus: expected 'pty' or tcp://HOST:PORT, got {url!r}")
    if args.device == "trigger":
        from simulators.trigger import main as sim_main
        return sim_main(["--url", url])
    from simulators.total_station import main as sim_main
    return sim_main(["--url", url])


def _cmd_sim(args: argparse.Namespace) -> int:
    if args.fault and "list" in args.fault:
        from rig.acquire.sim_faults import describe
        print(describe())
        return 0
    if args.device:
        if args.fault:
            raise SystemExit("rig sim: --fault applies to the whole simulated rig (without --device)")
        return _sim_alone(args)
    import tempfile

    from rig.acquire.factory import rig_geometry, start_simulators
    from rig.acquire.sim_faults import apply_faults, parse_faults
    cfg = load_config(args.config)
    faults = parse_faults(args.fault or [])
    work = tempfile.TemporaryDirectory(prefix="sssrig-sim-")
    sim = start_simulators(cfg, rig_geometry(cfg), Path(work.name))
    try:
        applied = apply_faults(sim, faults)
        if args.json:
            _json_out({"ok": True, "urls": sim.urls, "faults": applied, "drop_folder": str(sim.drop_folder)})
            sys.stdout.flush()
        else:
            for role, url in sim.urls.items():
                print(f"{role:<14} {url}", flush=True)
            for line in applied:
                print(f"fault          {line}", flush=True)
        print("simulators running; Ctrl-C to stop", file=sys.stderr, flush=True)
        stop = []
        signal.signal(signal.SIGTERM, lambda *a: stop.append(1))
        deadline = time.monotonic() + args.seconds if args.seconds else None
        while not stop and (deadline is None or time.monotonic() < deadline):
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        sim.close()
        work.cleanup()
    return 0


def _request(args: argparse.Namespace):
    from rig.acquire.plan import CaptureRequest
    return CaptureRequest(tuple(args.estimate), tuple(args.channels.upper()), args.complements,   # RequestError:
                          None if args.roi is None else tuple(args.roi))                        # exit 2


def _cmd_plan(args: argparse.Namespace) -> int:
    from rig.acquire.geometry import rig_geometry
    from rig.acquire.plan import budget, build_plan, devices_used, omissions, summarize
    cfg = load_config(args.config)
    geo = rig_geometry(cfg)
    req = _request(args)
    steps = build_plan(cfg, geo.led_directions, request=req)
    if args.json:
        print(json.dumps({"config": cfg.source, "request": req.resolved(cfg).to_dict(),
                          "steps": [s.to_dict() for s in steps], "budget": budget(steps, cfg),
                          "devices": devices_used(steps, cfg), "left_out": omissions(cfg, req)}, indent=2))
    else:
        print(summarize(steps, cfg, req))
    return 0


def _json_out(obj) -> None:
    from rig.files.provenance import json_default
    print(json.dumps(obj, indent=2, default=json_default))


def _say(args: argparse.Namespace):
    """Stage messages on stderr (never stdout: ``--json`` output stays clean); silent with ``--quiet``."""
    fb = getattr(args, "feedback", None)
    return fb if fb is not None else (lambda m: print(m, file=sys.stderr, flush=True))


def _progress_factory(args: argparse.Namespace):
    if args.no_progress or getattr(args, "quiet", False):
        return None
    from rig.acquire.runner import ProgressBar
    fb = getattr(args, "feedback", None)

    def make(steps):
        bar = ProgressBar(steps, sys.stderr)
        if fb is not None:
            fb.suspend()
            bar.on_close = fb.resume
        return bar
    return make


def _control(args: argparse.Namespace):
    """Ctrl-C pauses at the next checkpoint (a second aborts). On a terminal a pause waits for Enter; otherwise
    the run ends as paused, to be continued with `rig resume`."""
    import threading

    from rig.acquire.runner import RunControl
    interactive = sys.stdin is not None and sys.stdin.isatty() and not args.json
    control = RunControl(pause_mode="wait" if interactive else "stop")
    control.notify = lambda m: print(f"\n{m}", file=sys.stderr, flush=True)
    if interactive:
        def read_enter() -> None:
            for _ in sys.stdin:
                if control.state == "paused":
                    control.resume()
        threading.Thread(target=read_enter, name="rig-resume-on-enter", daemon=True).start()
    return control


def _finish_run(args: argparse.Namespace, outcome) -> int:
    """Print the outcome; exit 0 complete, 3 paused (resumable)."""
    if args.json:
        _json_out(outcome.to_dict())
    else:
        r = outcome.result
        n = len(outcome.session.frames())
        planned = sum(1 for s in outcome.steps if s.kind == "fetch")
        print(f"{r.status}: {n}/{planned} frames in {outcome.session.root} ({r.steps_run} steps run, "
              f"{r.steps_skipped} skipped, {r.retries} retries, {r.holds} holds, {r.reconnects} reconnects)")
        for note in outcome.notes:
            print(f"note: {note}")
        if r.status == "paused":
            print(f"continue with: rig resume {outcome.session.root}")
    return 0 if outcome.result.status == "complete" else 3


def _run_guarded(args: argparse.Namespace, fn) -> int:
    """Run a capture/resume under the Ctrl-C handlers (first pauses, second aborts). The handlers stay until the
    outcome is printed: a second Ctrl-C that arrives while the run is already ending at a pause is recorded
    (never raised into the cleanup) and the session then ends as aborted, in the journal and the exit code."""
    from rig.acquire.runner import Aborted, signal_handlers
    control = _control(args)
    with signal_handlers(control):
        try:
            outcome = fn(control)
            control.closing = True
            if control.abort_requested and outcome.result.status != "aborted":
                outcome.session.append_event({"type": "stop", "status": "aborted", "reason": control.abort_reason,
                                              "lights_off": outcome.result.lights_off})
                raise Aborted(control.abort_reason or "aborted", control.abort_signum)
        except Aborted as exc:
            control.closing = True
            print(f"rig {args.command}: aborted ({exc.reason}); the sphere was switched off; continue with "
                  "`rig resume SESSION`", file=sys.stderr)
            if args.json:
                _json_out({"status": "aborted", "reason": exc.reason})
            return 128 + (exc.signum or signal.SIGINT)
        return _finish_run(args, outcome)


def _cmd_capture(args: argparse.Namespace) -> int:
    from rig.acquire.capture import capture, simulated
    cfg = load_config(args.config)
    if args.sim:
        cfg = simulated(cfg)
    req = _request(args)
    world = None
    if args.sim_world:
        if not args.sim:
            raise SystemExit("rig capture: error: --sim-world needs --sim (it replaces the simulated rig)")
        from rig.calibration.run import make_world
        from rig.config.calibration_settings import load_settings
        world = make_world(cfg, load_settings(cfg))
    return _run_guarded(args, lambda control: capture(
        cfg, req, sessions_dir=args.sessions, name=args.name, control=control,
        progress_factory=_progress_factory(args), say=_say(args),
        calibration=args.calibration, sim_world=world))


def _cmd_resume(args: argparse.Namespace) -> int:
    from rig.acquire.capture import resume
    return _run_guarded(args, lambda control: resume(
        args.session, simulate=args.sim, control=control, progress_factory=_progress_factory(args),
        say=_say(args), accept_faults=args.accept_fault))


def _cmd_report(args: argparse.Namespace) -> int:
    from rig.report import write_report
    out = write_report(args.session, out_dir=args.out, fmt=args.format, run_estimators=not args.no_estimate,
                       log=_say(args))
    if args.json:
        _json_out(out)
    else:
        print(out["index"])
    return 0


def _cmd_devices(args: argparse.Namespace) -> int:
    from rig.acquire.capture import device_report, simulated
    cfg = load_config(args.config)
    if args.sim:
        cfg = simulated(cfg)
    rows = device_report(cfg)
    if args.json:
        _json_out({"config": cfg.source, "devices": rows, "ok": all(r["ok"] for r in rows)})
    else:
        for r in rows:
            ident = r.get("identity") or {}
            who = f"{ident.get('model', '?')} fw {ident.get('firmware', '?')} #{ident.get('serial_number', '')}"
            health = r.get("health") or {}
            detail = r.get("error") or ", ".join(f"{k}={v}" for k, v in health.items() if k != "ok")
            print(f"{r['role']:<14} {'ok  ' if r['ok'] else 'FAIL'} {r['url']:<24} {who:<36} {detail}")
    return 0 if all(r["ok"] for r in rows) else 1


def _patches_arg(text: str) -> int | str:
    """argparse type of ``--patches``: "auto" or an integer (its range is checked against the mesh later)."""
    if text == "auto":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 'auto' or an integer number of patches, got {text!r}") from None


def _int_at_least(lo: int):
    """argparse type: an integer >= lo (for the single-image reference options)."""
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer >= {lo}, got {text!r}") from None
        if v < lo:
            raise argparse.ArgumentTypeError(f"expected an integer >= {lo}, got {v}")
        return v
    return parse


def _cmd_estimate(args: argparse.Namespace) -> int:
    if args.what == "single-image":
        from rig.estimate.scenes import run_cli as run_scene  # a scene file a user brings (docs/scene-file.md)
        return run_scene(args)
    if args.what == "batch":
        from rig.estimate.batch import run_cli as run_batch  # many items on Dask (docs/scale-out.md)
        return run_batch(args)
    if args.what == "gradients":
        from rig.estimate.capture_folder import run_cli as run_folder  # a capture folder (docs/capture-folder.md)
        return run_folder(args)
    from rig.estimate.sessions import estimate_session
    from rig.files.provenance import json_default
    out = estimate_session(args.session, calibration=args.calibration, log=_say(args))
    if args.json:
        print(json.dumps(out, indent=2, default=json_default))
    else:
        from rig.estimate.sessions import format_rows
        print(format_rows(out))
    return 0


def _cmd_config(args: argparse.Namespace) -> int:
    if args.schema:
        from rig.acquire.config_check import json_schema
        print(json.dumps(json_schema(), indent=2))
        return 0
    if args.check:
        from rig.acquire.config_check import check_config
        out = check_config(args.check)
        if args.json:
            _json_out(out)
        else:
            b = out["budget"]
            print(f"{args.check}: valid rig config '{out['rig']}' (schema, [calibration], poses, exposures; the plan "
                  f"of every estimator: {b['frames']} frames, peak {b['max_current_a']:.2f} A of "
                  f"{b['max_total_current_a']:g} A, {b['peak_temperature_c']:.1f} C of {b['over_temperature_c']:g} C)")
    else:
        from rig.config import default_config_text
        if args.json:
            _json_out({"ok": True, "file": "<package>/rig/data/default_rig.toml", "text": default_config_text()})
        else:
            print(default_config_text(), end="")
    return 0


class _Parser(argparse.ArgumentParser):
    """argparse that raises :class:`UsageError` instead of exiting, so ``--json`` can report it as JSON."""

    def error(self, message: str):  # type: ignore[override]
        raise UsageError(f"{self.prog}: {message}", self.format_usage())


class UsageError(SystemExit):
    """Bad command-line arguments (exit code 2, as argparse's own)."""

    def __init__(self, message: str, usage: str) -> None:
        super().__init__(2)
        self.message, self.usage = message, usage

    def __str__(self) -> str:
        return self.message


def _common() -> argparse.ArgumentParser:
    """-v / --log-level / --quiet, accepted before or after the command (``rig -v demo``, ``rig demo -v``)."""
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("-v", "--verbose", action="count", default=argparse.SUPPRESS,
                   help="log more on stderr: -v info, -vv debug (the drivers' byte traces, pymodbus, geocompy)")
    p.add_argument("--log-level", default=argparse.SUPPRESS, metavar="LEVEL",
                   choices=["DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL", "debug", "info", "warning", "error",
                            "critical"], help="log level of every logger (overrides -v)")
    p.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                   help="no progress messages on stderr")
    return p


class _Version(argparse.Action):
    """``--version``, reading the installed version only when asked (importlib.metadata costs ~0.4 s)."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: object,
                 option_string: str | None = None) -> None:
        from rig import __version__
        print(f"rig (sssrig) {__version__}")
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    common = _common()
    parser = _Parser(prog="rig", parents=[common],
                     description="sssrig: light-stage acquisition and subsurface-scattering estimation")
    parser.add_argument("--version", action=_Version, nargs=0, help="show the version and exit")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)
    _orig_add = sub.add_parser

    def add_parser(name: str, **kw):
        kw.setdefault("parents", [common])
        return _orig_add(name, **kw)
    sub.add_parser = add_parser  # type: ignore[method-assign]

    p = sub.add_parser("demo", help="simulated capture session + estimates vs truth")
    _add_config(p)
    p.add_argument("--sessions", type=Path, default=Path("sessions"), help="folder for session folders")
    p.add_argument("--name", default=None, help="session name (default: demo-<timestamp>)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("sim", help="start the simulated devices, print their URLs")
    _add_config(p)
    p.add_argument("--seconds", type=float, default=0.0, help="stop after this long (0: until Ctrl-C)")
    p.add_argument("--device", choices=["sphere", "sphere-modbus", "trigger", "total-station"], default=None,
                   help="start only this device's simulator, on --url")
    p.add_argument("--url", default=None, help="with --device: 'pty' (default) or tcp://HOST:PORT")
    p.add_argument("--fault", action="append", metavar="DEVICE:FAULT[=VALUE]",
                   help="inject a fault to rehearse it (repeatable), e.g. sphere:led_fault, sphere:busy=3, "
                        "sphere:over_temperature, trigger:busy, total_station:corrupt=0.003, any:latency=0.2, "
                        "any:mute; `rig sim --fault list` lists them")
    p.add_argument("--json", action="store_true", help="print the URLs (and faults) as JSON")
    p.set_defaults(func=_cmd_sim)

    p = sub.add_parser("plan", help="print a capture plan with its budget (dry run, no devices)")
    _add_config(p)
    _add_request(p)
    p.add_argument("--dry-run", action="store_true", help="accepted for clarity; plan never captures")
    p.add_argument("--json", action="store_true", help="print the plan, budget and devices as JSON")
    p.set_defaults(func=_cmd_plan)

    p = sub.add_parser("capture", help="capture a session: config -> devices -> plan -> session folder")
    _add_config(p)
    _add_request(p)
    p.add_argument("--sim", action="store_true", help="simulate every device (else only those with url 'sim')")
    p.add_argument("--sessions", type=Path, default=Path("sessions"), help="folder for session folders")
    p.add_argument("--name", default=None, help="session name (default: capture-<timestamp>)")
    p.add_argument("--calibration", type=Path, default=None, metavar="FILE",
                   help="calibration file (`rig calibrate`) to record in the manifest (path, revision, SHA-256); "
                        "`rig estimate session` then uses it")
    p.add_argument("--sim-world", action="store_true",
                   help="with --sim: simulate the perturbed true rig that `rig calibrate --sim` measures (same "
                        "config and [scene] seed) instead of the design rig")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true", help="print the outcome as JSON")
    p.set_defaults(func=_cmd_capture)

    p = sub.add_parser("resume", help="continue an interrupted or paused session")
    p.add_argument("session", type=Path, help="session folder")
    p.add_argument("--sim", action="store_true", help="simulate every device")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--accept-fault", action="append", default=[], choices=["led_fault"],
                   help="continue although the sphere still reports this fault (after checking the LEDs)")
    p.add_argument("--json", action="store_true", help="print the outcome as JSON")
    p.set_defaults(func=_cmd_resume)

    p = sub.add_parser("report", help="write a session report (HTML or Markdown with PNGs)")
    p.add_argument("session", type=Path, help="session folder")
    p.add_argument("--format", choices=["html", "md"], default="html", help="report format")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: SESSION/report)")
    p.add_argument("--no-estimate", action="store_true", help="do not run the estimators if none ran yet")
    p.add_argument("--json", action="store_true", help="print the report's summary as JSON")
    p.set_defaults(func=_cmd_report)

    p = sub.add_parser("devices", help="identify each device and report its health")
    _add_config(p)
    p.add_argument("--sim", action="store_true", help="simulate every device")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.set_defaults(func=_cmd_devices)

    p = sub.add_parser("estimate", help="estimate scattering parameters from a session, a scene file or a "
                                        "capture folder")
    esub = p.add_subparsers(dest="what", required=True, metavar="WHAT")
    q = esub.add_parser("session", help="run every estimator a session folder has frames for")
    q.add_argument("session", type=Path, help="session folder (docs/session-format.md)")
    q.add_argument("--calibration", type=Path, default=None, metavar="FILE",
                   help="calibration file to use (default: the one the manifest records, which must be unchanged; "
                        "without one, the design values)")
    q.add_argument("--json", action="store_true", help="print the result as JSON")
    q = esub.add_parser("single-image", help="single-image method on a scene file (docs/scene-file.md)")
    q.add_argument("scene", type=Path, help="scene file (TOML)")
    q.add_argument("--method", choices=["direct", "tikhonov", "pinv"], default=None,
                   help="estimation method (default: the scene file's, else direct)")
    q.add_argument("--model", choices=["dipole-jensen", "dipole-better", "mc-table", "mc-table+reference"],
                   default=None, help="profile model (default: the scene file's [material].model, else "
                   "dipole-jensen); mc-table+reference corrects the Monte Carlo table fit by Monte Carlo renders "
                   "of the scene (one per iteration; docs/scene-file.md)")
    q.add_argument("--reference-spp", type=_int_at_least(2), default=None, metavar="N",
                   help="mc-table+reference: paths per pixel of each reference render (default: the scene "
                        "file's, else 128)")
    q.add_argument("--reference-iterations", type=_int_at_least(1), default=None, metavar="K",
                   help="mc-table+reference: at most K reference renders (default: the scene file's, else 4)")
    q.add_argument("--reference-seed", type=_int_at_least(0), default=None, metavar="S",
                   help="mc-table+reference: seed of every reference render (default: the scene file's, else 1)")
    q.add_argument("--reference-mode", choices=("legacy", "adaptive", "hybrid"), default=None,
                   help="mc-table+reference: 'hybrid' (default: adaptive; where sigma_s' is not ok, legacy from "
                        "the start; docs/model-error.md), 'adaptive' (a first render at spp/8, then the sample count "
                        "whose noise is at most half the fit's) or 'legacy' (every render at --reference-spp)")
    q.add_argument("--shadows", choices=["auto", "on", "off"], default=None,
                   help="cast shadows of the lights on the mesh (default: the scene file's [estimation].shadows, "
                        "else auto = on for non-convex meshes; docs/visibility.md)")
    q.add_argument("--patches", type=_patches_arg, default=None, metavar="auto|N",
                   help="patch budget: N patches from a copy of the mesh decimated to N faces (visibility, pixel "
                        "map and shadows stay on the full mesh); default: the scene file's [estimation].patches, "
                        "else auto = decimate to 10000 a mesh of more than max_patches faces (docs/scene-file.md)")
    q.add_argument("--out", type=Path, default=None,
                   help="JSON result file (default: <scene>.estimate.json beside the scene file)")
    q.add_argument("--json", action="store_true", help="print the result as JSON instead of a table")
    q = esub.add_parser("gradients", help="polarized spherical-gradient maps from a capture folder "
                                          "(docs/capture-folder.md)")
    q.add_argument("folder", type=Path, help="capture folder holding capture.toml and the frames")
    q.add_argument("--out", type=Path, default=None, help="output folder for the maps (default: FOLDER/maps)")
    q.add_argument("--format", choices=["exr", "tiff"], default="exr", help="float map file format")
    q.add_argument("--tile-rows", type=int, default=None, help="rows per processing tile (bounded memory)")
    q.add_argument("--model", choices=["dipole-jensen", "dipole-better", "mc-table"], default="dipole-jensen",
                   help="profile model of the diffusion estimate (default dipole-jensen: exact sphere integrals; the "
                        "others use the first-order small-blur method); its bias against the Monte Carlo table is "
                        "reported (docs/gradients.md)")
    q.add_argument("--maps", default=None, metavar="NAMES",
                   help="comma-separated map files to write (default all): albedo_diffuse, normals_diffuse, "
                        "diffuse_length, albedo_specular, normals_specular, R_d, alpha_prime, D_mm, "
                        "sigma_s_prime_per_mm, sigma_a_per_mm, shortening, D_seed_mm; maps.json says how the "
                        "others follow (docs/capture-folder.md)")
    q.add_argument("--half", action="store_true",
                   help="write normals and albedos as EXR HALF (float16); the diffusion maps stay float32")
    q.add_argument("--relief-window-px", type=_int_at_least(16), default=None, metavar="N",
                   help="without a sphere: window (pixels) of the per-window relief-blur fit (default 64; "
                        "docs/gradients.md sec. 9)")
    q.add_argument("--reference", action="store_true",
                   help="known sphere only: also correct the sphere summary by Monte Carlo renders of the same "
                        "capture (one render of every pattern per iteration; the per-pixel maps stay "
                        "uncorrected; docs/capture-folder.md)")
    q.add_argument("--reference-spp", type=_int_at_least(2), default=None, metavar="N",
                   help="--reference: paths per pixel of each reference render (default 64)")
    q.add_argument("--reference-iterations", type=_int_at_least(1), default=None, metavar="K",
                   help="--reference: at most K reference renders (default 8), plus a scan of 9 for a "
                        "channel whose shortening is below 0.1 (a lens-like sphere)")
    q.add_argument("--reference-seed", type=_int_at_least(0), default=None, metavar="S",
                   help="--reference: seed of every reference render (default 1)")
    q.add_argument("--reference-mode", choices=("adaptive", "legacy"), default=None,
                   help="--reference: 'adaptive' (default: renders at spp/8 first, at spp once needed; "
                        "docs/gradients.md) or 'legacy' (every render at --reference-spp)")
    q.add_argument("--json", action="store_true", help="print the summary as JSON instead of a table")
    q = esub.add_parser("batch", help="many sessions, scene files and capture folders on Dask workers "
                        "(docs/scale-out.md)")
    q.add_argument("items", type=Path, nargs="+", metavar="ITEM",
                   help="session folders, scene files (.toml) and capture folders, in any mix")
    where = q.add_mutually_exclusive_group()
    where.add_argument("--workers", type=_int_at_least(0), default=2, metavar="N",
                       help="local worker processes, one thread each (default 2; 0: serial, in this process)")
    where.add_argument("--scheduler", default=None, metavar="ADDRESS",
                       help="a running Dask scheduler (tcp://host:8786) instead of a local cluster")
    q.add_argument("--out", type=Path, default=Path("batch-out"),
                   help="output folder: one sub-folder per item, batch.json (default ./batch-out)")
    q.add_argument("--model", choices=["dipole-jensen", "dipole-better", "mc-table", "mc-table+reference"],
                   default=None, help="scene files: profile model (default: each scene's [material].model)")
    q.add_argument("--method", choices=["direct", "tikhonov", "pinv"], default=None,
                   help="scene files: solver (default: each scene's [estimation].method)")
    q.add_argument("--reference", action="store_true",
                   help="capture folders: also the Monte Carlo corrected sphere summary")
    q.add_argument("--reference-spp", type=_int_at_least(2), default=None, metavar="N",
                   help="Monte Carlo paths per pixel of each reference render (scenes and --reference)")
    q.add_argument("--reference-iterations", type=_int_at_least(1), default=None, metavar="K",
                   help="at most K reference renders per item")
    q.add_argument("--reference-seed", type=_int_at_least(0), default=None, metavar="S",
                   help="seed of the reference renders (the same on any number of workers)")
    q.add_argument("--format", choices=["exr", "tiff"], default="exr", help="capture folders: map file format")
    q.add_argument("--calibration", type=Path, default=None, metavar="FILE",
                   help="sessions: calibration file (default: the one each manifest records)")
    q.add_argument("--render-chunk-rows", type=_int_at_least(0), default=None, metavar="ROWS",
                   help="scene files: split each Monte Carlo reference render into chunks of ROWS rows across the "
                        "workers (the same numbers; helps when fewer items than workers are left; 0: whole renders; "
                        "default: 2 chunks per item slot, at most 8, on a cluster whose workers advertise the "
                        "'item' resource, "
                        "as --workers N's do, else whole renders)")
    q.add_argument("--no-progress", action="store_true", help="no progress bar (the per-item lines stay)")
    q.add_argument("--json", action="store_true", help="print the batch report as JSON")
    p.set_defaults(func=_cmd_estimate)

    from rig.calibration.cli import add_parser as add_calibrate
    add_calibrate(sub)

    p = sub.add_parser("config", help="print the default config, --check a file, or print the --schema")
    p.add_argument("--check", type=Path, default=None, metavar="FILE",
                   help="validate this config file: schema, [calibration], poses, exposures, the plan's budgets")
    p.add_argument("--schema", action="store_true", help="print the JSON Schema of rig config files (for editors)")
    p.add_argument("--json", action="store_true", help="with --check: print the resolved config as JSON")
    p.set_defaults(func=_cmd_config)
    return parser


# commands that can take more than 2 s: they report stages on stderr from the start
_LONG = {"demo": "simulated session and estimates", "capture": "capture", "resume": "resume",
         "report": "report", "devices": "device check", "estimate": "estimate", "calibrate": "calibration"}


def _error_json(exc: BaseException, kind: str) -> dict:
    err = {"type": kind, "message": str(exc)}
    for key in ("file", "field", "expected"):
        if getattr(exc, key, None) is not None:
            err[key] = str(getattr(exc, key))
    return {"ok": False, "error": err}


def main(argv: list[str] | None = None) -> int:
    """Run ``rig``. Exit codes: 0 ok, 1 a device check failed / internal error, 2 bad input (config, file,
    arguments), 3 paused (resumable), 128 + signal on abort. Errors are one line on stderr, or a JSON object
    on stdout with ``--json``; tracebacks only with ``-vv``."""
    import logging

    import os
    if os.name != "posix":  # pragma: no cover - exercised only off POSIX
        from rig import POSIX_ONLY
        print(f"rig: error: {POSIX_ONLY}", file=sys.stderr)
        return 2
    argv = list(sys.argv[1:] if argv is None else argv)
    want_json = "--json" in argv
    try:
        args = build_parser().parse_args(argv)
    except UsageError as exc:
        if want_json:
            _json_out(_error_json(exc, "usage"))
        else:
            print(exc.usage + exc.message, file=sys.stderr)
        return 2
    from rig.feedback import Feedback, setup_logging
    setup_logging(getattr(args, "verbose", 0), getattr(args, "log_level", None))
    quiet = getattr(args, "quiet", False)
    args.quiet = quiet
    args.feedback = Feedback(f"rig {args.command}", enabled=not quiet and args.command in _LONG)
    if args.command in _LONG:
        args.feedback.stage(f"rig {args.command}: {_LONG[args.command]} ...")
    try:
        return int(args.func(args) or 0)
    except RigError as exc:
        if getattr(args, "json", False):
            _json_out(_error_json(exc, type(exc).__name__))
        print(f"rig {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except SystemExit as exc:
        if isinstance(exc.code, str):
            if getattr(args, "json", False):
                _json_out(_error_json(exc, "usage"))
            print(exc.code, file=sys.stderr)
            return 2
        raise
    except KeyboardInterrupt:
        print(f"rig {args.command}: interrupted", file=sys.stderr)
        return 130
    except (OSError, ValueError) as exc:      # a bad path or value the checks above did not name
        logging.getLogger("rig").debug("rig %s failed", args.command, exc_info=True)
        if getattr(args, "json", False):
            _json_out(_error_json(exc, type(exc).__name__))
        print(f"rig {args.command}: error: {type(exc).__name__}: {exc} (-vv shows where)", file=sys.stderr)
        return 2
    finally:
        args.feedback.close()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
