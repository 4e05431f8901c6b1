"""The MPC keeps its constraints on a short scenario (synthetic landmark field, thesis model)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from control_scenarios import PITCH_DOWN_RAD, l_path, vertices

from perception_model import frames
from perception_model.model import PerceptionModel
from vtr.config import ControlConfig
from vtr.control.closed_loop import initial_state, simulate
from vtr.control.field import TaughtPathField
from vtr.control.flat_model import discrete_model, step
from vtr.control.mpc import PerceptionAwareMPC, TaughtPathReference


def test_flat_model_is_the_exact_triple_integrator():
    A, B = discrete_model(0.1)
    z = np.r_[1.0, 2.0, 3.0, 0.5, -1.0, 0.0, 0.2, 0.0, -0.3, 0.4]
    w = np.array([1.0, -2.0, 0.5, 0.3])
    # ten small steps of the held input equal one big step
    zz = z
    for _ in range(10):
        zz = step(zz, w, 0.01)
    assert np.allclose(zz, A @ z + B @ w, atol=1e-12)


@pytest.fixture(scope="module")
def scenario():
    heading = math.pi / 2  # gimbal: camera looks north
    verts = vertices(l_path(), heading, n_landmarks=260, seed=4)
    field = TaughtPathField(PerceptionModel.thesis(), verts, T_g_map=np.eye(4))
    return field, frames.optical_axis(heading, PITCH_DOWN_RAD)


def _fly(field, axis, mode, bound=0.0, cfg=None):
    cfg = cfg or ControlConfig()
    ref = TaughtPathReference(field.vehicle_position_g)
    mpc = PerceptionAwareMPC(ref, cfg, mode=mode, fixed_bound_m=bound, field=field, camera=axis)
    return simulate(field, mpc, initial_state(field))


#: The sharp (90 degree, no radius) corner of this scenario and the thesis model's steep field (mu - 3 sigma
#: falls ~20 inliers a metre off the path) need a larger margin than the thesis experiment's 1.5 (its default).
SHARP_CORNER = ControlConfig(perception_margin=6.0)


def test_mpc_keeps_its_constraints(scenario):
    field, axis = scenario
    free = _fly(field, axis, "none")
    fixed = _fly(field, axis, "fixed", 0.5)
    pa = _fly(field, axis, "perception", cfg=SHARP_CORNER)
    for r in (free, fixed, pa):
        assert r.completed and np.all(np.isfinite(r.z))
        assert np.abs(r.z[:, 6:9]).max() <= ControlConfig().accel_max_mps2 + 1e-2  # box constraints
    print(
        {
            n: (round(r.avg_speed_mps, 2), round(r.min_bound, 1), round(float(np.abs(r.lateral_m).max()), 2))
            for n, r in (("none", free), ("fixed", fixed), ("pa", pa))
        }
    )
    # the scenario is one where flying unconstrained loses the guarantee at the corner
    assert free.min_bound < 30.0
    assert np.abs(fixed.lateral_m).max() <= 0.5 + 0.05
    assert pa.min_bound >= 30.0
    assert fixed.avg_speed_mps < free.avg_speed_mps
    assert np.all(fixed.max_slack_inliers == 0.0) and np.all(pa.max_slack_m == 0.0)  # slacks in their units


@pytest.mark.xfail(
    strict=True,
    reason="measured: with the library's defaults (margin 1.5, governor 0.8) P-A "
    "reaches min mu - 3 sigma 29.3 at 10 m/s (29.1 at 8, 30.3 at 6) at this sharp corner",
)
def test_the_defaults_keep_the_guarantee_at_a_sharp_corner(scenario):
    field, axis = scenario
    assert _fly(field, axis, "perception").min_bound >= 30.0
