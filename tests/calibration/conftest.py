"""Shared fixtures: the simulated calibration rig (``calibration_rig.toml``) and one full calibration chain.

The chain runs every step once, in ``rig.calibration.run.ORDER``, through the real plans, runner, drivers and
simulators (about 35 s); the per-step tests then check its results against the simulator's truth.
"""
from __future__ import annotations

from pathlib import Path

import pytest

from rig.calibration.run import ORDER, make_world, run_all
from rig.config.calibration_settings import load_settings
from rig.acquire.capture import simulated
from rig.config import load_config

RIG_TOML = Path(__file__).with_name("calibration_rig.toml")


@pytest.fixture(scope="session")
def cal_config():
    return load_config(RIG_TOML)


@pytest.fixture(scope="session")
def cal_settings(cal_config):
    return load_settings(cal_config)


@pytest.fixture(scope="session")
def chain(cal_config, cal_settings, tmp_path_factory):
    """{step: StepReport} of one simulated ``calibrate all``, plus the world and the calibration file."""
    out = tmp_path_factory.mktemp("calibration") / "calibration.json"
    world = make_world(simulated(cal_config), cal_settings)
    reports = run_all(cal_config, out=out, simulate=True, world=world, settings=cal_settings)
    assert [r.step for r in reports] == list(ORDER)
    return {"reports": {r.step: r for r in reports}, "world": world, "out": out}
