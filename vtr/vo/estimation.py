"""Robust relative-pose estimation between stereo views.

* ``ransac_pnp``: minimal-solver RANSAC (OpenCV P3P) on 3-D landmarks of a reference view
  against pixels of a query view: the outlier filter.
* ``bundle_adjust``: stereo bundle adjustment (Levenberg-Marquardt, Schur complement, Huber) over
  poses and landmarks, used for tracking (landmarks held by their window observations), the window
  of odometry and localization against a taught submap. Depth is never taken as exact: landmarks
  stay free, and ``stereo_row_weights`` decides how much each disparity counts (near / far).
* ``triangulate_bearings``: multi-view triangulation from left-image rays alone (parallax).

Poses: ``T_q_r`` maps reference-camera coordinates into the query camera (both left rectified).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..camera import StereoCamera
from ..config import EstimationConfig
from ..errors import EstimationError
from ..geometry import exp_se3
from .kernels import bundle as kb


@dataclass(frozen=True)
class RansacResult:
    T_q_r: np.ndarray
    inliers: np.ndarray  # indices into the correspondences


def ransac_pnp(
    points_r: np.ndarray,
    uv_q: np.ndarray,
    camera: StereoCamera,
    iterations: int,
    threshold_px: float,
    confidence: float,
    seed: int,
    T_guess: np.ndarray | None = None,
) -> RansacResult | None:
    """P3P RANSAC of ``T_q_r`` from landmarks (N, 3) in frame r and their left pixels (N, 2) in q."""
    if len(points_r) < 4:
        return None
    cv2.setRNGSeed(seed)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        points_r.astype(np.float64),
        uv_q.astype(np.float64),
        camera.K,
        None,
        iterationsCount=iterations,
        reprojectionError=threshold_px,
        confidence=confidence,
        flags=cv2.SOLVEPNP_P3P,
    )
    if not ok or inl is None or len(inl) < 4:
        return None
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    return RansacResult(T, inl.ravel())


def stereo_row_weights(
    z: np.ndarray, camera: StereoCamera, near_depth_m: float, far_disparity_weight: float, min_near: int = 1
) -> np.ndarray:
    """Weights of the measurement rows (u_l, v, u_r) of stereo observations ``z`` (M, 3).

    The image position (u_l, v) always counts. The disparity row counts fully only for a near
    landmark (depth within ``near_depth_m``, i.e. disparity >= fb / near_depth_m); for a far one it
    keeps ``far_disparity_weight`` (0 where the right match is missing). A far landmark then fixes
    rotation and, seen from several poses, its own depth by parallax, while the scale comes from
    near landmarks: a disparity error of a fraction of a pixel, systematic over the image (a
    rectification error, see docs/far_structure.md), is a few percent of depth for a near landmark
    and tens of percent for a far one. When fewer than ``min_near`` observations are near (a camera
    high above the ground sees nothing near), every disparity counts fully: the scale can then come
    only from the far structure.
    """
    w = np.ones((len(z), 3))
    disparity = z[:, 0] - z[:, 2]
    measured = np.isfinite(disparity)
    w[~measured, 2] = 0.0
    far = measured & (disparity < camera.fb / near_depth_m)
    if np.count_nonzero(measured & ~far) >= min_near:
        w[far, 2] = far_disparity_weight
    return w


def odometry_row_weights(z: np.ndarray, camera: StereoCamera, config: EstimationConfig) -> np.ndarray:
    """:func:`stereo_row_weights` with the near/far settings of ``estimation`` (the one rule odometry and
    localization share): near within ``far_point_baselines`` baselines."""
    return stereo_row_weights(
        z,
        camera,
        config.far_point_baselines * camera.baseline,
        config.far_disparity_weight,
        config.min_near_observations,
    )


def triangulate_bearings(
    T_cam_world: np.ndarray,
    obs_pose: np.ndarray,
    obs_point: np.ndarray,
    uv: np.ndarray,
    camera: StereoCamera,
    n_points: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Multi-view triangulation of landmarks from their left-image bearings alone (no disparity).

    The point nearest, in the least-squares sense, to every ray that observed it (``obs_pose``,
    ``obs_point`` index the pose and landmark of each observation, ``uv`` its left pixel). Returns
    the points (n_points, 3) in world and the largest angle (rad) between two of each point's rays
    (its parallax; 0 for a point seen once, NaN points where the rays are parallel).
    """
    R = T_cam_world[:, :3, :3]
    centres = -np.einsum("kji,kj->ki", R, T_cam_world[:, :3, 3])
    rays = np.column_stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy, np.ones(len(uv))])
    d = np.einsum("mji,mj->mi", R[obs_pose], rays)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    P = np.eye(3) - d[:, :, None] * d[:, None, :]  # projector orthogonal to each ray
    A = np.zeros((n_points, 3, 3))
    b = np.zeros((n_points, 3))
    np.add.at(A, obs_point, P)
    np.add.at(b, obs_point, np.einsum("mij,mj->mi", P, centres[obs_pose]))
    points = np.full((n_points, 3), np.nan)
    ok = np.abs(np.linalg.det(A)) > 1e-12
    points[ok] = np.linalg.solve(A[ok], b[ok][:, :, None])[:, :, 0]
    # parallax: angle between the two most different rays, from the extreme directions about the mean
    mean = np.zeros((n_points, 3))
    np.add.at(mean, obs_point, d)
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)
    cos_to_mean = np.einsum("mi,mi->m", d, mean[obs_point])
    widest = np.ones(n_points)
    np.minimum.at(widest, obs_point, cos_to_mean)
    return points, 2 * np.arccos(np.clip(widest, -1.0, 1.0))


