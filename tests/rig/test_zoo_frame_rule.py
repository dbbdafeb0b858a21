"""The scene zoo's frame rule (benchmarks/zoo/frames.py): camera / zeros frames are rendered until their Monte Carlo
noise is at most 1/3 of the camera's at 95 % of the object's pixel-channels (capped by light), and a frame whose
cap binds states its whole noise in a ``[noise] stderr_path`` image. Pure numpy on synthetic arrays: < 1 s."""
from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from zoo import frames  # noqa: E402
from zoo.scenes import draw_zoo, quick_variant  # noqa: E402


@pytest.fixture(scope="module")
def specs() -> dict[str, object]:
    zoo = draw_zoo()
    return {"sky": next(s for s in zoo if s.noise == "camera" and s.light == "sky"),
            "point": next(s for s in zoo if s.noise == "zeros"),
            "mc": next(s for s in zoo if s.noise == "mc")}


def _frame(spec: object, rel_mc_over_camera: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A flat frame whose Monte Carlo stderr is ``rel_mc_over_camera`` x the camera sd at every pixel."""
    rad = np.full((8, 8, 1), 2.0)
    mask = np.ones((8, 8), bool)
    k, g, r = frames.noise_levels(spec, rad, mask)
    cam = frames.camera_sd(k * rad, g, r)
    return rad, rel_mc_over_camera * cam / k, mask


def test_spp_needed_follows_the_rule_and_its_caps(specs: dict[str, object]) -> None:
    sky = specs["sky"]
    rad, se, mask = _frame(sky, 1.0)          # ratio 1: (1 / (1/3))^2 = 9x the pilot
    np.testing.assert_allclose(frames.mc_to_camera_sd(sky, rad, se, mask), 1.0, rtol=1e-12)
    assert frames.frame_spp_needed(sky, rad, se, mask) == 9 * sky.frame_spp
    rad, se, mask = _frame(sky, 0.3)          # already within the rule: the pilot alone
    assert frames.frame_spp_needed(sky, rad, se, mask) == sky.frame_spp
    rad, se, mask = _frame(sky, 5.0)          # 225x wanted: capped at 16x under a sky
    assert frames.frame_spp_needed(sky, rad, se, mask) == frames.MAX_SPP_FACTOR["sky"] * sky.frame_spp
    pt = specs["point"]
    rad, se, mask = _frame(pt, 5.0)
    assert frames.frame_spp_needed(pt, rad, se, mask) == frames.MAX_SPP_FACTOR[pt.light] * pt.frame_spp
    # the mc class keeps its frame (heavy tails by design), and so does the CI subset (rule off)
    assert frames.frame_spp_needed(specs["mc"], rad, se, mask) == specs["mc"].frame_spp
    q = quick_variant(sky)
    assert not q.frame_rule and frames.frame_spp_needed(q, rad, se, mask) == q.frame_spp
    assert frames.frame_spp_needed(replace(sky, frame_rule=True), rad, se, mask) > sky.frame_spp


def test_stated_stderr_is_camera_plus_monte_carlo() -> None:
    values = np.array([[[0.0], [0.25]], [[-0.01], [1.0]]])
    mc = np.array([[[0.0], [0.01]], [[0.0], [0.02]]])
    se = frames.stated_stderr(values, mc, gain=100.0, read=0.005)
    want = np.sqrt(np.maximum(values, 0) / 100.0 + 0.005 ** 2 + mc ** 2)
    np.testing.assert_allclose(se, want, rtol=1e-6)
    assert se.dtype == np.float32 and se[0, 0, 0] == pytest.approx(0.005)   # a zero pixel keeps its read noise
