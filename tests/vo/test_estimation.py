"""Robust estimation on exact synthetic correspondences (known answers)."""

from typing import NamedTuple

import numpy as np
import pytest

from vtr.camera import StereoCamera
from vtr.geometry import exp_se3, log_se3
from vtr.vo.estimation import bundle_adjust, ransac_pnp

CAM = StereoCamera(fx=700.0, fy=700.0, cx=600.0, cy=185.0, baseline=0.54, width=1226, height=370)


def _scene(rng, n=400):
    z = rng.uniform(4, 60, n)
    u = rng.uniform(0, CAM.width, n)
    v = rng.uniform(0, CAM.height, n)
    return CAM.triangulate(u, v, CAM.fb / z)


def _views(rng, T_q_r, sigma):
    X = _scene(rng)
    Y = X @ T_q_r[:3, :3].T + T_q_r[:3, 3]
    zr = CAM.project(X) + rng.normal(0, sigma, (len(X), 3))
    zq = CAM.project(Y) + rng.normal(0, sigma, (len(X), 3))
    ok = (zr[:, 0] - zr[:, 2] > 0.5) & (zq[:, 0] - zq[:, 2] > 0.5) & (Y[:, 2] > 1)
    zr, zq = zr[ok], zq[ok]
    return CAM.triangulate(zr[:, 0], zr[:, 1], zr[:, 0] - zr[:, 2]), zr, zq


class TwoView(NamedTuple):
    T_q_r: np.ndarray
    covariance: np.ndarray
    inlier: np.ndarray


def refine_two_view(T_q_r, X, zr, zq, sigma_px, huber_px, iterations, outlier_px) -> TwoView:
    """Two-view stereo bundle adjustment (reference view fixed, landmarks free, every measured row counted)."""
    n = len(X)
    z = np.concatenate([zr, zq])
    res = bundle_adjust(
        np.stack([np.eye(4), T_q_r]),
        np.array([True, False]),
        X,
        np.r_[np.zeros(n, int), np.ones(n, int)],
        np.r_[np.arange(n), np.arange(n)],
        np.nan_to_num(z),
        np.isfinite(z).astype(float),
        CAM,
        sigma_px,
        huber_px,
        iterations,
    )
    inlier = np.maximum(res.error_sq[:n], res.error_sq[n:]) <= outlier_px**2
    return TwoView(res.T_cam_world[1], res.pose_covariance[1], inlier)


T_TRUE = exp_se3(np.array([0.01, -0.02, 0.005, 0.05, -0.02, -1.2]))


def test_ransac_finds_pose_despite_outliers():
    rng = np.random.default_rng(1)
    X, _, zq = _views(rng, T_TRUE, 0.0)
    uv = zq[:, :2].copy()
    bad = rng.random(len(uv)) < 0.4
    uv[bad] = rng.uniform(0, 600, (bad.sum(), 2))
    rs = ransac_pnp(X, uv, CAM, 2000, 2.0, 0.999, seed=0)
    assert rs is not None
    assert set(rs.inliers) >= set(np.flatnonzero(~bad)) - set(np.flatnonzero(bad))
    np.testing.assert_allclose(rs.T_q_r, T_TRUE, atol=1e-6)


def test_refinement_is_exact_without_noise():
    rng = np.random.default_rng(2)
    X, zr, zq = _views(rng, T_TRUE, 0.0)
    start = exp_se3(np.array([0.003, 0, 0, 0.02, 0.0, 0.05])) @ T_TRUE
    rf = refine_two_view(start, X, zr, zq, 1.0, 1.5, 20, 5.0)
    np.testing.assert_allclose(log_se3(rf.T_q_r @ np.linalg.inv(T_TRUE)), 0, atol=1e-8)
    assert rf.inlier.all()


def test_refinement_translation_is_unbiased_under_pixel_noise():
    """Stereo BA in both views: no scale bias from triangulating small disparities."""
    rng = np.random.default_rng(3)
    ratios = []
    for _ in range(20):
        X, zr, zq = _views(rng, T_TRUE, 0.5)
        rs = ransac_pnp(X, zq[:, :2], CAM, 500, 5.0, 0.999, seed=0)
        rf = refine_two_view(rs.T_q_r, X, zr, zq, 0.5, 1.0, 10, 5.0)
        ratios.append(np.linalg.norm(rf.T_q_r[:3, 3]) / np.linalg.norm(T_TRUE[:3, 3]) - 1)
    assert abs(np.mean(ratios)) < 3 * np.std(ratios) / np.sqrt(len(ratios)) + 1e-3


def test_refinement_with_mono_observations():
    rng = np.random.default_rng(4)
    X, zr, zq = _views(rng, T_TRUE, 0.0)
    zq = zq.copy()
    zq[::2, 2] = np.nan  # half the query features have no right match
    rf = refine_two_view(exp_se3(np.full(6, 1e-3)) @ T_TRUE, X, zr, zq, 1.0, 1.5, 20, 5.0)
    np.testing.assert_allclose(rf.T_q_r, T_TRUE, atol=1e-7)
    assert np.all(np.linalg.eigvalsh(rf.covariance) > 0)


@pytest.mark.parametrize("n", [0, 3])
def test_ransac_needs_four_points(n):
    assert ransac_pnp(np.zeros((n, 3)), np.zeros((n, 2)), CAM, 10, 1.0, 0.99, 0) is None


def test_triangulate_bearings_recovers_points_from_rays_alone():
    from vtr.vo.estimation import triangulate_bearings

    rng = np.random.default_rng(5)
    X = _scene(rng, 50)
    T = np.stack([exp_se3(np.r_[rng.normal(0, 0.02, 3), rng.normal(0, 0.5, 3)]) for _ in range(4)])
    pose = np.repeat(np.arange(4), len(X))
    point = np.tile(np.arange(len(X)), 4)
    Y = np.einsum("mij,mj->mi", T[pose, :3, :3], X[point]) + T[pose, :3, 3]
    ok = Y[:, 2] > 0.5
    uv = CAM.project(Y[ok])[:, :2]
    P, parallax = triangulate_bearings(T, pose[ok], point[ok], uv, CAM, len(X))
    seen = np.bincount(point[ok], minlength=len(X)) >= 2
    np.testing.assert_allclose(P[seen], X[seen], rtol=1e-6, atol=1e-6)
    assert np.all(parallax[seen] > 0) and np.all(parallax[~seen] == 0)


def test_stereo_row_weights_split_near_and_far():
    from vtr.vo.estimation import stereo_row_weights

    near_depth = 15 * CAM.baseline
    d = np.array([CAM.fb / near_depth + 1, CAM.fb / near_depth - 1, 2.0, np.nan])
    z = np.column_stack([np.full(4, 600.0), np.full(4, 100.0), 600.0 - d])
    w = stereo_row_weights(z, CAM, near_depth, 1e-4)
    np.testing.assert_array_equal(w[:, :2], 1.0)
    np.testing.assert_array_equal(w[:, 2], [1.0, 1e-4, 1e-4, 0.0])
    # fewer near observations than asked for: nothing to carry the scale but the far ones, which count fully
    w = stereo_row_weights(z, CAM, near_depth, 1e-4, min_near=2)
    np.testing.assert_array_equal(w[:, 2], [1.0, 1.0, 1.0, 0.0])
