"""Probe (issue 18): every command that can take longer than 2 s says something on stderr within 2 s, also with
``--json`` (whose stdout must stay one JSON document).

Runs each command with stderr and stdout piped (not a terminal, as in a script), records when the first stderr
line arrives, the longest silence on stderr, the run time, and whether stdout parses as JSON::

    python probes/progress_latency.py
"""
from __future__ import annotations

import json
import os
import selectors
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def watch(args: list[str], cwd: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), *sys.path]))
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "rig.cli", *args], cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    sel = selectors.DefaultSelector()
    sel.register(proc.stderr, selectors.EVENT_READ, "err")
    sel.register(proc.stdout, selectors.EVENT_READ, "out")
    first = None
    last = t0
    gap = 0.0
    out = b""
    open_streams = 2
    while open_streams:
        for key, _ in sel.select(timeout=0.1):
            data = os.read(key.fileobj.fileno(), 65536)
            now = time.monotonic()
            if not data:
                sel.unregister(key.fileobj)
                open_streams -= 1
                continue
            if key.data == "out":
                out += data
            else:
                first = first if first is not None else now - t0
                gap = max(gap, now - last)
                last = now
    proc.wait()
    total = time.monotonic() - t0
    gap = max(gap, total - (last - t0)) if first is not None else total
    try:
        json.loads(out)
        stdout_json = True
    except ValueError:
        stdout_json = False
    return {"command": "rig " + " ".join(args), "exit": proc.returncode, "seconds": round(total, 1),
            "first_stderr_s": None if first is None else round(first, 2), "longest_silence_s": round(gap, 1),
            "stdout_is_json": stdout_json}


def main() -> int:
    with tempfile.TemporaryDirectory(prefix="sssrig-probe-") as tmp:
        work = Path(tmp)
        cmds = [["demo", "--json", "--sessions", "s", "--name", "d"],
                ["capture", "--sim", "--json", "--sessions", "s", "--name", "c"],
                ["estimate", "session", "s/c", "--json"],
                ["report", "s/c", "--json"],
                ["resume", "s/c", "--json"],
                ["devices", "--sim", "--json"],
                ["calibrate", "intrinsics", "--sim", "--json", "--out", "cal.json"]]
        rows = [watch(c, work) for c in cmds]
    for r in rows:
        print(json.dumps(r))
    late = [r for r in rows if r["seconds"] > 2 and (r["first_stderr_s"] is None or r["first_stderr_s"] > 2)]
    print(json.dumps({"commands": len(rows), "longer_than_2_s": sum(r["seconds"] > 2 for r in rows),
                      "silent_first_2_s": len(late), "stdout_json": sum(r["stdout_is_json"] for r in rows)}))
    return 0 if not late else 1


if __name__ == "__main__":
    raise SystemExit(main())