def stereo_jacobian(p: np.ndarray, camera: StereoCamera) -> np.ndarray:
    """d(u_l, v, u_r)/d(point) at points p (N, 3) in the camera frame -> (N, 3, 3)."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    iz = 1.0 / z
    J = np.zeros((len(p), 3, 3))
    J[:, 0, 0] = camera.fx * iz
    J[:, 0, 2] = -camera.fx * x * iz * iz
    J[:, 1, 1] = camera.fy * iz
    J[:, 1, 2] = -camera.fy * y * iz * iz
    J[:, 2, 0] = camera.fx * iz
    J[:, 2, 2] = -camera.fx * (x - camera.baseline) * iz * iz
    return J


@dataclass(frozen=True)
class BundleResult:
    """Refined camera poses ``T_cam_world`` (K, 4, 4), landmarks (L, 3) in world, per-observation
    squared reprojection error (px^2, over the measured rows) and the marginal 6x6 covariance of
    each free pose ([rot, trans], left perturbation; zeros for fixed poses)."""

    T_cam_world: np.ndarray
    points: np.ndarray
    error_sq: np.ndarray
    pose_covariance: np.ndarray
    cost: float


RELATIVE_COST_TOLERANCE = 1e-6  # bundle adjustment stops when a step lowers the cost by less than this
POSE_STEP_TOLERANCE = 1e-5  # ... or moves no pose by more than this (rad, m): only landmarks still creep
MAX_LM_ATTEMPTS = 8  # damping increases per iteration before giving up
MIN_LM_DAMPING = 1e-7


def bundle_adjust(
    T_cam_world: np.ndarray,
    fixed: np.ndarray,
    points: np.ndarray,
    obs_pose: np.ndarray,
    obs_point: np.ndarray,
    z: np.ndarray,
    row_weight: np.ndarray,
    camera: StereoCamera,
    sigma_px: float,
    huber_px: float,
    iterations: int,
    fix_points: bool = False,
) -> BundleResult:
    """Levenberg-Marquardt bundle adjustment on stereo reprojection errors (u_l, v, u_r).

    ``obs_pose``/``obs_point`` index the pose and landmark of each observation (a landmark is seen at
    most once per pose), ``z`` (M, 3) its measurement and ``row_weight`` (M, 3) a weight per measured
    row (0 for a missing right match, small for the disparity of a far landmark). Landmarks are
    eliminated by the Schur complement (3x3 blocks), so the solve is over the free poses only;
    ``fix_points`` refines poses alone. Poses are perturbed on the left, ``T <- Exp(xi) T`` with
    ``xi = [omega, v]``. The per-observation work runs in compiled kernels (``vtr.vo.kernels.bundle``).
    """
    T = T_cam_world.copy()
    X = np.ascontiguousarray(points, dtype=np.float64).copy()
    K, L = len(T), len(X)
    pose_free = ~np.asarray(fixed, bool)
    free = np.flatnonzero(pose_free)
    free_rows = (free[:, None] * 6 + np.arange(6)).ravel()
    obs_pose = np.ascontiguousarray(obs_pose, dtype=np.int64)
    obs_point = np.ascontiguousarray(obs_point, dtype=np.int64)
    info_rows = np.ascontiguousarray(row_weight / sigma_px**2, dtype=np.float64)
    measured = (row_weight > 0).astype(np.float64)
    zz = np.ascontiguousarray(np.where(row_weight > 0, z, 0.0), dtype=np.float64)
    k_huber = huber_px / sigma_px
    point_obs = np.argsort(obs_point, kind="stable")
    point_start = np.searchsorted(obs_point[point_obs], np.arange(L + 1))
    cam = (camera.fx, camera.fy, camera.cx, camera.cy, camera.fb)

    def evaluate(T_, X_):
        return kb.residuals(
            np.ascontiguousarray(T_[:, :3, :3]),
            np.ascontiguousarray(T_[:, :3, 3]),
            X_,
            obs_pose,
            obs_point,
            zz,
            measured,
            info_rows,
            k_huber,
            *cam,
        )

    Y, e, w, cost, min_depth = evaluate(T, X)
    if not min_depth > 0:
        raise EstimationError("bundle_adjust: a landmark starts behind its camera")
    lam = 1e-4
    S = np.eye(6 * K)
    for _ in range(iterations):
        R = np.ascontiguousarray(T[:, :3, :3])
        H, b, Hll, bl, W = kb.normal_equations(
            R, Y, e, w, obs_pose, obs_point, info_rows, L, pose_free, fix_points, camera.fx, camera.fy, camera.fb
        )
        improved = converged = False
        for _attempt in range(MAX_LM_ATTEMPTS):
            if fix_points:
                S, g = H, b
            else:
                # damping on the landmark blocks too: far landmarks seen along one ray are ill-conditioned
                S, g, Hll_inv = kb.schur(H, b, Hll, bl, W, obs_pose, point_start, point_obs, pose_free, lam)
            S_f = S[np.ix_(free_rows, free_rows)]
            try:
                dp = np.linalg.solve(S_f + lam * np.diag(np.diag(S_f) + 1e-9), g[free_rows])
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            dpk = np.zeros(6 * K)
            dpk[free_rows] = dp
            T_new = T.copy()
            for k in free:
                T_new[k] = exp_se3(dpk[6 * k : 6 * k + 6]) @ T[k]
            X_new = X
            if not fix_points:
                X_new = kb.back_substitute(X, Hll_inv, bl, W, obs_pose, point_start, point_obs, dpk)
            Y_n, e_n, w_n, cost_n, depth_n = evaluate(T_new, X_new)
            if depth_n > 0 and cost_n < cost:
                converged = cost - cost_n < RELATIVE_COST_TOLERANCE * cost or np.max(np.abs(dp)) < POSE_STEP_TOLERANCE
                T, X, Y, e, w, cost = T_new, X_new, Y_n, e_n, w_n, cost_n
                lam = max(lam / 10, MIN_LM_DAMPING)
                improved = True
                break
            lam *= 10
        if not improved or converged:
            break
    cov = np.zeros((K, 6, 6))
    if len(free):
        try:
            Sinv = np.linalg.inv(S[np.ix_(free_rows, free_rows)])
            for j, k in enumerate(free):
                cov[k] = Sinv[6 * j : 6 * j + 6, 6 * j : 6 * j + 6]
        except np.linalg.LinAlgError:
            cov[free] = np.nan
    err_sq = ((camera.project(Y) - zz) ** 2 * measured).sum(1)
    return BundleResult(T, X, err_sq, cov, cost)
