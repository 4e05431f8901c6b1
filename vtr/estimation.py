"""Robust relative-pose estimation between stereo views.

* ``ransac_pnp``: minimal-solver RANSAC (OpenCV P3P) on 3-D landmarks of a reference view
  against pixels of a query view: the outlier filter.
* ``refine_two_view``: a two-view stereo bundle adjustment, minimising the stereo reprojection
  error (u_l, v, u_r) in *both* views over the relative pose and the landmark positions, with a
  Huber kernel. Depth is never taken as exact: a far landmark (small disparity) is free to move
  along its ray, so it constrains rotation far more than translation, and the depth bias of
  triangulation from small disparities does not leak into the translation.

Poses: ``T_q_r`` maps reference-camera coordinates into the query camera (both left rectified).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .camera import StereoCamera
from .geometry import exp_se3, skew


@dataclass(frozen=True)
class RansacResult:
    T_q_r: np.ndarray
    inliers: np.ndarray  # indices into the correspondences


def ransac_pnp(points_r: np.ndarray, uv_q: np.ndarray, camera: StereoCamera, iterations: int,
               threshold_px: float, confidence: float, seed: int,
               T_guess: np.ndarray | None = None) -> RansacResult | None:
    """P3P RANSAC of ``T_q_r`` from landmarks (N, 3) in frame r and their left pixels (N, 2) in q."""
    if len(points_r) < 4:
        return None
    cv2.setRNGSeed(seed)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        points_r.astype(np.float64), uv_q.astype(np.float64), camera.K, None,
        iterationsCount=iterations, reprojectionError=threshold_px, confidence=confidence,
        flags=cv2.SOLVEPNP_P3P,
    )
    if not ok or inl is None or len(inl) < 4:
        return None
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    return RansacResult(T, inl.ravel())


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
class RefineResult:
    """Refined ``T_q_r``, its 6x6 covariance ([rot, trans], left perturbation), landmarks in r,
    the final per-correspondence inlier mask and the RMS reprojection error (px)."""

    T_q_r: np.ndarray
    covariance: np.ndarray
    points_r: np.ndarray
    inlier: np.ndarray
    rms_px: float


def _huber_weights(r2: np.ndarray, k: float) -> np.ndarray:
    """IRLS weights of the Huber kernel for squared normalised residuals r2."""
    r = np.sqrt(r2)
    return np.where(r <= k, 1.0, k / np.maximum(r, 1e-12))


def refine_two_view(T_q_r: np.ndarray, points_r: np.ndarray, z_r: np.ndarray, z_q: np.ndarray,
                    camera: StereoCamera, sigma_px: float, huber_px: float, iterations: int,
                    outlier_px: float) -> RefineResult:
    """Two-view stereo bundle adjustment of T_q_r and the landmarks (reference view held fixed).

    ``z_r``/``z_q`` (N, 3): stereo measurements (u_l, v, u_r) of each landmark in the reference and
    query views, u_r NaN where a view has no right match (only u_l, v count there).
    """
    n = len(points_r)
    z = np.concatenate([z_r, z_q])
    rows = np.isfinite(z).astype(float)
    res = bundle_adjust(np.stack([np.eye(4), T_q_r]), np.array([True, False]), points_r,
                        np.r_[np.zeros(n, int), np.ones(n, int)], np.r_[np.arange(n), np.arange(n)],
                        np.nan_to_num(z), rows, camera, sigma_px, huber_px, iterations)
    e2 = np.maximum(res.error_sq[:n], res.error_sq[n:])
    inlier = e2 <= outlier_px**2
    sq = np.r_[res.error_sq[:n][inlier], res.error_sq[n:][inlier]] / 3
    rms = float(np.sqrt(np.mean(sq))) if inlier.any() else float("nan")
    return RefineResult(res.T_cam_world[1], res.pose_covariance[1], res.points, inlier, rms)


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


RELATIVE_COST_TOLERANCE = 1e-6   # bundle adjustment stops when a step lowers the cost by less than this


def inv_sym3(A: np.ndarray) -> np.ndarray:
    """Inverse of symmetric 3x3 matrices (..., 3, 3) by the adjugate (vectorized, no LAPACK call)."""
    a, b, c = A[..., 0, 0], A[..., 0, 1], A[..., 0, 2]
    d, e, f = A[..., 1, 1], A[..., 1, 2], A[..., 2, 2]
    c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
    c11, c12, c22 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * c00 + b * c01 + c * c02
    out = np.stack([c00, c01, c02, c01, c11, c12, c02, c12, c22], axis=-1).reshape(A.shape)
    return out / det[..., None, None]


def _observation_pairs(obs_point: np.ndarray, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """All ordered pairs (o1, o2) of observations of the same landmark (including o1 == o2)."""
    order = np.argsort(obs_point, kind="stable")
    counts = np.bincount(obs_point, minlength=n_points)
    starts = np.cumsum(counts) - counts
    c_sorted = counts[obs_point[order]]
    o1 = np.repeat(order, c_sorted)
    rank = np.arange(len(o1)) - np.repeat(np.cumsum(c_sorted) - c_sorted, c_sorted)
    return o1, order[starts[obs_point[o1]] + rank]


def segment_sum(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Sum rows of ``values`` (M, ...) into ``n`` bins by ``index`` (M,) -> (n, ...) (fast ``np.add.at``)."""
    tail = values.shape[1:]
    width = int(np.prod(tail)) if tail else 1
    flat = (index[:, None] * width + np.arange(width)[None, :]).ravel()
    out = np.bincount(flat, weights=values.reshape(-1), minlength=n * width)
    return out.reshape((n, *tail))


