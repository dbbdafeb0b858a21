"""The ``rig`` command line."""
from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from pathlib import Path

from drivers.errors import RigError

from .config import default_config_text, load_config


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
    from .demo import format_table, run_demo
    result = run_demo(config_path=args.config, sessions_dir=args.sessions, name=args.name,
                      log=None if args.json else (lambda m: print(m, file=sys.stderr, flush=True)))
    if args.json:
        from .session import _json_default
        print(json.dumps(result, indent=2, default=_json_default))
    else:
        print(format_table(result))
    return 0


def _sim_alone(args: argparse.Namespace) -> int:
    """One device's simulator on a URL given by the user (its own module's command line)."""
    from .geometry import rig_geometry
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
    if args.device:
        return _sim_alone(args)
    from .factory import rig_geometry, start_simulators
    cfg = load_config(args.config)
    sim = start_simulators(cfg, rig_geometry(cfg))
    try:
        for role, url in sim.urls.items():
            print(f"{role:<14} {url}", flush=True)
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
    return 0


def _request(args: argparse.Namespace):
    from .plan import CaptureRequest
    return CaptureRequest(tuple(args.estimate), tuple(args.channels.upper()), args.complements,   # RequestError:
                          None if args.roi is None else tuple(args.roi))                        # exit 2


def _cmd_plan(args: argparse.Namespace) -> int:
    from .geometry import rig_geometry
    from .plan import budget, build_plan, devices_used, omissions, summarize
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
    from .session import _json_default
    print(json.dumps(obj, indent=2, default=_json_default))


def _say(args: argparse.Namespace):
    return lambda m: print(m, file=sys.stderr, flush=True)


def _progress_factory(args: argparse.Namespace):
    if args.json or args.no_progress:
        return None
    from .runner import ProgressBar
    return lambda steps: ProgressBar(steps, sys.stderr)


def _control(args: argparse.Namespace):
    """Ctrl-C pauses at the next checkpoint (a second aborts). On a terminal a pause waits for Enter; otherwise
    the run ends as paused, to be continued with `rig resume`."""
    import threading

    from .runner import RunControl
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
    from .runner import Aborted, signal_handlers
    control = _control(args)
    try:
        with signal_handlers(control):
            outcome = fn(control)
    except Aborted as exc:
        print(f"rig {args.command}: aborted ({exc.reason}); the sphere was switched off; continue with "
              "`rig resume SESSION`", file=sys.stderr)
        if args.json:
            _json_out({"status": "aborted", "reason": exc.reason})
        return 128 + (exc.signum or signal.SIGINT)
    return _finish_run(args, outcome)


def _cmd_capture(args: argparse.Namespace) -> int:
    from .capture import capture, simulated
    cfg = load_config(args.config)
    if args.sim:
        cfg = simulated(cfg)
    req = _request(args)
    world = None
    if args.sim_world:
        if not args.sim:
            raise SystemExit("rig capture: error: --sim-world needs --sim (it replaces the simulated rig)")
        from .calibration.run import make_world
        from .calibration.settings import load_settings
        world = make_world(cfg, load_settings(cfg))
    return _run_guarded(args, lambda control: capture(
        cfg, req, sessions_dir=args.sessions, name=args.name, control=control,
        progress_factory=_progress_factory(args), say=None if args.json else _say(args),
        calibration=args.calibration, sim_world=world))


def _cmd_resume(args: argparse.Namespace) -> int:
    from .capture import resume
    return _run_guarded(args, lambda control: resume(
        args.session, simulate=args.sim, control=control, progress_factory=_progress_factory(args),
        say=None if args.json else _say(args)))


def _cmd_report(args: argparse.Namespace) -> int:
    from .report import write_report
    out = write_report(args.session, out_dir=args.out, fmt=args.format, run_estimators=not args.no_estimate,
                       log=None if args.json else _say(args))
    if args.json:
        _json_out(out)
    else:
        print(out["index"])
    return 0


def _cmd_devices(args: argparse.Namespace) -> int:
    from .capture import device_report, simulated
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
        from .scene_file import run_cli as run_scene  # a scene file a user brings (docs/scene-file.md)
        return run_scene(args)
    if args.what == "gradients":
        from .capture_folder import run_cli as run_folder  # a capture folder (docs/capture-folder.md)
        return run_folder(args)
    from .estimate import estimate_session
    from .session import _json_default
    out = estimate_session(args.session, calibration=args.calibration,
                           log=None if args.json else (lambda m: print(m, file=sys.stderr)))
    if args.json:
        print(json.dumps(out, indent=2, default=_json_default))
    else:
        for row in out.get("rows", []):
            print("  ".join(f"{k}={v}" for k, v in row.items()))
    return 0


def _cmd_config(args: argparse.Namespace) -> int:
    if args.check:
        cfg = load_config(args.check)
        print(f"{args.check}: valid rig config '{cfg.name}'")
    else:
        print(default_config_text(), end="")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="rig", description="sssrig: light-stage acquisition and subsurface-scattering estimation")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

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
    q.add_argument("--reference", action="store_true",
                   help="known sphere only: also correct the sphere summary by Monte Carlo renders of the same "
                        "capture (one render of every pattern per iteration; the per-pixel maps stay "
                        "uncorrected; docs/capture-folder.md)")
    q.add_argument("--reference-spp", type=_int_at_least(2), default=None, metavar="N",
                   help="--reference: paths per pixel of each reference render (default 64)")
    q.add_argument("--reference-iterations", type=_int_at_least(1), default=None, metavar="K",
                   help="--reference: at most K reference renders (default 4)")
    q.add_argument("--reference-seed", type=_int_at_least(0), default=None, metavar="S",
                   help="--reference: seed of every reference render (default 1)")
    q.add_argument("--json", action="store_true", help="print the summary as JSON instead of a table")
    p.set_defaults(func=_cmd_estimate)

    from .calibration.cli import add_parser as add_calibrate
    add_calibrate(sub)

    p = sub.add_parser("config", help="print the default config or --check a file")
    p.add_argument("--check", type=Path, default=None, help="validate this config file")
    p.set_defaults(func=_cmd_config)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except RigError as exc:
        print(f"rig {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"rig {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
