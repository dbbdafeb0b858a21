"""Smoke runs of the benchmarks (--quick): they run to completion and print their figures.
The figures themselves are read by people, never asserted as timings."""
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(script, *args):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path), MPLBACKEND="Agg")
    return subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), "--quick", *args], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=600)


def test_devices_benchmark_quick_prints_every_transport():
    proc = _run("devices.py", "--json")
    assert proc.returncode == 0, proc.stderr
    data = json.loads(proc.stdout)
    text = json.dumps(data)
    for transport in ("serial/pty", "serial/TCP", "Modbus TCP"):
        assert transport in text


def test_single_image_benchmark_quick_prints_tables():
    proc = _run("single_image.py")
    assert proc.returncode == 0, proc.stderr
    assert "| direct |" in proc.stdout and "| pinv |" in proc.stdout
