"""Tests of the controller-facing state, the reference path and the path-tracking error."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from vtr.config import SmoothingConfig
from vtr.errors import EstimationError
from vtr.geometry import exp_se3, inv_T, log_se3, make_T
from vtr.state.controller import (
    ControllerState,
    ReferencePath,
    controller_state,
    gravity_aligned_T_o_t,
    trunk_in_world,
    yaw_of,
)
from vtr.state.smoothing import TrajectorySmoother, TrajectoryState

FD_T = 1e-5  # s, time step of finite differences along a trajectory
FD_X = 1e-6  # perturbation step for Jacobians


def _T_world_sensor(t: float) -> np.ndarray:
    """A smooth, tilted, turning and accelerating sensor trajectory in a gravity-aligned world."""
    R = Rotation.from_euler("zyx", [0.3 + 0.4 * t + 0.1 * t * t, 0.1 * np.sin(t), -0.05 + 0.1 * t]).as_matrix()
    p = np.array([2.0 * t + 0.3 * t * t, np.sin(t), 0.2 * t**3])
    return make_T(R, p)


T_SENSOR_VEHICLE = make_T(Rotation.from_euler("xyz", [-100, 5, -92], degrees=True).as_matrix(), [0.1, -0.05, 0.2])
T_WORLD_TRUNK = make_T(Rotation.from_euler("ZYX", [1.0, 0.05, -0.03]).as_matrix(), [1.0, -0.5, 0.3])


def _state_from_truth(t: float, covariance=None) -> TrajectoryState:
    """TrajectoryState of the analytic trajectory (twist and its rate by finite differences)."""

    def twist(u):
        return log_se3(inv_T(_T_world_sensor(u - FD_T)) @ _T_world_sensor(u + FD_T)) / (2 * FD_T)

    acc = (twist(t + 1e-3) - twist(t - 1e-3)) / 2e-3
    return TrajectoryState(int(t * 1e9), _T_world_sensor(t), twist(t), acc, covariance, "interpolated")


def _truth_in_o(t: float, T_o_t: np.ndarray) -> np.ndarray:
    return (T_o_t @ inv_T(T_WORLD_TRUNK) @ _T_world_sensor(t) @ T_SENSOR_VEHICLE)[:3, 3]


def test_gravity_aligned_frame():
    T_o_t = gravity_aligned_T_o_t(T_WORLD_TRUNK[:3, :3])
    C_world_o = T_WORLD_TRUNK[:3, :3] @ T_o_t[:3, :3].T
    np.testing.assert_allclose(C_world_o[:, 2], [0, 0, 1], atol=1e-12)  # z of o is up
    assert abs(yaw_of(T_o_t[:3, :3])) < 1e-12  # o has the trunk's yaw
    np.testing.assert_allclose(T_o_t[:3, 3], 0.0)  # origin at the trunk
    np.testing.assert_allclose(yaw_of(C_world_o), 1.0, atol=1e-12)


def test_controller_state_matches_trajectory_derivatives():
    T_o_t = gravity_aligned_T_o_t(T_WORLD_TRUNK[:3, :3])
    t = 0.8
    cs = controller_state(_state_from_truth(t), T_WORLD_TRUNK, T_o_t, T_SENSOR_VEHICLE)
    h = 1e-3
    p = [_truth_in_o(t + k * h, T_o_t) for k in (-1, 0, 1)]
    np.testing.assert_allclose(cs.position, p[1], atol=1e-12)
    np.testing.assert_allclose(cs.velocity, (p[2] - p[0]) / (2 * h), atol=1e-5)
    np.testing.assert_allclose(cs.acceleration, (p[2] - 2 * p[1] + p[0]) / h**2, atol=1e-3)
    T_o_a = T_o_t @ inv_T(T_WORLD_TRUNK) @ _T_world_sensor(t) @ T_SENSOR_VEHICLE
    np.testing.assert_allclose(cs.T_o_a, T_o_a, atol=1e-12)
    assert cs.yaw == pytest.approx(np.arctan2(T_o_a[1, 0], T_o_a[0, 0]))
    # thesis form: T_o_a = T_o_t inv(T_a_t)
    T_a_t = inv_T(_T_world_sensor(t) @ T_SENSOR_VEHICLE) @ T_WORLD_TRUNK
    np.testing.assert_allclose(cs.T_o_a, T_o_t @ inv_T(T_a_t), atol=1e-12)
    assert cs.z.shape == (10,) and cs.y.shape == (4,)
    np.testing.assert_allclose(cs.y, np.r_[cs.position, cs.yaw])


def test_controller_covariance_jacobians_numerical():
    """Position/velocity/yaw covariances equal J Sigma J^T with J by numerical differences."""
    rng = np.random.default_rng(0)
    A = rng.normal(size=(12, 12))
    Sigma = A @ A.T * 1e-3 + np.eye(12) * 1e-4
    T_o_t = gravity_aligned_T_o_t(T_WORLD_TRUNK[:3, :3])
    base = _state_from_truth(0.5, Sigma)
    cs = controller_state(base, T_WORLD_TRUNK, T_o_t, T_SENSOR_VEHICLE)

    def outputs(delta):
        s = TrajectoryState(
            base.t_ns,
            base.pose @ exp_se3(delta[:6]),
            base.velocity + delta[6:],
            base.acceleration,
            None,
            "interpolated",
        )
        c = controller_state(s, T_WORLD_TRUNK, T_o_t, T_SENSOR_VEHICLE)
        return np.r_[c.position, c.velocity, c.yaw]

    J = np.zeros((7, 12))
    for j in range(12):
        d = np.zeros(12)
        d[j] = FD_X
        J[:, j] = (outputs(d) - outputs(-d)) / (2 * FD_X)
    C = J @ Sigma @ J.T
    np.testing.assert_allclose(cs.position_covariance, C[:3, :3], rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(cs.velocity_covariance, C[3:6, 3:6], rtol=1e-6, atol=1e-12)
    assert cs.yaw_variance == pytest.approx(C[6, 6], rel=1e-6)


def test_trunk_in_world_and_from_world_path():
    T_world_leaf = exp_se3([0.1, 0.0, 0.4, 3.0, 1.0, 0.5])
    T_leaf_trunk = exp_se3([0.0, 0.02, -0.1, -0.4, 0.2, 0.0])
    T_world_trunk = trunk_in_world(T_world_leaf, T_leaf_trunk)
    np.testing.assert_allclose(T_world_trunk, T_world_leaf @ T_leaf_trunk)
    T_o_t = gravity_aligned_T_o_t(T_world_trunk[:3, :3])
    verts = np.stack([T_world_trunk @ exp_se3([0, 0, 0, k, 0.1 * k, 0]) for k in range(4)])
    path_w = ReferencePath.from_world(verts, T_world_trunk, T_o_t)
    path_t = ReferencePath.from_vertices(np.stack([inv_T(T_world_trunk) @ T for T in verts]), T_o_t)
    np.testing.assert_allclose(path_w.points, path_t.points, atol=1e-12)
    np.testing.assert_allclose(path_w.points[0], 0.0, atol=1e-12)  # trunk at the origin of o
    # p_o^{nt} = C_o_t p_t^{nt}
    p_t = (inv_T(T_world_trunk) @ verts[2])[:3, 3]
    np.testing.assert_allclose(path_w.points[2], T_o_t[:3, :3] @ p_t, atol=1e-12)


# ---- reference path -----------------------------------------------------------------------------


def test_path_error_straight_line():
    path = ReferencePath(np.array([[0.0, 0, 0], [10.0, 0, 0]]))
    e = path.error(np.array([3.0, 2.0, 1.0]))
    assert e.lateral == pytest.approx(2.0)  # left of +x travel is +y
    assert e.vertical == pytest.approx(1.0)
    assert e.along_track == pytest.approx(3.0)
    assert e.segment == 0
    np.testing.assert_allclose(e.reference_point, [3, 0, 0])
    np.testing.assert_allclose(e.direction, [1, 0, 0])
    e = path.error(np.array([[4.0, -1.5, -0.5], [-2.0, 0.0, 0.0], [12.0, 0.0, 0.0]]))
    np.testing.assert_allclose(e.lateral, [-1.5, 0, 0])
    np.testing.assert_allclose(e.vertical, [-0.5, 0, 0])
    np.testing.assert_allclose(e.along_track, [4.0, -2.0, 12.0])
    np.testing.assert_allclose(e.cross_track, [np.hypot(1.5, 0.5), 0, 0])


def test_path_error_l_shape_and_slope():
    path = ReferencePath(np.array([[0.0, 0, 10], [10.0, 0, 10], [10.0, 10, 10]]))
    e = path.error(np.array([[9.0, 5.0, 10.0], [5.0, 0.5, 10.0]]))
    np.testing.assert_array_equal(e.segment, [1, 0])
    np.testing.assert_allclose(e.lateral, [1.0, 0.5])  # left of +y travel is -x
    np.testing.assert_allclose(e.along_track, [15.0, 5.0])
    assert path.length == pytest.approx(20.0)
    # climbing segment: vertical is measured perpendicular to it in its vertical plane
    slope = ReferencePath(np.array([[0.0, 0, 0], [3.0, 0, 4.0]]))
    e = slope.error(np.array([1.5, 0.0, 2.0]) + np.array([-0.8, 0.0, 0.6]))
    assert e.vertical == pytest.approx(1.0)
    assert e.lateral == pytest.approx(0.0, abs=1e-12)
    assert e.along_track == pytest.approx(2.5)


def test_path_vertical_segment_and_duplicates():
    path = ReferencePath(np.array([[0.0, 0, 0], [0.0, 0, 0], [0.0, 0, 5.0]]))
    assert len(path.points) == 2
    e = path.error(np.array([3.0, 4.0, 2.0]))
    assert e.lateral == pytest.approx(5.0)
    assert e.along_track == pytest.approx(2.0)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000))
def test_path_error_vectorized_equals_single(seed):
    rng = np.random.default_rng(seed)
    pts = np.cumsum(rng.normal(size=(6, 3)), axis=0)
    path = ReferencePath(pts)
    P = rng.normal(scale=3.0, size=(8, 3))
    batch = path.error(P)
    for i, p in enumerate(P):
        one = path.error(p)
        assert one.segment == batch.segment[i]
        assert one.lateral == pytest.approx(batch.lateral[i])
        assert one.vertical == pytest.approx(batch.vertical[i])
        assert one.along_track == pytest.approx(batch.along_track[i])
        # the chosen segment is the closest one
        d = np.linalg.norm(one.reference_point - p)
        for a, b in zip(pts[:-1], pts[1:], strict=True):
            s = np.clip(np.dot(p - a, b - a) / np.dot(b - a, b - a), 0, 1)
            assert d <= np.linalg.norm(a + s * (b - a) - p) + 1e-9
        # decomposition: the offset from the segment's line is lateral*left + vertical*up
        k = one.segment
        a = path.points[k]
        off = (p - a) - np.dot(p - a, path.directions[k]) * path.directions[k]
        np.testing.assert_allclose(
            off, one.lateral * path.left_normals[k] + one.vertical * path.up_normals[k], atol=1e-9
        )


@pytest.mark.parametrize(
    "points",
    [np.zeros((1, 3)), np.zeros((3, 2)), np.array([[0.0, 0, 0], [np.nan, 0, 0]]), np.zeros((4, 3))],
)
def test_path_bad_input(points):
    with pytest.raises(EstimationError):
        ReferencePath(points)


def test_controller_state_bad_input():
    s = _state_from_truth(0.3)
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(EstimationError):
        controller_state(s, bad, np.eye(4))
    with pytest.raises(EstimationError):
        gravity_aligned_T_o_t(np.full((3, 3), np.nan))


def test_with_smoother_end_to_end():
    """Smoother + controller state: the extrapolated controller state tracks a straight flight."""
    sm = TrajectorySmoother(SmoothingConfig())
    cov = np.diag([1e-6] * 3 + [1e-4] * 3)
    speed = 3.0
    for k in range(30):
        sm.add_pose(k * 66_666_667, make_T(np.eye(3), [speed * k * 0.066666667, 0.0, 10.0]), cov)
    t_now = 29 * 66_666_667 + 20_000_000
    T_world_trunk = make_T(np.eye(3), [5.0, 0.0, 10.0])
    T_o_t = gravity_aligned_T_o_t(T_world_trunk[:3, :3])
    cs = controller_state(sm.state_at(t_now), T_world_trunk, T_o_t)
    assert isinstance(cs, ControllerState)
    np.testing.assert_allclose(cs.velocity, [speed, 0, 0], atol=1e-3)
    np.testing.assert_allclose(cs.position, [speed * t_now / 1e9 - 5.0, 0, 0], atol=1e-3)
    path = ReferencePath(np.array([[0.0, 0, 0], [20.0, 0, 0]]))
    e = path.error(cs.position)
    assert abs(e.lateral) < 1e-3 and abs(e.vertical) < 1e-3
    assert np.all(np.linalg.eigvalsh(cs.position_covariance) > 0)
