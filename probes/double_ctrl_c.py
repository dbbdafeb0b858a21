"""Probe (issue 18): a second Ctrl-C within 0.3 s of the first must abort, every time.

Runs ``rig capture --sim`` on a small simulated rig N times; once the first frame is journalled it sends
SIGINT, waits a random 0..0.3 s and sends SIGINT again. Counts runs that end aborted (exit code 130 and the
journal's last ``stop`` event ``aborted`` with the sphere confirmed off)::

    python probes/double_ctrl_c.py --runs 10
"""
from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rig.config import default_config_text  # noqa: E402

SMALL = (("width_px = 112", "width_px = 24"), ("height_px = 112", "height_px = 24"), ("fx_px = 1700.0", "fx_px = 400.0"),
         ("geodesic_frequency = 6", "geodesic_frequency = 3"), ("tessellation = 4", "tessellation = 2"),
         ("key_exposure_s = 1.5", "key_exposure_s = 0.1"), ("settle_s = 0.0", "settle_s = 0.15"))


def one(work: Path, name: str, delay_s: float) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), *sys.path]))
    proc = subprocess.Popen([sys.executable, "-m", "rig.cli", "capture", "--sim", "--config", "small.toml",
                             "--sessions", "sessions", "--name", name, "--no-progress"], cwd=work, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    events = work / "sessions" / name / "events.jsonl"
    deadline = time.monotonic() + 120
    while not (events.exists() and '"type":"frame"' in events.read_text()):
        if proc.poll() is not None or time.monotonic() > deadline:
            return {"name": name, "error": "capture ended before the first frame", "stderr": proc.stderr.read()}
        time.sleep(0.005)
    proc.send_signal(signal.SIGINT)
    time.sleep(delay_s)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    stops = [json.loads(line) for line in events.read_text().splitlines() if '"type":"stop"' in line]
    last = stops[-1] if stops else {}
    aborted = proc.returncode == 128 + signal.SIGINT and last.get("status") == "aborted"
    return {"name": name, "delay_s": round(delay_s, 3), "exit": proc.returncode, "journal": last.get("status"),
            "lights_off": last.get("lights_off"), "aborted": aborted, "traceback": "Traceback" in err}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--seed", type=int, default=18)
    args = ap.parse_args()
    rng = random.Random(args.seed)
    text = default_config_text()
    for old, new in SMALL:
        text = text.replace(old, new)
    with tempfile.TemporaryDirectory(prefix="sssrig-probe-") as tmp:
        work = Path(tmp)
        (work / "small.toml").write_text(text)
        runs = [one(work, f"cc{i}", rng.uniform(0.0, 0.3)) for i in range(args.runs)]
    for r in runs:
        print(json.dumps(r), file=sys.stderr)
    n = sum(r.get("aborted", False) for r in runs)
    print(json.dumps({"runs": len(runs), "aborted": n, "lights_off": sum(bool(r.get("lights_off")) for r in runs),
                      "tracebacks": sum(bool(r.get("traceback")) for r in runs)}))
    return 0 if n == len(runs) else 1


if __name__ == "__main__":
    raise SystemExit(main())
