"""Shared fixtures: paths of the shipped sample data."""

from __future__ import annotations

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
