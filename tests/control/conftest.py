"""Fixtures of the control tests (helpers in control_scenarios.py)."""

from __future__ import annotations

import math

import pytest
from control_scenarios import l_path, vertices


@pytest.fixture
def l_vertices():
    return vertices(l_path(), None, n_landmarks=400, mount_yaw=math.pi / 2)
