"""Suite-wide ordering for the two-worker CI run (README test line: ``pytest -n 2 --dist loadfile``).

pytest-xdist hands whole files to the workers in collection order; the Monte Carlo files below take minutes each
and, collected last (tests/simulators, tests/rig), left one worker running alone for the final ~3 minutes of a
20-minute run. They go first; the order inside each file is unchanged (a stable sort).
"""
from __future__ import annotations

import os

import pytest

if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) > 1:
    # two workers on two cores: one OpenBLAS thread each (a second thread per worker spins against the other
    # worker: QR solves measured 6x slower on the loaded 2-core machine, docs/visibility.md); set before numpy loads
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

HEAVY_FILES: tuple[str, ...] = (
    "tests/simulators/test_mc_frames_single_image.py",
    "tests/rig/test_scene_zoo.py",
    "tests/rig/test_scene_file_mc_reference.py",
    "tests/rig/test_scene_file.py",
    "tests/estimation/test_model_correction.py",
    "tests/simulators/test_mc_frames_gradients.py",
    "tests/simulators/test_mc_acceptance.py",
)


def pytest_collection_modifyitems(session: pytest.Session, config: pytest.Config, items: list[pytest.Item]) -> None:
    rank = {f: i for i, f in enumerate(HEAVY_FILES)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::")[0], len(rank)))
