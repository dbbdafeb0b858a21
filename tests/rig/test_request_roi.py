"""A region not requested is not processed: gradient maps are unknown outside ``roi_px`` and the single-image
method observes only patches inside it; a region off the frame is refused before any device is touched."""
import json
import tomllib

import numpy as np
import pytest

from rig.acquire.capture import capture, simulated
from rig.cli import main
from rig.config import default_config_text, parse_config
from rig.acquire.plan import CaptureRequest, RequestError
from rig.files.session import Session

SMALL = {"sphere": {"geodesic_frequency": 3},
         "camera": {"width_px": 32, "height_px": 32, "fx_px": 500.0, "key_exposure_s": 0.3},
         "scene": {"tessellation": 2}}
ROI = (0, 0, 16, 32)     # the left half of a 32 x 32 frame


def _config():
    data = tomllib.loads(default_config_text())
    for section, fields in SMALL.items():
        data[section].update(fields)
    return simulated(parse_config(data, "small.toml"))


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    root = tmp_path_factory.mktemp("s")
    out = {}
    for name, roi in (("whole", None), ("left", ROI)):
        res = capture(_config(), CaptureRequest(("gradients", "single-image"), roi_px=roi), sessions_dir=root,
                      name=name)
        assert res.result.status == "complete"
        assert main(["estimate", "session", str(res.session.root), "--json"]) == 0
        out[name] = res.session
    return out


def _estimate(session: Session, name: str) -> dict:
    return json.loads((session.root / "estimates" / f"{name}.json").read_text())


def test_request_round_trips_through_the_manifest(sessions):
    req = CaptureRequest.from_dict(sessions["left"].manifest["request"])
    assert req.roi_px == ROI


def test_gradients_use_only_pixels_inside_the_region(sessions):
    whole, left = _estimate(sessions["whole"], "gradients"), _estimate(sessions["left"], "gradients")
    n_whole, n_left = np.array(whole["n_pixels"]), np.array(left["n_pixels"])
    assert np.all(n_left > 0) and np.all(n_left < 0.7 * n_whole)   # the sphere is centred: about half
    # the parameters are still those of the (homogeneous) object
    assert np.allclose(left["sigma_s_prime_per_mm"], whole["sigma_s_prime_per_mm"], rtol=0.1)


def test_single_image_observes_only_patches_inside_the_region(sessions):
    whole, left = _estimate(sessions["whole"], "single-image"), _estimate(sessions["left"], "single-image")
    n_whole, n_left = whole["inputs"]["observed_patches"], left["inputs"]["observed_patches"]
    assert 0 < n_left < 0.7 * n_whole


def test_bad_regions_are_refused_with_the_reason(capsys):
    with pytest.raises(RequestError, match="reaches outside the 32x32 frame"):
        CaptureRequest(roi_px=(0, 0, 40, 10)).check_frame(32, 32)
    with pytest.raises(RequestError, match="expected four integers x0 y0 x1 y1"):
        CaptureRequest(roi_px=(5, 0, 5, 10))
    assert main(["plan", "--roi", "0", "0", "200", "10"]) == 2     # the default rig's frames are 112 px wide
    assert "roi_px [0, 0, 200, 10] reaches outside the 112x112 frame" in capsys.readouterr().err
    assert main(["plan", "--roi", "5", "0", "5", "10"]) == 2
    assert "expected four integers x0 y0 x1 y1" in capsys.readouterr().err


def test_plan_says_what_the_region_leaves_out(capsys):
    assert main(["plan", "--roi", "10", "20", "60", "70"]) == 0
    assert "pixels outside the region x 10..59, y 20..69 not processed" in capsys.readouterr().out
