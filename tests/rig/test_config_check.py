"""`rig config --check` (issue 18): the broken configs of probes/broken_inputs.py are each refused with one line
naming the file and the field (typos with a did-you-mean, enumerations, degenerate poses, exposures against the
trigger's range, [calibration], the plan's energy and thermal budgets); the JSON Schema file is current."""
import importlib.util
import json
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from drivers.errors import ConfigError
from rig.config import default_config_text
from rig.acquire.config_check import check_config, json_schema, packaged_schema_text

ROOT = Path(__file__).resolve().parents[2]


def _probe():
    spec = importlib.util.spec_from_file_location("broken_inputs", ROOT / "probes" / "broken_inputs.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


PROBE = _probe()


@pytest.mark.parametrize("what, mutate, field", PROBE.BROKEN, ids=[b[0] for b in PROBE.BROKEN])
def test_broken_config_is_refused_naming_file_and_field(tmp_path, what, mutate, field):
    data = tomllib.loads(default_config_text())
    mutate(data)
    path = tmp_path / "rig.toml"
    path.write_text(PROBE._toml(data))
    with pytest.raises(ConfigError) as err:
        check_config(path)
    msg = str(err.value)
    assert err.value.field == field and msg.startswith(f"{path}: field '{field}': expected "), msg
    assert "\n" not in msg


def test_the_default_config_passes_and_resolves_every_default(tmp_path):
    path = tmp_path / "rig.toml"
    path.write_text(PROBE._toml(tomllib.loads(default_config_text())))
    out = check_config(path)
    assert out["ok"] and out["config"]["runner"]["on_led_fault"] == "pause"
    assert out["config"]["total_station"]["crc"] is True
    assert out["calibration"]["board"]["square_mm"] > 0          # "0 = auto" sizes resolved
    assert out["budget"]["problems"] == []


def test_typos_get_a_did_you_mean(tmp_path):
    data = tomllib.loads(default_config_text())
    data["sphere"]["watchdg_s"] = 0.5
    path = tmp_path / "rig.toml"
    path.write_text(PROBE._toml(data))
    with pytest.raises(ConfigError, match=r"did you mean 'watchdog_s'\?.*got 0.5"):
        check_config(path)


def test_check_prints_the_resolved_config_or_the_error_as_json(tmp_path):
    good, bad = tmp_path / "good.toml", tmp_path / "bad.toml"
    good.write_text(default_config_text())
    data = tomllib.loads(default_config_text())
    data["estimation"]["single_image_method"] = "bogus"
    bad.write_text(PROBE._toml(data))
    run = [sys.executable, "-m", "rig.cli", "config", "--json", "--check"]
    res = subprocess.run(run + [str(good)], capture_output=True, text=True, timeout=120)
    out = json.loads(res.stdout)
    assert res.returncode == 0 and out["ok"] and out["config"]["camera"]["key_exposure_s"] == 1.5
    res = subprocess.run(run + [str(bad)], capture_output=True, text=True, timeout=120)
    err = json.loads(res.stdout)["error"]
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert err["file"] == str(bad) and err["field"] == "estimation.single_image_method"
    assert "one of direct, tikhonov, pinv" in err["expected"]


def test_packaged_json_schema_is_current():
    """rig/data/rig-config.schema.json is what `rig config --schema` prints (regenerate it after a schema
    change: rig config --schema > rig/data/rig-config.schema.json)."""
    assert json.loads(packaged_schema_text()) == json_schema()
    schema = json_schema()
    assert schema["additionalProperties"] is False and "calibration" in schema["properties"]
