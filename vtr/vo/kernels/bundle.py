"""Kernels of the stereo bundle adjustment in ``vtr.vo.estimation.bundle_adjust``.

Observation m sees landmark ``obs_point[m]`` from camera ``obs_pose[m]``; poses are ``T_cam_world``
split into rotations R (K, 3, 3) and translations t (K, 3); residual rows are (u_l, v, u_r) in
pixels. Pose perturbations are on the left, ``xi = [omega, v]``; the landmark Jacobian is with
respect to its world position.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def residuals(R, t, X, obs_pose, obs_point, z, measured, info_rows, k_huber, fx, fy, cx, cy, fb):
    """Camera-frame points Y (M, 3), residuals e (M, 3; 0 on unmeasured rows), Huber weights w (M,),
    the robust cost and the smallest depth of any observation."""
    M = len(obs_pose)
    Y = np.empty((M, 3))
    e = np.empty((M, 3))
    w = np.empty(M)
    cost = 0.0
    min_depth = np.inf
    for m in range(M):
        k = obs_pose[m]
        p = X[obs_point[m]]
        for i in range(3):
            Y[m, i] = R[k, i, 0] * p[0] + R[k, i, 1] * p[1] + R[k, i, 2] * p[2] + t[k, i]
        iz = 1.0 / Y[m, 2]
        u = fx * Y[m, 0] * iz + cx
        e[m, 0] = (u - z[m, 0]) * measured[m, 0]
        e[m, 1] = (fy * Y[m, 1] * iz + cy - z[m, 1]) * measured[m, 1]
        e[m, 2] = (u - fb * iz - z[m, 2]) * measured[m, 2]
        r2 = info_rows[m, 0] * e[m, 0] ** 2 + info_rows[m, 1] * e[m, 1] ** 2 + info_rows[m, 2] * e[m, 2] ** 2
        r = np.sqrt(r2)
        w[m] = 1.0 if r <= k_huber else k_huber / max(r, 1e-12)
        cost += w[m] * r2 * (2.0 - w[m])
        min_depth = min(min_depth, Y[m, 2])
    return Y, e, w, cost, min_depth


@njit(cache=True, nogil=True)
def normal_equations(R, Y, e, w, obs_pose, obs_point, info_rows, n_points, pose_free, fix_points, fx, fy, fb):
    """Gauss-Newton blocks: pose system H (6K, 6K) and b (6K,), landmark blocks Hll (L, 3, 3) and
    bl (L, 3), and the pose-landmark coupling W (M, 6, 3) of each observation (J_pose^T J_point).
    Blocks of poses with ``pose_free`` false stay zero (they are never solved for)."""
    M = len(obs_pose)
    K = len(R)
    H = np.zeros((6 * K, 6 * K))
    b = np.zeros(6 * K)
    Hll = np.zeros((n_points, 3, 3))
    bl = np.zeros((n_points, 3))
    W = np.zeros((M, 6, 3))
    Jy = np.empty((3, 3))
    Jp = np.empty((3, 6))
    Jx = np.empty((3, 3))
    ew = np.empty(3)
    for m in range(M):
        k = obs_pose[m]
        x, y, zc = Y[m, 0], Y[m, 1], Y[m, 2]
        iz = 1.0 / zc
        iz2 = iz * iz
        # d(u_l, v, u_r)/d(Y)
        Jy[0, 0], Jy[0, 1], Jy[0, 2] = fx * iz, 0.0, -fx * x * iz2
        Jy[1, 0], Jy[1, 1], Jy[1, 2] = 0.0, fy * iz, -fy * y * iz2
        Jy[2, 0], Jy[2, 1], Jy[2, 2] = fx * iz, 0.0, -(fx * x - fb) * iz2
        for r in range(3):
            s = np.sqrt(w[m] * info_rows[m, r])
            for c in range(3):
                Jy[r, c] *= s
            ew[r] = e[m, r] * s
            # d/d omega of Exp(xi) Y = -J [Y]x, i.e. the row Y x J_r
            Jp[r, 0] = y * Jy[r, 2] - zc * Jy[r, 1]
            Jp[r, 1] = zc * Jy[r, 0] - x * Jy[r, 2]
            Jp[r, 2] = x * Jy[r, 1] - y * Jy[r, 0]
            Jp[r, 3], Jp[r, 4], Jp[r, 5] = Jy[r, 0], Jy[r, 1], Jy[r, 2]
        free = pose_free[k]
        o = 6 * k
        for i in range(6 if free else 0):
            acc = 0.0
            for r in range(3):
                acc += Jp[r, i] * ew[r]
            b[o + i] -= acc
            for j in range(i, 6):
                acc = 0.0
                for r in range(3):
                    acc += Jp[r, i] * Jp[r, j]
                H[o + i, o + j] += acc
                if j != i:
                    H[o + j, o + i] += acc
        if fix_points:
            continue
        l = obs_point[m]
        for r in range(3):
            for c in range(3):
                Jx[r, c] = Jy[r, 0] * R[k, 0, c] + Jy[r, 1] * R[k, 1, c] + Jy[r, 2] * R[k, 2, c]
        for i in range(3):
            bl[l, i] -= Jx[0, i] * ew[0] + Jx[1, i] * ew[1] + Jx[2, i] * ew[2]
            for j in range(3):
                Hll[l, i, j] += Jx[0, i] * Jx[0, j] + Jx[1, i] * Jx[1, j] + Jx[2, i] * Jx[2, j]
        for i in range(6 if free else 0):
            for j in range(3):
                W[m, i, j] = Jp[0, i] * Jx[0, j] + Jp[1, i] * Jx[1, j] + Jp[2, i] * Jx[2, j]
    return H, b, Hll, bl, W


@njit(cache=True, nogil=True)
def _inv3(A):
    a, b_, c = A[0, 0], A[0, 1], A[0, 2]
    d, e, f = A[1, 1], A[1, 2], A[2, 2]
    c00, c01, c02 = d * f - e * e, c * e - b_ * f, b_ * e - c * d
    c11, c12, c22 = a * f - c * c, b_ * c - a * e, a * d - b_ * b_
    det = a * c00 + b_ * c01 + c * c02
    out = np.empty((3, 3))
    out[0, 0], out[0, 1], out[0, 2] = c00 / det, c01 / det, c02 / det
    out[1, 0], out[1, 1], out[1, 2] = c01 / det, c11 / det, c12 / det
    out[2, 0], out[2, 1], out[2, 2] = c02 / det, c12 / det, c22 / det
    return out


@njit(cache=True, nogil=True)
def schur(H, b, Hll, bl, W, obs_pose, point_start, point_obs, pose_free, damping):
    """Reduced camera system S = H - sum_l W_l Hll_l^-1 W_l^T, g = b - sum_l W_l Hll_l^-1 bl_l, with
    ``damping`` (LM lambda) on the landmark blocks too; returns S, g and the damped Hll^-1 (L, 3, 3).

    ``point_obs[point_start[l]:point_start[l + 1]]`` lists the observations of landmark l; rows and
    columns of fixed poses (``pose_free`` false) are left as in H.
    """
    S = H.copy()
    g = b.copy()
    L = len(Hll)
    Hinv = np.empty((L, 3, 3))
    A = np.empty((3, 3))
    C = np.empty((6, 3))
    for l in range(L):
        scale = damping * ((Hll[l, 0, 0] + Hll[l, 1, 1] + Hll[l, 2, 2]) / 3.0 + 1e-9)
        for i in range(3):
            for j in range(3):
                A[i, j] = Hll[l, i, j] + (scale if i == j else 0.0)
        Ai = _inv3(A)
        Hinv[l] = Ai
        for a in range(point_start[l], point_start[l + 1]):
            ma = point_obs[a]
            if not pose_free[obs_pose[ma]]:
                continue
            ka = 6 * obs_pose[ma]
            for i in range(6):
                for j in range(3):
                    C[i, j] = W[ma, i, 0] * Ai[0, j] + W[ma, i, 1] * Ai[1, j] + W[ma, i, 2] * Ai[2, j]
                g[ka + i] -= C[i, 0] * bl[l, 0] + C[i, 1] * bl[l, 1] + C[i, 2] * bl[l, 2]
            for c in range(point_start[l], point_start[l + 1]):
                mc = point_obs[c]
                if not pose_free[obs_pose[mc]]:
                    continue
                kc = 6 * obs_pose[mc]
                for i in range(6):
                    for j in range(6):
                        S[ka + i, kc + j] -= C[i, 0] * W[mc, j, 0] + C[i, 1] * W[mc, j, 1] + C[i, 2] * W[mc, j, 2]
    return S, g, Hinv


@njit(cache=True, nogil=True)
def back_substitute(X, Hinv, bl, W, obs_pose, point_start, point_obs, dp):
    """Landmark update X + Hll^-1 (bl - sum_obs W^T dp_pose) for a pose step dp (6K,)."""
    X_new = X.copy()
    rhs = np.empty(3)
    for l in range(len(X)):
        for j in range(3):
            rhs[j] = bl[l, j]
        for a in range(point_start[l], point_start[l + 1]):
            m = point_obs[a]
            o = 6 * obs_pose[m]
            for j in range(3):
                acc = 0.0
                for i in range(6):
                    acc += W[m, i, j] * dp[o + i]
                rhs[j] -= acc
        for i in range(3):
            X_new[l, i] += Hinv[l, i, 0] * rhs[0] + Hinv[l, i, 1] * rhs[1] + Hinv[l, i, 2] * rhs[2]
    return X_new
