"""``rig calibrate STEP``: the calibration steps from the command line (``docs/calibration.md``).

Wire into ``rig/cli.py``'s ``build_parser`` with ``from .calibration.cli import add_parser; add_parser(sub)``;
the parser sets ``func`` like the other commands, so ``main`` runs it and reports ``RigError`` s.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Callable

STEP_HELP = {
    "intrinsics": "camera intrinsics and lens distortion from a ChArUco board",
    "rig-frame": "camera pose from surveyed targets (solvePnP) and LED positions refined by survey",
    "led-directions": "LED directions from a mirror ball",
    "gains": "per-LED, per-channel gains from a diffuse sphere",
    "extinction": "polarizer extinction check: a cross-polarized mirror ball must be dark",
    "radiometry": "black level and linearity from RAW; absolute albedo scale from a reference target",
    "seed-k": "the length k of D = k R_d / |n_z| from a reference material",
    "all": "every step in order, each reading the ones before",
}

__all__ = ["add_parser", "run_cli", "STEP_HELP"]


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``calibrate`` (with one subcommand per step and ``all``) to the ``rig`` subparsers."""
    p = subparsers.add_parser("calibrate", help="scripted calibration of the rig; writes a versioned calibration file",
                              description="Capture a calibration step through the plans and runner, compute it, and "
                                          "write its section of the calibration file (docs/calibration.md).")
    steps = p.add_subparsers(dest="step", required=True, metavar="STEP")
    for name, text in STEP_HELP.items():
        q = steps.add_parser(name, help=text, description=text)
        q.add_argument("--config", type=Path, default=None,
                       help="rig config TOML; its [calibration] table sets the targets (default: packaged rig)")
        q.add_argument("--sim", action="store_true",
                       help="simulate every device and target; the output also compares with the simulator's truth")
        q.add_argument("--out", type=Path, default=Path("calibration.json"),
                       help="calibration file to create or update (default: ./calibration.json)")
        q.add_argument("--sessions", type=Path, default=None,
                       help="folder for the capture sessions (default: <out folder>/calibration-sessions)")
        q.add_argument("--yes", action="store_true",
                       help="do not wait for Enter at operator prompts (targets already in place)")
        q.add_argument("--require-predecessors", action="store_true",
                       help="refuse to run a step whose earlier steps are not in the calibration file (by default "
                            "it warns and uses their design values)")
        q.add_argument("--json", action="store_true", help="print the result as JSON")
        q.set_defaults(func=run_cli)
    return p


def _operator(args: argparse.Namespace) -> Callable[[dict[str, Any]], None] | None:
    if args.sim:
        return None        # the simulated operator (the world) places the targets

    def prompt(op: dict[str, Any]) -> None:
        print(f"operator: {op.get('say', 'prepare the next target')}", file=sys.stderr, flush=True)
        if not args.yes:
            if sys.stdin is None or not sys.stdin.isatty():
                raise SystemExit("rig calibrate: an operator action is needed and stdin is not a terminal; "
                                 "place the targets and pass --yes")
            input("press Enter when ready ")
    return prompt


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_fmt(x)}" for k, x in v.items() if k not in ("truth", "by_led")) + "}"
    return str(v)


def run_cli(args: argparse.Namespace) -> int:
    from rig.config import load_config
    from rig.files.provenance import json_default
    from rig.calibration.run import ORDER, run_step
    from rig.config.calibration_settings import load_settings

    config = load_config(args.config)
    settings = load_settings(config)
    say = getattr(args, "feedback", None) or (lambda m: print(m, file=sys.stderr, flush=True))   # stderr
    steps = ORDER if args.step == "all" else (args.step,)
    world = None
    if args.sim:
        from rig.acquire.capture import simulated
        from rig.calibration.run import make_world

        world = make_world(simulated(config), settings)
    reports = []
    for step in steps:
        rep = run_step(step, config, out=args.out, sessions_dir=args.sessions, settings=settings, simulate=args.sim,
                       world=world, operator=_operator(args), say=say,
                       require_predecessors=args.require_predecessors)
        reports.append(rep)
        if not args.json:
            print(f"{step}: revision {rep.revision} of {rep.file} ({rep.seconds:.1f} s; session {rep.session})")
            for w in rep.warnings:
                print(f"  WARNING: {w}")
            for line in rep.output.summary:
                print(f"  {line}")
            if rep.truth is not None:
                print(f"  vs simulator truth: {_fmt(rep.truth)}")
    if args.json:
        print(json.dumps({"file": str(args.out), "steps": [r.to_dict() for r in reports]}, indent=2,
                         default=json_default))
    return 0
