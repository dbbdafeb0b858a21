"""Hardware-in-the-loop tests: ``pytest hil --rig-config FILE`` runs the device tests against the devices
named in a rig config. ``--rig-config sim`` runs them against the packaged simulated rig (the simulators
start on ptys and loopback TCP), which is how CI keeps these tests honest. Without the option every test
is skipped with a message saying how to enable it.
"""
from __future__ import annotations

import pytest


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--rig-config", default=None,
                     help="rig config TOML naming real devices, or 'sim' for the simulated rig")


@pytest.fixture(scope="session")
def rig_config(pytestconfig: pytest.Config):
    from rig.config import load_config

    path = pytestconfig.getoption("--rig-config")
    if path is None:
        pytest.skip("hardware tests need --rig-config FILE (or --rig-config sim)")
    return load_config(None if path == "sim" else path), path == "sim"


@pytest.fixture(scope="session")
def rig(rig_config):
    """(config, geometry, devices) for the whole session; the sphere is darkened at the end."""
    from rig.acquire.factory import open_devices, rig_geometry, start_simulators

    cfg, simulated = rig_config
    geo = rig_geometry(cfg)
    sim = start_simulators(cfg, geo) if simulated else None
    devices = open_devices(cfg, geo, sim)
    try:
        yield cfg, geo, devices
    finally:
        try:
            devices.light.all_off()
        finally:
            devices.close()
            if sim is not None:
                sim.close()
