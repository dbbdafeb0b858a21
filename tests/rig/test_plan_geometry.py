"""Plans leave out what a request does not need; the LED layout and patterns are what they claim."""
import numpy as np
import pytest

from rig.config import load_config
from rig.geometry import geodesic_directions, led_layout
from rig.patterns import pattern_rgb16, pattern_values
from rig.plan import build_plan, summarize


@pytest.mark.parametrize("f", [1, 2, 5, 6])
def test_geodesic_counts_and_unit_length(f):
    d = geodesic_directions(f)
    assert len(d) == 10 * f * f + 2
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    # roughly uniform: the mean direction of a full geodesic sphere is the origin
    assert np.linalg.norm(d.mean(axis=0)) < 1e-9


def test_led_layout_cuts_below_min_elevation():
    pos, d = led_layout(6, 1000.0, -60.0)
    assert np.all(d[:, 2] >= np.sin(np.radians(-60)) - 1e-9)
    assert np.allclose(np.linalg.norm(pos, axis=1), 1000.0)
    assert 300 <= len(d) < 362


def test_gradient_patterns_sum_to_full_and_complements():
    _, d = led_layout(4, 1000.0)
    for axis in "xyz":
        assert np.allclose(pattern_values(axis, d) + pattern_values(axis + "_c", d), 1.0)
    q = pattern_rgb16("z", d, peak=0.8)
    assert q.dtype == np.uint16 and q.shape == (len(d), 3) and q.max() <= round(0.8 * 65535)
    with pytest.raises(ValueError, match="unknown pattern"):
        pattern_values("w", d)


def test_plan_tables():
    cfg = load_config()
    _, d = led_layout(cfg.sphere.geodesic_frequency, 1000.0, cfg.sphere.min_elevation_deg)
    both = build_plan(cfg, d)
    caps = [(s.params["pattern"], s.params["polarization"]) for s in both if s.kind == "capture"]
    assert caps == [("ambient", "cross"), ("full", "cross"), ("x", "cross"), ("y", "cross"),
                    ("z", "cross"), ("key", "cross")]
    assert [s.params["target"] for s in both if s.kind == "survey"] == ["object_top", "key_led"]
    grad_only = build_plan(cfg, d, estimate=("gradients",))
    # no survey of the key light without single-image; the object is still surveyed
    assert [s.params["target"] for s in grad_only if s.kind == "survey"] == ["object_top"]
    assert "key" not in [s.params.get("pattern") for s in grad_only]
    comp = build_plan(cfg, d, estimate=("gradients",), complements=True)
    assert [s.params["pattern"] for s in comp if s.kind == "capture"] == [
        "ambient", "x", "y", "z", "x_c", "y_c", "z_c"]
    assert all(s.reason for s in both)
    assert "6 frames" in summarize(both)
    with pytest.raises(ValueError, match="unknown estimator"):
        build_plan(cfg, d, estimate=("tarot",))
