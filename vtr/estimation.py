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

    ``z_r`` (N, 3): stereo measurements (u_l, v, u_r) of each landmark in the reference view;
    ``z_q`` (N, 3): in the query view, with u_r NaN where the query feature has no stereo match
    (then only u_l, v count). Landmarks are eliminated with the Schur complement (3x3 blocks),
    so each iteration costs O(N). Levenberg-Marquardt damping keeps steps safe.
    """
    T = T_q_r.copy()
    X = points_r.copy()
    n = len(X)
    mono_q = ~np.isfinite(z_q[:, 2])
    mono_r = ~np.isfinite(z_r[:, 2])
    zq = np.where(mono_q[:, None], np.c_[z_q[:, :2], np.zeros(n)], z_q)
    zr = np.where(mono_r[:, None], np.c_[z_r[:, :2], np.zeros(n)], z_r)
    w_q_rows = np.ones((n, 3))
    w_q_rows[mono_q, 2] = 0.0
    w_r_rows = np.ones((n, 3))
    w_r_rows[mono_r, 2] = 0.0
    info = 1.0 / sigma_px**2
    k = huber_px / sigma_px
    lam = 1e-4

    def residuals(T_, X_):
        Y = X_ @ T_[:3, :3].T + T_[:3, 3]
        er = (camera.project(X_) - zr) * w_r_rows
        eq = (camera.project(Y) - zq) * w_q_rows
        return Y, er, eq

    def cost(er, eq):
        r2r = (er**2).sum(1) * info
        r2q = (eq**2).sum(1) * info
        wr, wq = _huber_weights(r2r, k), _huber_weights(r2q, k)
        return float(np.sum(wr * r2r * (2 - wr)) + np.sum(wq * r2q * (2 - wq))), wr, wq

    Y, er, eq = residuals(T, X)
    valid = (X[:, 2] > 0) & (Y[:, 2] > 0)
    c0, wr, wq = cost(er[valid], eq[valid])
    S = np.eye(6)
    for _ in range(iterations):
        Xv, Yv = X[valid], Y[valid]
        erv, eqv = er[valid], eq[valid]
        _, wr, wq = cost(erv, eqv)
        R = T[:3, :3]
        Jr_X = stereo_jacobian(Xv, camera) * w_r_rows[valid][:, :, None]                     # (m, 3, 3)
        Jq_Y = stereo_jacobian(Yv, camera) * w_q_rows[valid][:, :, None]
        Jq_X = Jq_Y @ R
        dY_dxi = np.concatenate([-skew(Yv), np.broadcast_to(np.eye(3), Yv.shape[:1] + (3, 3))], axis=2)
        Jq_P = Jq_Y @ dY_dxi                                     # (m, 3, 6)
        Wr = (wr * info)[:, None, None]
        Wq = (wq * info)[:, None, None]
        Hll = (np.swapaxes(Jr_X, 1, 2) @ (Wr * Jr_X)) + (np.swapaxes(Jq_X, 1, 2) @ (Wq * Jq_X))
        Hpl = np.swapaxes(Jq_P, 1, 2) @ (Wq * Jq_X)              # (m, 6, 3)
        Hpp = np.einsum("mki,mkj->ij", Jq_P, Wq * Jq_P)
        bl = -(np.einsum("mki,mk->mi", Jr_X, (wr * info)[:, None] * erv)
               + np.einsum("mki,mk->mi", Jq_X, (wq * info)[:, None] * eqv))
        bp = -np.einsum("mki,mk->i", Jq_P, (wq * info)[:, None] * eqv)
        improved = False
        for _attempt in range(6):
            Hll_d = Hll + lam * np.eye(3) * (1 + np.trace(Hll, axis1=1, axis2=2)[:, None, None] / 3)
            Hll_inv = np.linalg.inv(Hll_d)
            HplHinv = Hpl @ Hll_inv                               # (m, 6, 3)
            S = Hpp - np.einsum("mij,mkj->ik", HplHinv, Hpl)
            g = bp - np.einsum("mij,mj->i", HplHinv, bl)
            S_d = S + lam * np.diag(np.diag(S) + 1e-9)
            dp = np.linalg.solve(S_d, g)
            dl = np.einsum("mij,mj->mi", Hll_inv, bl - np.einsum("mji,j->mi", Hpl, dp))
            T_new = exp_se3(dp) @ T
            X_new = X.copy()
            X_new[valid] += dl
            Y_new, er_new, eq_new = residuals(T_new, X_new)
            ok_new = (X_new[valid, 2] > 0) & (Y_new[valid, 2] > 0)
            c_new = cost(er_new[valid], eq_new[valid])[0] if np.all(ok_new) else np.inf
            if c_new < c0:
                T, X, Y, er, eq, c0 = T_new, X_new, Y_new, er_new, eq_new, c_new
                lam = max(lam / 10, 1e-7)
                improved = True
                break
            lam *= 10
        if not improved or np.linalg.norm(dp) < 1e-10:
            break
    e2 = np.maximum((er**2).sum(1), (eq**2).sum(1))
    inlier = valid & (e2 <= outlier_px**2)
    try:
        cov = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        cov = np.full((6, 6), np.nan)
    sq = np.r_[(er[inlier] ** 2).sum(1), (eq[inlier] ** 2).sum(1)] / 3
    rms = float(np.sqrt(np.mean(sq))) if inlier.any() else float("nan")
    return RefineResult(T, cov, X, inlier, rms)
