"""The return flight on the controller side: direction through the field, the reference, the MPC and the
closed loop; validity in the field (distances, OFF_ROUTE, the gradient guard); errors through VtrError;
slacks per unit; the constraint's two forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
from control_scenarios import l_path, vertices
from hypothesis import given, settings
from hypothesis import strategies as st

from perception_model import frames
from perception_model.errors import GeometryError, PerceptionModelError
from perception_model.horizon import OFF_ROUTE, OK
from perception_model.model import PerceptionModel
from vtr.config import ControlConfig
from vtr.control.closed_loop import initial_state, simulate
from vtr.control.field import CameraMount, PerceptionFieldError, TaughtPathField, TaughtVertex
from vtr.control.mpc import PerceptionAwareMPC, TaughtPathReference
from vtr.errors import EstimationError, VtrError
from vtr.navigation.trunk import BACKWARD, FORWARD

MODEL = PerceptionModel.thesis()
LEVER = np.array([0.1, 0.0, -0.05])


@pytest.fixture(scope="module")
def field():
    """The L path with the camera on its mount looking along the taught travel (50 deg down)."""
    return TaughtPathField(
        MODEL, vertices(l_path(), None, n_landmarks=400), T_g_map=np.eye(4), mount=CameraMount(0.0, LEVER)
    )


# ----------------------------------------------------------------------------- field: direction
def test_the_trunk_window_mirrors_with_the_direction(field):
    # a pose at taught vertex 2 while the previous trunk is 17: 15 vertices behind in taught order.
    # forward the window reaches 10 back (it stops at 7); flown backward it reaches 20 ahead of travel
    p, yaw = field.vehicle_position_g[2][None], field.vehicle_yaw_g[2:3]
    assert field.select_trunks(p, yaw, 17, direction=FORWARD)[0] == 7
    assert field.select_trunks(p, yaw, 17, direction=BACKWARD)[0] == 2
    assert field.evaluate(p, yaw, previous=17, direction=BACKWARD).trunk[0] == 2
    assert field.evaluate(p, yaw, previous=17).trunk[0] == 7  # default: taught order
    # and the other way round: 15 ahead in taught order is in reach forward only
    p, yaw = field.vehicle_position_g[20][None], field.vehicle_yaw_g[20:21]
    assert field.select_trunks(p, yaw, 5, direction=FORWARD)[0] == 20
    assert field.select_trunks(p, yaw, 5, direction=BACKWARD)[0] == 15


@pytest.mark.parametrize("direction", [0, 2, True, "backward", 1.0 + 1e-9])
def test_a_direction_is_plus_or_minus_one(field, direction):
    p, yaw = field.vehicle_position_g[:1], field.vehicle_yaw_g[:1]
    with pytest.raises(EstimationError, match="direction"):
        field.evaluate(p, yaw, direction=direction)


# ----------------------------------------------------------------------------- field: validity
@pytest.mark.parametrize("past_m", [6.0, 12.0])
def test_past_either_end_is_off_route(field, past_m):
    pts = field.vehicle_position_g
    end_dir = (pts[-1] - pts[-2]) / np.linalg.norm(pts[-1] - pts[-2])
    start_dir = (pts[1] - pts[0]) / np.linalg.norm(pts[1] - pts[0])
    p = np.array([pts[-1] + past_m * end_dir, pts[0] - past_m * start_dir])
    for k, previous in ((0, len(field) - 1), (1, 0)):
        ev = field.evaluate(p[k : k + 1], field.vehicle_yaw_g[[-1, 0][k] :][:1], previous=previous)
        assert ev.flag[0] == OFF_ROUTE and ev.off_route[0]
        assert ev.past_end_m[0] == pytest.approx(past_m, abs=1e-9)
        assert ev.path_distance_m[0] == pytest.approx(past_m, abs=1e-9)
        assert ev.trunk_distance_m[0] == pytest.approx(past_m, abs=1e-9)


def test_on_the_route_and_a_little_off_it_is_not_off_route(field):
    pts, yaw = field.vehicle_position_g, field.vehicle_yaw_g
    left = np.array([0.0, 1.0, 0.0])
    # on the path, 2 m to its left, 2 m past its end (within off_route_past_end_m, 3 m), 11 m to its right
    p = np.array([pts[5], pts[5] + 2.0 * left, pts[-1] + np.array([0.0, 2.0, 0.0]), pts[5] - 11.0 * left])
    ev = field.evaluate(p, yaw[[5, 5, -1, 5]], trunk=np.array([5, 5, len(field) - 1, 5]), gradient=False)
    assert ev.flag[:3].tolist() == [OK, OK, OK]
    assert np.allclose(ev.path_distance_m, [0.0, 2.0, 2.0, 11.0]) and np.allclose(ev.past_end_m, [0, 0, 2, 0])
    assert ev.flag[3] == OFF_ROUTE  # beyond off_route_distance_m (10 m by default)
    wider = field.with_bounds(30.0, 3.0, control=ControlConfig(off_route_distance_m=12.0))
    assert wider.evaluate(p[3:], yaw[5:6], trunk=np.array([5]), gradient=False).flag[0] != OFF_ROUTE


@settings(max_examples=60, deadline=None)
@given(
    index=st.integers(0, 24), angle=st.floats(0.0, 2 * math.pi), distance=st.floats(0.0, 40.0), dz=st.floats(-3.0, 3.0)
)
def test_the_row_gradient_never_points_away_from_the_trunk_where_mu_is_small(field, index, angle, distance, dz):
    p = field.vehicle_position_g[index] + np.array([distance * math.cos(angle), distance * math.sin(angle), dz])
    ev = field.evaluate(p[None], field.vehicle_yaw_g[index : index + 1], trunk=np.array([index]))
    toward = field.vehicle_position_g[index] - p
    assert ev.guarded[0] == (ev.mu[0] < 0.25 * field.c_bar**2)
    if ev.guarded[0]:
        # the guarded row's gradient is grad mu: it never asks the vehicle to fly further away
        assert ev.dg_dpos[0] @ toward >= -1e-9 * max(1.0, np.linalg.norm(ev.dg_dpos[0]))
        assert np.allclose(ev.dg_dpos[0], ev.raw.dmu_dpos[0])
    else:
        assert np.allclose(ev.dg_dpos[0], ev.raw.dg_dpos[0])


def test_without_the_guard_the_gradient_points_away_far_from_the_path(field):
    # 20 m to the left of vertex 5, level: mu is small and d(mu - 3 sigma) points away from the path
    p = field.vehicle_position_g[5] + np.array([0.0, 20.0, 0.0])
    ev = field.evaluate(p[None], field.vehicle_yaw_g[5:6], trunk=np.array([5]))
    toward = field.vehicle_position_g[5] - p
    assert 0.0 < ev.mu[0] < 0.25 * field.c_bar**2 and ev.guarded[0]
    assert ev.raw.dg_dpos[0] @ toward < 0.0 and ev.raw.dgc_dpos[0] @ toward < 0.0
    assert ev.dg_dpos[0] @ toward > 0.0


def test_constraint_forms(field):
    p, yaw = field.vehicle_position_g[3:8] + np.array([0.0, 1.0, 0.5]), field.vehicle_yaw_g[3:8]
    normal = field.evaluate(p, yaw, previous=3)
    cons = field.with_bounds(30.0, 3.0, form="conservative").evaluate(p, yaw, previous=3)
    assert np.allclose(normal.g, normal.mu - 3.0 * normal.sigma - 30.0)
    assert np.allclose(cons.g, cons.mu - 3.0 * np.sqrt(cons.mu) - 30.0) and cons.form == "conservative"
    assert np.all(cons.g <= normal.g + 1e-9)  # sigma^2 <= mu: eq. 7.8 is the conservative one
    with pytest.raises(EstimationError, match="constraint form"):
        field.with_bounds(30.0, 3.0, form="loose")


# ----------------------------------------------------------------------------- errors through VtrError
def test_perception_model_errors_are_vtr_errors_at_the_control_boundary():
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, 12.0]
    with pytest.raises(VtrError, match="vertical optical axis"):  # the camera looking straight down
        TaughtPathField(MODEL, [TaughtVertex(0, T, np.zeros((0, 3)))], T_g_map=np.eye(4))
    T[:3, :3] = frames.camera_rotation(0.0, 0.8)
    bad = [TaughtVertex(0, T, np.array([[0.0, 0.0, 12.0]]))]  # a landmark at the taught camera
    try:
        TaughtPathField(MODEL, bad, T_g_map=np.eye(4))
    except VtrError as err:
        assert isinstance(err, PerceptionFieldError) and isinstance(err, PerceptionModelError)
        assert isinstance(err.__cause__, GeometryError) and "taught camera" in str(err)
    else:
        pytest.fail("no error")
    with pytest.raises(VtrError, match="up"):
        TaughtPathField.from_map(None, MODEL, up_map=(0.0, 0.0, 0.0))  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- reference and MPC
def test_a_reversed_reference_runs_from_the_taught_end(field):
    fwd, back = TaughtPathReference.from_field(field), TaughtPathReference.from_field(field, BACKWARD)
    assert back.length == pytest.approx(fwd.length)
    p, yaw = back.at(np.array([0.0, back.length]), "along_travel")
    assert np.allclose(p, field.vehicle_position_g[[-1, 0]])
    # travelling the last (north) leg backward heads south; as taught, the vehicle keeps its taught yaw
    assert yaw[0] == pytest.approx(-math.pi / 2)
    _, taught = back.at(np.array([0.0, back.length]), "as_taught")
    assert np.allclose(taught, field.vehicle_yaw_g[[-1, 0]])
    # lateral is left of travel: a point east of the north leg is left of travel flown back (south)
    east = field.vehicle_position_g[-4] + np.array([1.5, 0.0, 0.0])
    assert back.path.error(east).lateral == pytest.approx(1.5) and fwd.path.error(east).lateral == pytest.approx(-1.5)
    with pytest.raises(EstimationError, match="taught yaw"):
        TaughtPathReference(field.vehicle_position_g, BACKWARD).at(np.zeros(1), "as_taught")
    with pytest.raises(EstimationError, match="as_taught"):
        PerceptionAwareMPC(
            TaughtPathReference(field.vehicle_position_g), ControlConfig(yaw_reference="as_taught"), mode="none"
        )


def test_started_at_the_end_the_backward_plan_goes_back(field):
    z = initial_state(field, -1)
    back = PerceptionAwareMPC(TaughtPathReference.from_field(field, BACKWARD), ControlConfig(), field=field)
    sol = back.solve(z, len(field) - 1)
    assert back.progress_m == pytest.approx(0.0, abs=1e-9)
    assert sol.z_pred[-1, 1] < z[1] - 1.0  # south, back along the north leg
    sol = back.solve(z, len(field) - 1)  # linearized about that plan: its trunks
    assert np.all(np.diff(sol.trunk) <= 0) and sol.trunk[-1] < len(field) - 1  # trunks in travel order
    assert sol.flag is not None and np.all(sol.flag != OFF_ROUTE)
    fwd = PerceptionAwareMPC(TaughtPathReference.from_field(field), ControlConfig(), field=field)
    assert fwd.solve(z, len(field) - 1).z_pred[-1, 1] <= z[1] + 1.0  # forward from the end: nowhere to go


def test_slacks_are_reported_in_their_own_units(field):
    z = initial_state(field, 5)
    z[:3] += np.array([0.0, 3.0, 0.0])  # 3 m off the path: the 1 m bound needs slack
    fixed = PerceptionAwareMPC(
        TaughtPathReference.from_field(field), ControlConfig(), mode="fixed", fixed_bound_m=1.0
    ).solve(z)
    assert fixed.max_slack_m > 0.5 and fixed.max_slack_inliers == 0.0 and fixed.flag is None
    z = initial_state(field, 5)
    z[:3] += np.array([0.0, 6.0, 0.0])  # g far below L_min: perception slack in inliers
    pa = PerceptionAwareMPC(TaughtPathReference.from_field(field), ControlConfig(), field=field).solve(z, 5)
    assert pa.max_slack_m == 0.0 and pa.max_slack_inliers > 1.0


# ----------------------------------------------------------------------------- closed loop
@pytest.fixture(scope="module")
def return_flights(field):
    out = {}
    for name, yaw_ref, mode, governor in (
        ("pa", "as_taught", "perception", 0.8),
        ("none", "as_taught", "none", 0.8),
        ("pa_turned", "along_travel", "perception", 0.8),
        ("pa_no_governor", "as_taught", "perception", 1.0),
    ):
        cfg = ControlConfig(yaw_reference=yaw_ref, speed_governor=governor)
        mpc = PerceptionAwareMPC(TaughtPathReference.from_field(field, BACKWARD), cfg, mode=mode, field=field)
        out[name] = simulate(field, mpc, initial_state(field, -1), time_limit_s=12.0)
    return out


def test_a_return_flight_with_the_camera_on_its_mount_stays_guaranteed(field, return_flights):
    r = return_flights["pa"]
    assert r.completed and r.direction == BACKWARD
    assert np.linalg.norm(r.z[-1, :3] - field.vehicle_position_g[0]) < 1.5  # back at the taught start
    assert r.trunk[0] == len(field) - 1 and r.trunk[-1] <= 1 and np.all(np.diff(r.trunk) <= 0)
    assert r.min_bound >= 30.0  # measured 42.9
    assert np.all(r.flag == OK)
    # the vehicle flew tail first: its yaw stayed the taught one (up to the rate-limited turn at the corner,
    # where the taught yaw steps by 90 degrees), never turned around (pi)
    off = np.abs(np.angle(np.exp(1j * (r.z[:, 9] - field.vehicle_yaw_g[r.trunk]))))
    assert np.median(off) < 0.2 and off.max() < 0.6
    # the same return without the perception rows cuts the corner and loses the guarantee (measured 13.1)
    assert return_flights["none"].completed and return_flights["none"].min_bound < 30.0


def test_turning_the_camera_away_on_the_return_loses_the_landmarks(return_flights):
    # the yaw along travel turns a mounted camera away from everything taught: no guarantee, no arrival
    r = return_flights["pa_turned"]
    assert r.min_bound < 30.0 and not r.completed


def test_the_speed_governor_is_what_keeps_the_return_guaranteed(return_flights):
    # the same return flight with the governor off (speed_governor = 1): measured min mu - 3 sigma 9.1
    off = return_flights["pa_no_governor"]
    assert off.completed and off.min_bound < 30.0 <= return_flights["pa"].min_bound


def test_the_conservative_form_reaches_the_mpc(field):
    mpc = PerceptionAwareMPC(
        TaughtPathReference.from_field(field, BACKWARD),
        ControlConfig(constraint_form="conservative", yaw_reference="as_taught"),
        field=field,
    )
    assert mpc.field.form == "conservative" and field.form == "normal"
    sol = mpc.solve(initial_state(field, -1), len(field) - 1)
    assert sol.status == "solved" and np.all(np.isfinite(sol.w))