def _pose_jacobian(Y: np.ndarray, J_Y: np.ndarray) -> np.ndarray:
    """d(measurement)/d(left perturbation [omega, v] of T_cam_world), given Y = T X and dz/dY."""
    dY = np.concatenate([-skew(Y), np.broadcast_to(np.eye(3), Y.shape[:1] + (3, 3))], axis=2)
    return J_Y @ dY


def bundle_adjust(T_cam_world: np.ndarray, fixed: np.ndarray, points: np.ndarray, obs_pose: np.ndarray,
                  obs_point: np.ndarray, z: np.ndarray, row_weight: np.ndarray, camera: StereoCamera,
                  sigma_px: float, huber_px: float, iterations: int, fix_points: bool = False) -> BundleResult:
    """Levenberg-Marquardt bundle adjustment on stereo reprojection errors (u_l, v, u_r).

    ``obs_pose``/``obs_point`` index the pose and landmark of each observation, ``z`` (M, 3) its
    measurement and ``row_weight`` (M, 3) a weight per measured row (0 for a missing right match,
    small for the disparity of a far landmark). Landmarks are eliminated by the Schur complement
    (3x3 blocks), so the solve is over the free poses only; ``fix_points`` refines poses alone.
    """
    T = T_cam_world.copy()
    X = points.copy()
    K, L = len(T), len(X)
    free = np.flatnonzero(~fixed)
    slot = -np.ones(K, int)
    slot[free] = np.arange(len(free))
    info_rows = row_weight / sigma_px**2
    zz = np.where(row_weight > 0, z, 0.0)
    k_huber = huber_px / sigma_px
    if not fix_points:
        o1, o2 = _observation_pairs(obs_point, L)

    def evaluate(T_, X_):
        Y = np.einsum("mij,mj->mi", T_[obs_pose, :3, :3], X_[obs_point]) + T_[obs_pose, :3, 3]
        e = (camera.project(Y) - zz) * (row_weight > 0)
        r2 = (info_rows * e**2).sum(1)
        w = _huber_weights(r2, k_huber)
        return Y, e, r2, w, float(np.sum(w * r2 * (2 - w)))

    Y, e, _, w, cost = evaluate(T, X)
    if not np.all(Y[:, 2] > 0):
        raise ValueError("bundle_adjust: a landmark starts behind its camera")
    lam = 1e-4
    Hpp_blocks = np.zeros((K, 6, 6))
    for _ in range(iterations):
        J_Y = stereo_jacobian(Y, camera)
        J_p = _pose_jacobian(Y, J_Y)                                  # (M, 3, 6)
        J_x = J_Y @ T[obs_pose, :3, :3]                               # (M, 3, 3)
        Wd = (w[:, None] * info_rows)                                 # (M, 3) diagonal weights
        WJp = Wd[:, :, None] * J_p
        WJx = Wd[:, :, None] * J_x
        Hpp_blocks = segment_sum(obs_pose, np.swapaxes(J_p, 1, 2) @ WJp, K)
        bp = -segment_sum(obs_pose, np.einsum("mki,mk->mi", J_p, Wd * e), K)
        if not fix_points:
            Hll = segment_sum(obs_point, np.swapaxes(J_x, 1, 2) @ WJx, L)
            bl = -segment_sum(obs_point, np.einsum("mki,mk->mi", J_x, Wd * e), L)
            Hpl = np.swapaxes(J_p, 1, 2) @ WJx                        # (M, 6, 3)
        improved = converged = False
        for _attempt in range(8):
            F = len(free)
            if fix_points:
                S = np.zeros((F * 6, F * 6))
                g = np.zeros(F * 6)
                for k in free:
                    s = slot[k] * 6
                    S[s:s + 6, s:s + 6] = Hpp_blocks[k]
                    g[s:s + 6] = bp[k]
            else:
                Hll_d = Hll + lam * (np.eye(3) * (np.trace(Hll, axis1=1, axis2=2)[:, None, None] / 3 + 1e-9))
                Hll_inv = inv_sym3(Hll_d)
                A = Hpl @ Hll_inv[obs_point]                          # (M, 6, 3)
                # pairs of observations of the same landmark give the Schur blocks (k_o, k_o')
                S_full = -segment_sum(obs_pose[o1] * K + obs_pose[o2], A[o1] @ np.swapaxes(Hpl[o2], 1, 2),
                                      K * K).reshape(K, K, 6, 6)
                S_full[np.arange(K), np.arange(K)] += Hpp_blocks
                g_full = bp - segment_sum(obs_pose, np.einsum("mij,mj->mi", A, bl[obs_point]), K)
                S = S_full[np.ix_(free, free)].transpose(0, 2, 1, 3).reshape(F * 6, F * 6)
                g = g_full[free].reshape(-1)
            S_d = S + lam * np.diag(np.diag(S) + 1e-9)
            try:
                dp = np.linalg.solve(S_d, g).reshape(F, 6)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            T_new = T.copy()
            for k in free:
                T_new[k] = exp_se3(dp[slot[k]]) @ T[k]
            X_new = X
            if not fix_points:
                dpk = np.zeros((K, 6))
                dpk[free] = dp
                rhs = bl - segment_sum(obs_point, np.einsum("mji,mj->mi", Hpl, dpk[obs_pose]), L)
                X_new = X + np.einsum("lij,lj->li", Hll_inv, rhs)
            Y_n, e_n, _, w_n, cost_n = evaluate(T_new, X_new)
            if np.all(Y_n[:, 2] > 0) and cost_n < cost:
                converged = cost - cost_n < RELATIVE_COST_TOLERANCE * cost
                T, X, Y, e, w, cost = T_new, X_new, Y_n, e_n, w_n, cost_n
                lam = max(lam / 10, 1e-7)
                improved = True
                break
            lam *= 10
        if not improved or converged:
            break
    cov = np.zeros((K, 6, 6))
    if len(free):
        try:
            Sinv = np.linalg.inv(S)
            for k in free:
                s = slot[k] * 6
                cov[k] = Sinv[s:s + 6, s:s + 6]
        except np.linalg.LinAlgError:
            cov[free] = np.nan
    err_sq = ((camera.project(Y) - zz) ** 2 * (row_weight > 0)).sum(1)
    return BundleResult(T, X, err_sq, cov, cost)
