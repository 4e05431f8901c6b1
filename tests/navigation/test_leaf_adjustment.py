"""The localization's compiled submap adjustment (vtr.navigation.leaf_adjustment) against the general bundle
adjustment it stands in for (vtr.vo.estimation.bundle_adjust) on the same problems: the same pose, landmarks,
errors, covariance and cost to rounding, with noise, outliers (Huber), missing and down-weighted disparity rows,
an iteration cap and a singular system."""

from __future__ import annotations

import numpy as np
import pytest

from vtr.camera import StereoCamera
from vtr.errors import EstimationError
from vtr.geometry import exp_se3
from vtr.navigation.leaf_adjustment import adjust_leaf
from vtr.vo.estimation import bundle_adjust

CAMERA = StereoCamera(fx=718.856, fy=718.856, cx=607.19, cy=185.22, baseline=0.537, width=1226, height=370)


def _project(T: np.ndarray, X: np.ndarray) -> np.ndarray:
    Y = X @ T[:3, :3].T + T[:3, 3]
    return CAMERA.project(Y)


def _problem(seed: int, n: int = 300, vertices: int = 3, outliers: float = 0.1):
    """A leaf near a few taught vertices along +z, landmarks 3-60 m ahead, noisy stereo measurements from the
    vertex that stored each landmark and from the leaf; a share of the leaf's measurements are outliers, some right
    matches missing, far disparities down-weighted and the stored points perturbed (the adjustment's start)."""
    rng = np.random.default_rng(seed)
    T_vertex_trunk = np.stack([np.eye(4) for _ in range(vertices)])
    for s in range(vertices):
        T_vertex_trunk[s, 2, 3] = -0.4 * (s - vertices // 2)  # vertex s sits 0.4 m along the route from the trunk
    T_true = exp_se3(np.r_[rng.normal(0, 0.02, 3), rng.normal(0, 0.3, 3)])
    depth = rng.uniform(3.0, 60.0, n)
    X = np.column_stack([rng.uniform(-0.5, 0.5, n) * depth, rng.uniform(-0.15, 0.15, n) * depth, depth])
    slot = rng.integers(0, vertices, n)
    z_taught = np.array([_project(T_vertex_trunk[s], X[i : i + 1])[0] for i, s in enumerate(slot)])
    z_leaf = _project(T_true, X)
    z = np.concatenate([z_taught, z_leaf]) + rng.normal(0, 0.4, (2 * n, 3))
    bad = n + np.flatnonzero(rng.random(n) < outliers)
    z[bad, :2] += rng.normal(0, 8.0, (len(bad), 2))
    w = np.ones((2 * n, 3))
    w[rng.random(2 * n) < 0.05, 2] = 0.0  # no right match
    w[np.r_[depth, depth] > 30.0, 2] = 0.1  # a far landmark's disparity barely counts
    T_start = exp_se3(np.r_[rng.normal(0, 0.01, 3), rng.normal(0, 0.05, 3)]) @ T_true
    X_start = X + rng.normal(0, 0.05, X.shape) * (depth[:, None] / 10.0)
    return T_vertex_trunk, slot, T_start, X_start, np.where(w > 0, z, np.nan), w


def _general(T_vertex_trunk, slot, T_start, X_start, z, w, iterations=10):
    V, n = len(T_vertex_trunk), len(X_start)
    return bundle_adjust(
        np.concatenate([T_vertex_trunk, T_start[None]]),
        np.r_[np.ones(V, bool), False],
        X_start,
        np.r_[slot, np.full(n, V)],
        np.r_[np.arange(n), np.arange(n)],
        np.nan_to_num(z),
        w,
        CAMERA,
        1.0,
        1.5,
        iterations,
    )


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("iterations", [1, 3, 10])
def test_the_leaf_adjustment_is_bundle_adjust_of_its_shape(seed, iterations):
    T_vertex_trunk, slot, T_start, X_start, z, w = _problem(seed)
    ref = _general(T_vertex_trunk, slot, T_start, X_start, z, w, iterations)
    got = adjust_leaf(T_vertex_trunk, slot, T_start, X_start, np.nan_to_num(z), w, CAMERA, 1.0, 1.5, iterations)
    V = len(T_vertex_trunk)
    assert not np.allclose(got.T_leaf_trunk, T_start, atol=1e-6)  # it moved
    np.testing.assert_allclose(got.T_leaf_trunk, ref.T_cam_world[V], rtol=0, atol=1e-9)
    np.testing.assert_allclose(got.points, ref.points, rtol=1e-7, atol=1e-7)
    np.testing.assert_allclose(got.error_sq, ref.error_sq, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(got.covariance, ref.pose_covariance[V], rtol=1e-6, atol=1e-15)
    assert got.cost == pytest.approx(ref.cost, rel=1e-9)


def test_the_leaf_adjustment_recovers_the_pose_without_outliers():
    T_vertex_trunk, slot, T_start, X_start, z, w = _problem(7, outliers=0.0)
    got = adjust_leaf(T_vertex_trunk, slot, T_start, X_start, np.nan_to_num(z), w, CAMERA, 1.0, 1.5, 10)
    rng = np.random.default_rng(7)  # the same draws as _problem: the true pose
    T_true = exp_se3(np.r_[rng.normal(0, 0.02, 3), rng.normal(0, 0.3, 3)])
    assert np.abs(got.T_leaf_trunk[:3, 3] - T_true[:3, 3]).max() < 0.05
    assert np.abs(got.T_leaf_trunk[:3, 3] - T_true[:3, 3]).max() < np.abs(T_start[:3, 3] - T_true[:3, 3]).max()
    assert np.all(np.linalg.eigvalsh(got.covariance) > 0)


def test_a_landmark_behind_a_camera_is_an_estimation_error():
    T_vertex_trunk, slot, T_start, X_start, z, w = _problem(1)
    X_start[5, 2] = -2.0
    with pytest.raises(EstimationError, match="behind its camera"):
        adjust_leaf(T_vertex_trunk, slot, T_start, X_start, np.nan_to_num(z), w, CAMERA, 1.0, 1.5, 10)
    with pytest.raises(EstimationError, match="behind its camera"):
        _general(T_vertex_trunk, slot, T_start, X_start, z, w)


def test_a_pose_the_measurements_do_not_fix_gets_a_nan_covariance_as_bundle_adjust_does():
    # every leaf row unmeasured: the leaf's system is zero, the damped step is zero, its inverse does not exist
    T_vertex_trunk, slot, T_start, X_start, z, w = _problem(2, n=20)
    w[20:] = 0.0
    ref = _general(T_vertex_trunk, slot, T_start, X_start, z, w)
    got = adjust_leaf(T_vertex_trunk, slot, T_start, X_start, np.nan_to_num(z), w, CAMERA, 1.0, 1.5, 10)
    assert np.isnan(ref.pose_covariance[len(T_vertex_trunk)]).all()
    assert np.isnan(got.covariance).all()
    np.testing.assert_array_equal(got.T_leaf_trunk, T_start)


def test_the_warm_up_compiles_the_signature_a_localization_calls():
    """``.ci/setup`` warms the kernel up (vtr.navigation.kernels.warm_up): a localization's call then needs no
    compilation of its own (the first repeat after an install would otherwise take ~15 s longer)."""
    from vtr.navigation import kernels

    kernels.warm_up()
    before = list(kernels.adjust.signatures)
    T_vertex_trunk, slot, T_start, X_start, z, w = _problem(3)
    adjust_leaf(T_vertex_trunk, slot, T_start, X_start, np.nan_to_num(z), w, CAMERA, 1.0, 1.5, 10)
    assert list(kernels.adjust.signatures) == before
