"""The controller API refuses what it cannot answer: an infeasible tick raises (no garbage command), inputs are
checked where they enter, ControlConfig owns l_min / c_bar, negative bounds are refused everywhere."""

from __future__ import annotations

import math

import numpy as np
import pytest
from control_scenarios import l_path, vertices

from perception_model.constraint import PerceptionConstraint
from perception_model.errors import GeometryError, PerceptionModelError
from perception_model.horizon import HorizonEvaluator
from perception_model.model import PerceptionModel
from vtr.config import ControlConfig
from vtr.control.closed_loop import initial_state
from vtr.control.field import TaughtPathField
from vtr.control.mpc import MpcInfeasible, PerceptionAwareMPC, TaughtPathReference
from vtr.errors import ConfigError, EstimationError

MODEL = PerceptionModel.thesis()


@pytest.fixture(scope="module")
def field():
    return TaughtPathField(MODEL, vertices(l_path(), None, n_landmarks=200, mount_yaw=math.pi / 2), T_g_map=np.eye(4))


def mpc_of(field, mode="perception", **cfg):
    return PerceptionAwareMPC(
        TaughtPathReference(field.vehicle_position_g), ControlConfig(**cfg), mode=mode, fixed_bound_m=1.0, field=field
    )


@pytest.mark.parametrize("mode", ["none", "fixed", "perception"])
@pytest.mark.parametrize("speed", [15.0, 40.0])
def test_an_infeasible_start_raises_instead_of_returning_garbage(field, mode, speed):
    z = initial_state(field)
    z[3] = speed  # above speed_max_mps (12): no plan meets the bounds
    with pytest.raises(MpcInfeasible, match="infeasible.*speed_max_mps") as err:
        mpc_of(field, mode).solve(z)
    assert isinstance(err.value, EstimationError)


def test_a_feasible_tick_still_solves_and_after_an_infeasible_one(field):
    mpc = mpc_of(field, "fixed")
    bad = initial_state(field)
    bad[4] = 20.0
    with pytest.raises(MpcInfeasible):
        mpc.solve(bad)
    sol = mpc.solve(initial_state(field))
    assert sol.status == "solved" and np.all(np.isfinite(sol.w))
    assert np.abs(sol.w[:3]).max() <= ControlConfig().jerk_max_mps3 + 1e-3


@pytest.mark.parametrize(
    "z, msg",
    [
        (np.full(10, np.nan), "not finite"),
        (np.zeros(9), r"shape \(10,\)"),
        (np.zeros((2, 10)), r"shape \(10,\)"),
        ("hover", "expected"),
    ],
)
def test_bad_states_are_package_errors(field, z, msg):
    with pytest.raises(EstimationError, match=msg):
        mpc_of(field).solve(z)


@pytest.mark.parametrize("trunk", [999, -1, 2.5, True])
def test_bad_trunks_are_package_errors(field, trunk):
    with pytest.raises(EstimationError, match="trunk"):
        mpc_of(field).solve(initial_state(field), trunk)


def test_control_config_owns_l_min_and_c_bar(field):
    strict = mpc_of(field, l_min=80.0, c_bar=1.0)
    assert (strict.field.l_min, strict.field.c_bar) == (80.0, 1.0)
    assert (field.l_min, field.c_bar) == (30.0, 3.0)  # the caller's field is not changed
    z = initial_state(field)
    p, psi = np.tile(z[:3], (3, 1)), np.full(3, z[9])
    a, b = field.evaluate(p, psi, previous=0), strict.field.evaluate(p, psi, previous=0)
    assert np.allclose(b.g, b.mu - 1.0 * b.sigma - 80.0) and np.allclose(a.g, a.mu - 3.0 * a.sigma - 30.0)


def test_field_inputs_are_checked(field):
    z = initial_state(field)
    for args, kw, msg in [
        ((np.zeros((0, 3)), np.zeros(0)), {}, "N >= 1"),
        ((np.zeros((2, 3)), np.zeros(3)), {}, "yaw"),
        ((np.full((2, 3), np.nan), np.zeros(2)), {}, "finite"),
        ((np.tile(z[:3], (2, 1)), np.zeros(2)), {"previous": 10_000}, "previous trunk"),
        ((np.tile(z[:3], (2, 1)), np.zeros(2)), {"trunk": np.array([0, 10_000])}, "trunk"),
        ((np.tile(z[:3], (2, 1)), np.zeros(2)), {"axes": np.zeros((2, 3))}, "axes"),
    ]:
        with pytest.raises(EstimationError, match=msg):
            field.evaluate(*args, **kw)


def test_negative_bounds_are_refused_everywhere(field):
    pts = np.array([[1.0, 0.0, 10.0], [0.0, 1.0, 12.0]])
    for kw in ({"l_min": -1.0}, {"c_bar": -3.0}, {"l_min": math.inf}):
        with pytest.raises(PerceptionModelError, match="l_min|c_bar"):
            PerceptionConstraint(MODEL, pts, **kw)
        with pytest.raises(PerceptionModelError, match="l_min|c_bar"):
            HorizonEvaluator(MODEL, field.evaluator.trunks, **kw)
        with pytest.raises(EstimationError, match="l_min|c_bar"):
            field.with_bounds(kw.get("l_min", 30.0), kw.get("c_bar", 3.0))
    with pytest.raises(ConfigError, match="l_min"):
        mpc_of(field, l_min=-1.0)  # the config's own domain


def test_zero_positions_are_a_clear_error():
    c = PerceptionConstraint(MODEL, np.array([[1.0, 0.0, 10.0]]))
    with pytest.raises(GeometryError, match="none given"):
        c.evaluate(np.zeros((0, 3)), np.zeros(0))
