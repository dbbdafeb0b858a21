"""The hardware-in-the-loop device tests run against the simulated rig, and skip cleanly without a config.

(hil/test_trigger_uhid.py needs Linux /dev/uhid and skips without it; it is not part of this check.)
"""
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _pytest(*args):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "hil/test_devices_hil.py", *args],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)


def test_hil_suite_passes_on_the_simulated_rig():
    proc = _pytest("--rig-config", "sim")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "6 passed" in proc.stdout


def test_hil_suite_skips_without_a_rig_config():
    proc = _pytest()
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "6 skipped" in proc.stdout and "passed" not in proc.stdout
