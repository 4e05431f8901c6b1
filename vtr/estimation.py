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
from .geometry import exp_se3


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
    """Refined ``T_q_r``, its 6x6 covariance ([rot, trans], left perturbation), landmarks in r and
    the final per-correspondence inlier mask."""

    T_q_r: np.ndarray
    covariance: np.ndarray
    points_r: np.ndarray
    inlier: np.ndarray


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
    return RefineResult(res.T_cam_world[1], res.pose_covariance[1], res.points, inlier)


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
MAX_LM_ATTEMPTS = 8              # damping increases per iteration before giving up
MIN_LM_DAMPING = 1e-7


def inv_sym3(A: np.ndarray) -> np.ndarray:
    """Inverse of symmetric 3x3 matrices (..., 3, 3) by the adjugate (vectorized, no LAPACK call)."""
    a, b, c = A[..., 0, 0], A[..., 0, 1], A[..., 0, 2]
    d, e, f = A[..., 1, 1], A[..., 1, 2], A[..., 2, 2]
    c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
    c11, c12, c22 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * c00 + b * c01 + c * c02
    out = np.stack([c00, c01, c02, c01, c11, c12, c02, c12, c22], axis=-1).reshape(A.shape)
    return out / det[..., None, None]


def segment_sum(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Sum rows of ``values`` (M, ...) into ``n`` bins by ``index`` (M,) -> (n, ...) (fast ``np.add.at``)."""
    tail = values.shape[1:]
    width = int(np.prod(tail)) if tail else 1
    flat = (index[:, None] * width + np.arange(width)[None, :]).ravel()
    out = np.bincount(flat, weights=values.reshape(-1), minlength=n * width)
    return out.reshape((n, *tail))


def _cross_rows(y: np.ndarray, J: np.ndarray) -> np.ndarray:
    """Row-wise cross products ``y x J[:, r]`` for y (M, 3) and J (M, R, 3) -> (M, R, 3)."""
    y0, y1, y2 = y[:, None, 0], y[:, None, 1], y[:, None, 2]
    j0, j1, j2 = J[:, :, 0], J[:, :, 1], J[:, :, 2]
    return np.stack([y1 * j2 - y2 * j1, y2 * j0 - y0 * j2, y0 * j1 - y1 * j0], axis=-1)


def bundle_adjust(T_cam_world: np.ndarray, fixed: np.ndarray, points: np.ndarray, obs_pose: np.ndarray,
                  obs_point: np.ndarray, z: np.ndarray, row_weight: np.ndarray, camera: StereoCamera,
                  sigma_px: float, huber_px: float, iterations: int, fix_points: bool = False) -> BundleResult:
    """Levenberg-Marquardt bundle adjustment on stereo reprojection errors (u_l, v, u_r).

    ``obs_pose``/``obs_point`` index the pose and landmark of each observation (a landmark is seen at
    most once per pose), ``z`` (M, 3) its measurement and ``row_weight`` (M, 3) a weight per measured
    row (0 for a missing right match, small for the disparity of a far landmark). Landmarks are
    eliminated by the Schur complement (3x3 blocks): the reduced camera system is one dense GEMM over
    a landmark-by-pose coupling array, so the solve is over the free poses only; ``fix_points``
    refines poses alone. Poses are perturbed on the left, ``T <- Exp(xi) T`` with ``xi = [omega, v]``.
    """
    T = T_cam_world.copy()
    X = points.copy()
    K, L = len(T), len(X)
    free = np.flatnonzero(~fixed)
    free_rows = (free[:, None] * 6 + np.arange(6)).ravel()
    info_rows = row_weight / sigma_px**2
    measured = row_weight > 0
    zz = np.where(measured, z, 0.0)
    k_huber = huber_px / sigma_px
    by_pose = [np.flatnonzero(obs_pose == k) for k in range(K)]

    def evaluate(T_, X_):
        Y = np.empty((len(obs_pose), 3))
        for k, sel in enumerate(by_pose):       # one GEMM per pose instead of M tiny products
            Y[sel] = X_[obs_point[sel]] @ T_[k, :3, :3].T + T_[k, :3, 3]
        e = (camera.project(Y) - zz) * measured
        r2 = (info_rows * e**2).sum(1)
        w = _huber_weights(r2, k_huber)
        return Y, e, w, float(np.sum(w * r2 * (2 - w)))

    Y, e, w, cost = evaluate(T, X)
    if not np.all(Y[:, 2] > 0):
        raise ValueError("bundle_adjust: a landmark starts behind its camera")
    lam = 1e-4
    S = np.eye(6 * K)
    for _ in range(iterations):
        J_Y = stereo_jacobian(Y, camera)                               # (M, 3, 3)
        sw = np.sqrt(w[:, None] * info_rows)                          # (M, 3) square-root weights
        Jy_w = J_Y * sw[:, :, None]
        Jp_w = np.empty((len(Y), 3, 6))
        Jp_w[:, :, :3] = _cross_rows(Y, Jy_w)                          # d/d omega of Exp(xi) Y = -J_Y [Y]x
        Jp_w[:, :, 3:] = Jy_w
        e_w = e * sw
        H = np.zeros((6 * K, 6 * K))
        b = np.zeros(6 * K)
        for k, sel in enumerate(by_pose):
            A = Jp_w[sel].reshape(-1, 6)
            H[6 * k:6 * k + 6, 6 * k:6 * k + 6] = A.T @ A
            b[6 * k:6 * k + 6] = -A.T @ e_w[sel].reshape(-1)
        if not fix_points:
            Jx_w = np.empty_like(Jy_w)
            for k, sel in enumerate(by_pose):
                Jx_w[sel] = (Jy_w[sel].reshape(-1, 3) @ T[k, :3, :3]).reshape(-1, 3, 3)
            Hll = segment_sum(obs_point, np.swapaxes(Jx_w, 1, 2) @ Jx_w, L)
            bl = -segment_sum(obs_point, np.einsum("mra,mr->ma", Jx_w, e_w), L)
            # pose-landmark coupling blocks, laid out (pose row, landmark, 3) so that the reduced
            # camera system below is one contiguous GEMM
            B = np.zeros((K, 6, L, 3))
            B[obs_pose, :, obs_point, :] = np.swapaxes(Jp_w, 1, 2) @ Jx_w
            B = B.reshape(6 * K, L, 3)
        improved = converged = False
        for _attempt in range(MAX_LM_ATTEMPTS):
            if fix_points:
                S, g = H, b
            else:
                # damping on the landmark blocks too: far landmarks seen along one ray are ill-conditioned
                Hll_inv = inv_sym3(Hll + lam * np.eye(3) * (np.trace(Hll, axis1=1, axis2=2)[:, None, None] / 3
                                                             + 1e-9))
                C = sum(B[:, :, a, None] * Hll_inv[None, :, a, :] for a in range(3)).reshape(6 * K, 3 * L)
                S = H - C @ B.reshape(6 * K, 3 * L).T
                g = b - C @ bl.reshape(-1)
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
                T_new[k] = exp_se3(dpk[6 * k:6 * k + 6]) @ T[k]
            X_new = X
            if not fix_points:
                rhs = bl - (dpk @ B.reshape(6 * K, 3 * L)).reshape(L, 3)
                X_new = X + np.einsum("lab,lb->la", Hll_inv, rhs)
            Y_n, e_n, w_n, cost_n = evaluate(T_new, X_new)
            if np.all(Y_n[:, 2] > 0) and cost_n < cost:
                converged = cost - cost_n < RELATIVE_COST_TOLERANCE * cost
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
                cov[k] = Sinv[6 * j:6 * j + 6, 6 * j:6 * j + 6]
        except np.linalg.LinAlgError:
            cov[free] = np.nan
    err_sq = ((camera.project(Y) - zz) ** 2 * measured).sum(1)
    return BundleResult(T, X, err_sq, cov, cost)
