"""The LED layout and the patterns are what they claim (plan tables: test_plan_tables.py)."""
import numpy as np
import pytest

from rig.acquire.geometry import geodesic_directions, led_layout
from rig.acquire.patterns import pattern_rgb16, pattern_values


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
