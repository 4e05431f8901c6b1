"""Shared fixtures: paths of the shipped sample data."""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest

DATASETS = Path(__file__).resolve().parents[1] / "datasets"


@pytest.fixture(scope="session")
def kitti_clip() -> Path:
    return DATASETS / "kitti06_clip"


@pytest.fixture(scope="session")
def kitti_ramp_clip() -> Path:
    """Open ramp, most of the scene far away (the hard case for scale)."""
    return DATASETS / "kitti00_ramp_clip"


@pytest.fixture(scope="session")
def euroc_micro() -> Path:
    return DATASETS / "euroc_v101_micro"


@pytest.fixture(scope="session")
def euroc_pairs() -> Path:
    return DATASETS / "euroc_revisit_pairs"


@pytest.fixture
def permissions_bind() -> Callable[[list[str]], list[str]]:
    """A command line that runs ``args`` so that file permissions bind: as is for a normal user; for root, through
    ``setpriv`` with the capabilities that override permissions dropped (root keeps its uid). Skips when root has no
    ``setpriv``."""
    if os.geteuid() != 0:
        return lambda args: args
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        pytest.skip("running as root without setpriv: permissions do not bind")
    caps = "-dac_override,-dac_read_search"
    return lambda args: [setpriv, f"--bounding-set={caps}", f"--inh-caps={caps}", *args]


#: The long end-to-end modules (runs on imagery, Dask clusters, subprocess commands): marked ``slow`` and left out
#: of the default ``python3 -m pytest -q`` (``-m "not slow"`` in pyproject.toml's addopts; the README gives both
#: times). ``python3 -m pytest -q -m "slow or not slow"`` runs everything, as CI does (.ci/run).
SLOW_MODULES = frozenset(
    {
        "tests/app/test_batch.py",
        "tests/app/test_output_safety.py",
        "tests/app/test_mission.py",
        "tests/cli/test_batch_cli.py",
        "tests/cli/test_run_lifecycle.py",
        "tests/cli/test_vtr_cli.py",
        "tests/control/test_return_flight.py",
        "tests/navigation/test_experiences.py",
        "tests/navigation/test_teach_repeat.py",
        "tests/navigation/test_repeat_pipeline.py",
        "tests/navigation/test_return_flight_state.py",
        "tests/navigation/test_synthetic_repeat.py",
        "tests/perception_model/test_end_to_end.py",
        "tests/vo/test_far_structure.py",
        "tests/vo/test_odometry_kitti.py",
        "tests/test_readme.py",
    }
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    root = Path(__file__).resolve().parents[1]
    for item in items:
        if item.path.resolve().relative_to(root).as_posix() in SLOW_MODULES:
            item.add_marker(pytest.mark.slow)
