"""The command line's feedback (issue 18): --version, -v/-vv reaching the drivers' byte traces and geocompy,
stage messages and heartbeats on stderr with stdout left to the result, errors as JSON, `rig sim --fault`
parsing."""
import io
import json
import subprocess
import sys
import time

import pytest

from drivers.errors import ConfigError
from rig import __version__
from rig.cli import main
from rig.feedback import Feedback
from rig.acquire.sim_faults import parse_faults


def _rig(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "rig.cli", *args], capture_output=True, text=True, timeout=120,
                          cwd=cwd)


def test_version(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0 and capsys.readouterr().out.strip() == f"rig (sssrig) {__version__}"


def test_vv_shows_the_drivers_byte_traces_and_geocompy_on_stderr_only(tmp_path):
    res = _rig("-vv", "devices", "--sim", "--json", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["ok"]                       # stdout: the result alone
    assert "drivers.led_sphere.driver DEBUG: LED sphere >> IDENTIFY" in res.stderr
    assert "geocompy DEBUG: GeoComResponse(COM_NullProc)" in res.stderr
    quiet = _rig("devices", "--sim", cwd=tmp_path)
    assert "DEBUG" not in quiet.stderr and "Traceback" not in quiet.stderr


def test_feedback_stages_and_heartbeat_go_to_the_stream_not_stdout(capsys):
    stream = io.StringIO()
    fb = Feedback("rig test", stream, tty=False, heartbeat_s=0.3)
    fb.stage("first stage")
    time.sleep(1.2)
    fb.close()
    lines = stream.getvalue().splitlines()
    assert lines[0].endswith("] first stage") and any("still: first stage" in line for line in lines[1:])
    assert capsys.readouterr().out == ""
    off = io.StringIO()
    silent = Feedback("rig test", off, enabled=False)
    silent.stage("nothing")
    silent.close()
    assert off.getvalue() == ""


def test_usage_and_input_errors_are_json_with_json(capsys):
    assert main(["plan", "--channels", "XY", "--json"]) == 2
    out = json.loads(capsys.readouterr().out)
    assert out["ok"] is False and "channels" in out["error"]["message"]
    assert main(["config", "--check", "nope.toml", "--json", "--bogus"]) == 2
    assert json.loads(capsys.readouterr().out)["error"]["type"] == "usage"


def test_sim_fault_specs():
    specs = parse_faults(["sphere:led_fault", "trigger:busy=2", "any:latency=0.1"])
    assert [str(s) for s in specs] == ["sphere:led_fault", "trigger:busy=2", "sphere:latency=0.1",
                                       "trigger:latency=0.1", "total_station:latency=0.1"]
    for bad, field in (("sphere:ledfault", "fault"), ("lamp:mute", "device"), ("trigger:led_fault", "led_fault"),
                       ("sphere:corrupt=2", "corrupt")):
        with pytest.raises(ConfigError) as err:
            parse_faults([bad])
        assert err.value.field == field
    with pytest.raises(ConfigError, match="did you mean 'led_fault'"):
        parse_faults(["sphere:led_falt"])


def test_simulators_remove_their_own_temporary_folder():
    """start_simulators without a work folder makes its own and removes it on close (issue 18: `rig sim` left a
    /tmp/sssrig-simcam-* folder per run)."""
    from rig.config import load_config
    from rig.acquire.factory import start_simulators
    from rig.acquire.geometry import rig_geometry

    cfg = load_config()
    sim = start_simulators(cfg, rig_geometry(cfg))
    own = sim.drop_folder.parent
    assert own.name.startswith("sssrig-simcam-") and own.is_dir()
    sim.close()
    assert not own.exists()
