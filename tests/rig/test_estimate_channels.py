"""A channel the user did not request is not captured (dark in every pattern) and not processed: its
parameters are None ("not requested") in the estimates, never a number fitted to darkness."""
import json
import tomllib

import numpy as np
import pytest

from rig.acquire.capture import capture, simulated
from rig.cli import main
from rig.config import default_config_text, parse_config
from rig.acquire.plan import CaptureRequest

SMALL = {"sphere": {"geodesic_frequency": 3},
         "camera": {"width_px": 32, "height_px": 32, "fx_px": 500.0, "key_exposure_s": 0.3},
         "scene": {"tessellation": 2}}


@pytest.fixture(scope="module")
def green_session(tmp_path_factory):
    data = tomllib.loads(default_config_text())
    for section, fields in SMALL.items():
        data[section].update(fields)
    cfg = simulated(parse_config(data, "small.toml"))
    out = capture(cfg, CaptureRequest(("gradients", "single-image"), channels=("G",)),
                  sessions_dir=tmp_path_factory.mktemp("s"), name="green")
    assert out.result.status == "complete"
    return out.session


def test_unrequested_channels_are_none_and_left_out_of_the_table(green_session, capsys):
    assert main(["estimate", "session", str(green_session.root), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    rows = out["rows"]
    assert rows and all(r["quantity"].endswith(" G") for r in rows)
    for name in ("gradients", "single-image"):
        est = json.loads((green_session.root / "estimates" / f"{name}.json").read_text())
        assert est["channels"] == ["G"]
        for key in ("R_d", "sigma_s_prime_per_mm", "sigma_a_per_mm"):
            assert est[key][0] is None and est[key][2] is None, (name, key)
            assert np.isfinite(est[key][1]) and est[key][1] > 0, (name, key)
    # the green channel is still recovered by the gradient method (simulator truth: marble, sigma_s' G =
    # 2.62 /mm; 5 %: a 32 px image has ~500 object pixels, the full-size demo gets 0.8 %)
    gr = json.loads((green_session.root / "estimates" / "gradients.json").read_text())
    assert abs(gr["sigma_s_prime_per_mm"][1] / 2.62 - 1) < 0.05
    # the session path widens the sphere intervals by the dipole's measured shortening bias, as the capture
    # folder does (estimation.sphere_bias): the record says so and the widened interval holds the truth
    bias = gr["model_shortening_bias"]
    assert bias is not None and bias["K"][1] > 1.0 and bias["K"][0] is None
    lo, hi = gr["sigma_s_prime_per_mm_interval"][1]
    plain_lo, plain_hi = bias["plain_intervals"]["sigma_s_prime_per_mm"][1]
    assert lo <= plain_lo and hi >= plain_hi and (hi - lo) > (plain_hi - plain_lo)
    assert lo <= 2.62 <= hi
    assert gr["notes"] == []          # the green channel is lit: no channel is dark


def test_report_lists_only_requested_channels(green_session, capsys):
    assert main(["report", str(green_session.root), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert {p["channel"] for p in summary["parameters"] if p["channel"]} == {"G"}
