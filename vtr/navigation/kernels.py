"""Compiled (numba) inner loops of place recognition's queries (:mod:`vtr.navigation.place`: the first pass
over the inverted file and the exact scores of the shortlisted vertices) and of the localization's submap adjustment
(:mod:`vtr.navigation.leaf_adjustment`: its whole Levenberg-Marquardt loop, ``adjust``). Plain arrays in, plain arrays
out; compiled on first use and cached next to this file, as ``vtr.vo.kernels`` are. ``jackknife`` is the covariance
the localization reports (:func:`vtr.navigation.leaf_adjustment.leaf_pose_jackknife`)."""

from __future__ import annotations

import numpy as np
from numba import njit

from ..vo.estimation import MAX_LM_ATTEMPTS, MIN_LM_DAMPING, POSE_STEP_TOLERANCE, RELATIVE_COST_TOLERANCE

#: the first Levenberg-Marquardt damping of the leaf adjustment (bundle_adjust's)
INITIAL_LM_DAMPING = 1e-4
#: added to the diagonal before damping, so a zero row still damps (bundle_adjust's)
DIAGONAL_FLOOR = 1e-9
#: rotation angle (rad) below which the exponential map takes its series
SMALL_ANGLE_RAD = 1e-8
#: a block whose leverage reaches 1 minus this in some direction holds all of that direction's information: the
#: system without it is singular (the jackknife counts no blocks then)
LEVERAGE_MARGIN = 1e-9


@njit(cache=True, nogil=True)
def coarse_scores(indptr, vertex, weight, words, query_weight, n_vertices):
    """Sum over the query's ``words`` (with ``query_weight``) of each vertex's weight in the inverted file
    (``indptr`` (W+1,), ``vertex``, ``weight``): (n_vertices,) float64."""
    acc = np.zeros(n_vertices)
    for k in range(len(words)):
        w = words[k]
        qw = query_weight[k]
        for e in range(indptr[w], indptr[w + 1]):
            acc[vertex[e]] += qw * weight[e]
    return acc


@njit(cache=True, nogil=True)
def row_scores(indptr, word, weight, rows, q):
    """Dot product of CSR rows ``rows`` (``indptr``, ``word``, ``weight``) with the dense vector ``q``."""
    out = np.zeros(len(rows))
    for k in range(len(rows)):
        r = rows[k]
        s = 0.0
        for e in range(indptr[r], indptr[r + 1]):
            s += weight[e] * q[word[e]]
        out[k] = s
    return out


@njit(cache=True, nogil=True, inline="always")
def _observe(R, t, X, i, z, meas, info, m, k_huber, fx, fy, cx, cy, fb, Y, e, wh):
    """Observation m of landmark i from the pose (R, t): camera point Y[m], residual e[m] and Huber weight wh[m];
    returns its robust cost."""
    p0, p1, p2 = X[i, 0], X[i, 1], X[i, 2]
    for a in range(3):
        Y[m, a] = R[a, 0] * p0 + R[a, 1] * p1 + R[a, 2] * p2 + t[a]
    iz = 1.0 / Y[m, 2]
    u = fx * Y[m, 0] * iz + cx
    e[m, 0] = (u - z[m, 0]) * meas[m, 0]
    e[m, 1] = (fy * Y[m, 1] * iz + cy - z[m, 1]) * meas[m, 1]
    e[m, 2] = (u - fb * iz - z[m, 2]) * meas[m, 2]
    r2 = info[m, 0] * e[m, 0] ** 2 + info[m, 1] * e[m, 1] ** 2 + info[m, 2] * e[m, 2] ** 2
    r = np.sqrt(r2)
    w = 1.0 if r <= k_huber else k_huber / max(r, 1e-12)
    wh[m] = w
    return w * r2 * (2.0 - w)


@njit(cache=True, nogil=True)
def _evaluate(Rt, tt, slot, R, t, X, z, meas, info, k_huber, fx, fy, cx, cy, fb, Y, e, wh):
    """Camera points, residuals and Huber weights of every observation (taught views 0..N-1, the leaf's N..2N-1);
    returns (cost, smallest depth), the cost summed in that order."""
    n = len(X)
    cost = 0.0
    min_depth = np.inf
    for m in range(n):
        s = slot[m]
        cost += _observe(Rt[s], tt[s], X, m, z, meas, info, m, k_huber, fx, fy, cx, cy, fb, Y, e, wh)
        min_depth = min(min_depth, Y[m, 2])
    for m in range(n, 2 * n):
        cost += _observe(R, t, X, m - n, z, meas, info, m, k_huber, fx, fy, cx, cy, fb, Y, e, wh)
        min_depth = min(min_depth, Y[m, 2])
    return cost, min_depth


@njit(cache=True, nogil=True, inline="always")
def _jacobians(Rk, Y, e, wh, info, m, fx, fy, fb, Jy, Jp, Jx, ew, pose):
    """Whitened Jacobians of observation m: Jp (3, 6) in the pose (left perturbation [omega, v]), Jx (3, 3) in the
    landmark (Jp only when ``pose``: the taught views are held), and the whitened residual ew (3,) (bundle_adjust's
    normal equations, term for term)."""
    x, y, zc = Y[m, 0], Y[m, 1], Y[m, 2]
    iz = 1.0 / zc
    iz2 = iz * iz
    Jy[0, 0], Jy[0, 1], Jy[0, 2] = fx * iz, 0.0, -fx * x * iz2
    Jy[1, 0], Jy[1, 1], Jy[1, 2] = 0.0, fy * iz, -fy * y * iz2
    Jy[2, 0], Jy[2, 1], Jy[2, 2] = fx * iz, 0.0, -(fx * x - fb) * iz2
    for r in range(3):
        s = np.sqrt(wh[m] * info[m, r])
        for c in range(3):
            Jy[r, c] *= s
        ew[r] = e[m, r] * s
        if not pose:
            continue
        Jp[r, 0] = y * Jy[r, 2] - zc * Jy[r, 1]
        Jp[r, 1] = zc * Jy[r, 0] - x * Jy[r, 2]
        Jp[r, 2] = x * Jy[r, 1] - y * Jy[r, 0]
        Jp[r, 3], Jp[r, 4], Jp[r, 5] = Jy[r, 0], Jy[r, 1], Jy[r, 2]
    for r in range(3):
        for c in range(3):
            Jx[r, c] = Jy[r, 0] * Rk[0, c] + Jy[r, 1] * Rk[1, c] + Jy[r, 2] * Rk[2, c]


@njit(cache=True, nogil=True)
def _normal_equations(Rt, slot, R, Y, e, wh, info, fx, fy, fb, H, b, Hll, bl, W):
    """The leaf's pose block H (6, 6) and b (6,), landmark blocks Hll (N, 3, 3) and bl (N, 3) and the leaf's
    coupling W (N, 6, 3), accumulated in bundle_adjust's order (the taught views, then the leaf's)."""
    n = len(Hll)
    H[:] = 0.0
    b[:] = 0.0
    Hll[:] = 0.0
    bl[:] = 0.0
    Jy = np.empty((3, 3))
    Jp = np.empty((3, 6))
    Jx = np.empty((3, 3))
    ew = np.empty(3)
    for m in range(2 * n):
        leaf = m >= n
        i = m - n if leaf else m
        _jacobians(R if leaf else Rt[slot[i]], Y, e, wh, info, m, fx, fy, fb, Jy, Jp, Jx, ew, leaf)
        if leaf:
            for a in range(6):
                acc = 0.0
                for r in range(3):
                    acc += Jp[r, a] * ew[r]
                b[a] -= acc
                for c in range(a, 6):
                    acc = 0.0
                    for r in range(3):
                        acc += Jp[r, a] * Jp[r, c]
                    H[a, c] += acc
                    if c != a:
                        H[c, a] += acc
        for a in range(3):
            bl[i, a] -= Jx[0, a] * ew[0] + Jx[1, a] * ew[1] + Jx[2, a] * ew[2]
            for c in range(a, 3):
                Hll[i, a, c] += Jx[0, a] * Jx[0, c] + Jx[1, a] * Jx[1, c] + Jx[2, a] * Jx[2, c]
                if c != a:
                    Hll[i, c, a] = Hll[i, a, c]
        if leaf:
            for a in range(6):
                for c in range(3):
                    W[i, a, c] = Jp[0, a] * Jx[0, c] + Jp[1, a] * Jx[1, c] + Jp[2, a] * Jx[2, c]


@njit(cache=True, nogil=True)
def _inv3(A, out, i):
    a, b_, c = A[0, 0], A[0, 1], A[0, 2]
    d, e, f = A[1, 1], A[1, 2], A[2, 2]
    c00, c01, c02 = d * f - e * e, c * e - b_ * f, b_ * e - c * d
    c11, c12, c22 = a * f - c * c, b_ * c - a * e, a * d - b_ * b_
    det = a * c00 + b_ * c01 + c * c02
    out[i, 0, 0], out[i, 0, 1], out[i, 0, 2] = c00 / det, c01 / det, c02 / det
    out[i, 1, 0], out[i, 1, 1], out[i, 1, 2] = c01 / det, c11 / det, c12 / det
    out[i, 2, 0], out[i, 2, 1], out[i, 2, 2] = c02 / det, c12 / det, c22 / det


@njit(cache=True, nogil=True)
def _schur(H, b, Hll, bl, W, damping, S, g, Hinv):
    """The reduced system of the leaf pose, S = H - sum W Hll^-1 W^T and g = b - sum W Hll^-1 bl, with the damping on
    the landmark blocks too (bundle_adjust's); the damped Hll^-1 into Hinv."""
    S[:] = H
    g[:] = b
    A = np.empty((3, 3))
    C = np.empty((6, 3))
    for i in range(len(Hll)):
        scale = damping * ((Hll[i, 0, 0] + Hll[i, 1, 1] + Hll[i, 2, 2]) / 3.0 + 1e-9)
        for a in range(3):
            for c in range(3):
                A[a, c] = Hll[i, a, c] + (scale if a == c else 0.0)
        _inv3(A, Hinv, i)
        for a in range(6):
            for c in range(3):
                C[a, c] = W[i, a, 0] * Hinv[i, 0, c] + W[i, a, 1] * Hinv[i, 1, c] + W[i, a, 2] * Hinv[i, 2, c]
            g[a] -= C[a, 0] * bl[i, 0] + C[a, 1] * bl[i, 1] + C[a, 2] * bl[i, 2]
        for a in range(6):
            for c in range(a, 6):
                S[a, c] -= C[a, 0] * W[i, c, 0] + C[a, 1] * W[i, c, 1] + C[a, 2] * W[i, c, 2]
    for a in range(6):
        for c in range(a + 1, 6):
            S[c, a] = S[a, c]


@njit(cache=True, nogil=True)
def _lu_solve(A, rhs, out):
    """Solve A x = rhs (6x6, partial pivoting) into ``out``; False when A is singular (a zero pivot)."""
    n = len(A)
    M = A.copy()
    x = rhs.copy()
    for k in range(n):
        p = k
        for r in range(k + 1, n):
            if abs(M[r, k]) > abs(M[p, k]):
                p = r
        if M[p, k] == 0.0:
            return False
        if p != k:
            for c in range(n):
                M[k, c], M[p, c] = M[p, c], M[k, c]
            x[k], x[p] = x[p], x[k]
        for r in range(k + 1, n):
            f = M[r, k] / M[k, k]
            for c in range(k, n):
                M[r, c] -= f * M[k, c]
            x[r] -= f * x[k]
    for k in range(n - 1, -1, -1):
        acc = x[k]
        for c in range(k + 1, n):
            acc -= M[k, c] * out[c]
        out[k] = acc / M[k, k]
    return True


@njit(cache=True, nogil=True)
def _exp_se3(xi, T):
    """Exp([omega, v]) @ T (left perturbation; GTSAM's Pose3.Expmap)."""
    wx, wy, wz = xi[0], xi[1], xi[2]
    v = xi[3:6]
    th2 = wx * wx + wy * wy + wz * wz
    K = np.array([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]])
    K2 = K @ K
    E = np.eye(4)
    if th2 > SMALL_ANGLE_RAD**2:
        th = np.sqrt(th2)
        a, c = np.sin(th) / th, (1.0 - np.cos(th)) / th2
        R = np.eye(3) + a * K + c * K2
        wv = K @ v  # omega x v
        tr = (wv - R @ wv + np.array([wx, wy, wz]) * (wx * v[0] + wy * v[1] + wz * v[2])) / th2
    else:
        R = np.eye(3) + K + 0.5 * K2
        tr = v + 0.5 * (K @ v)
    E[:3, :3] = R
    E[:3, 3] = tr
    return E @ T


@njit(cache=True, nogil=True)
def adjust(Rt, tt, slot, T0, X0, z, meas, info, k_huber, fx, fy, cx, cy, fb, iterations):
    """Levenberg-Marquardt of one free pose T0 (4, 4) and N free landmarks X0, landmark i seen by the held pose
    (Rt[slot[i]], tt[slot[i]]) (observation i) and by the free one (observation N + i); measurements z (2N, 3),
    ``meas`` 1/0 per measured row, ``info`` the rows' information (px^-2). Returns (T, X, squared reprojection
    errors (2N,), the pose's covariance (6, 6), cost, False when a landmark starts behind a camera)."""
    n = len(X0)
    T = T0.copy()
    X = X0.copy()
    Y = np.empty((2 * n, 3))
    e = np.empty((2 * n, 3))
    wh = np.empty(2 * n)
    Yn, en, whn = np.empty((2 * n, 3)), np.empty((2 * n, 3)), np.empty(2 * n)
    cost, min_depth = _evaluate(
        Rt, tt, slot, T[:3, :3].copy(), T[:3, 3].copy(), X, z, meas, info, k_huber, fx, fy, cx, cy, fb, Y, e, wh
    )
    cov = np.full((6, 6), np.nan)
    err_sq = np.zeros(2 * n)
    if not min_depth > 0:
        return T, X, err_sq, cov, cost, False
    H, b = np.empty((6, 6)), np.empty(6)
    Hll, bl, W = np.empty((n, 3, 3)), np.empty((n, 3)), np.empty((n, 6, 3))
    S, g, Hinv = np.eye(6), np.empty(6), np.empty((n, 3, 3))
    dp = np.empty(6)
    lam = INITIAL_LM_DAMPING
    for _ in range(iterations):
        _normal_equations(Rt, slot, T[:3, :3].copy(), Y, e, wh, info, fx, fy, fb, H, b, Hll, bl, W)
        improved = converged = False
        for _attempt in range(MAX_LM_ATTEMPTS):
            _schur(H, b, Hll, bl, W, lam, S, g, Hinv)
            A = S.copy()
            for k in range(6):
                A[k, k] += lam * (S[k, k] + DIAGONAL_FLOOR)
            if not _lu_solve(A, g, dp):
                lam *= 10
                continue
            T_new = _exp_se3(dp, T)
            X_new = X.copy()
            rhs = np.empty(3)
            for i in range(n):
                for c in range(3):
                    acc = 0.0
                    for a in range(6):
                        acc += W[i, a, c] * dp[a]
                    rhs[c] = bl[i, c] - acc
                for a in range(3):
                    X_new[i, a] += Hinv[i, a, 0] * rhs[0] + Hinv[i, a, 1] * rhs[1] + Hinv[i, a, 2] * rhs[2]
            cost_n, depth_n = _evaluate(
                Rt,
                tt,
                slot,
                T_new[:3, :3].copy(),
                T_new[:3, 3].copy(),
                X_new,
                z,
                meas,
                info,
                k_huber,
                fx,
                fy,
                cx,
                cy,
                fb,
                Yn,
                en,
                whn,
            )
            if depth_n > 0 and cost_n < cost:
                step = 0.0
                for k in range(6):
                    step = max(step, abs(dp[k]))
                converged = cost - cost_n < RELATIVE_COST_TOLERANCE * cost or step < POSE_STEP_TOLERANCE
                T, X, cost = T_new, X_new, cost_n
                Y, Yn = Yn, Y
                e, en = en, e
                wh, whn = whn, wh
                lam = max(lam / 10, MIN_LM_DAMPING)
                improved = True
                break
            lam *= 10
        if not improved or converged:
            break
    unit = np.eye(6)
    col = np.empty(6)
    for k in range(6):
        if not _lu_solve(S, unit[k], col):
            cov[:] = np.nan
            break
        cov[:, k] = col
    for m in range(2 * n):  # e: the residuals at (T, X), unmeasured rows zeroed (_observe)
        err_sq[m] = e[m, 0] * e[m, 0] + e[m, 1] * e[m, 1] + e[m, 2] * e[m, 2]
    return T, X, err_sq, cov, cost, True


@njit(cache=True, nogil=True)
def jackknife(Rt, tt, slot, T_leaf, X, z, meas, info, k_huber, fx, fy, cx, cy, fb, cell, n_cells, damping):
    """The delete-one-block jackknife of the leaf pose (vtr.navigation.leaf_adjustment.leaf_pose_jackknife) at the
    leaf adjustment's solution, with its inputs (``adjust``'s: observations, their weights and the Huber weights
    linearized as there, by ``_evaluate`` and ``_jacobians``): per landmark i its share of the reduced leaf system
    and gradient, summed per ``cell[i]`` (< n_cells); each block's step with that block left out. Returns the
    covariance (6x6) and the number of non-empty blocks (0 when a system without a block is singular)."""
    n = len(X)
    R, t = T_leaf[:3, :3], T_leaf[:3, 3]
    Y, e, wh = np.empty((2 * n, 3)), np.empty((2 * n, 3)), np.empty(2 * n)
    _evaluate(Rt, tt, slot, R, t, X, z, meas, info, k_huber, fx, fy, cx, cy, fb, Y, e, wh)
    Sb, gb = np.zeros((n_cells, 6, 6)), np.zeros((n_cells, 6))
    used = np.zeros(n_cells, np.bool_)
    Jy, Jp, Jxt, Jxl = np.empty((3, 3)), np.empty((3, 6)), np.empty((3, 3)), np.empty((3, 3))
    et, el = np.empty(3), np.empty(3)
    A, Hinv, W, C = np.empty((3, 3)), np.empty((1, 3, 3)), np.empty((6, 3)), np.empty((3, 6))
    bl = np.empty(3)
    for i in range(n):
        _jacobians(Rt[slot[i]], Y, e, wh, info, i, fx, fy, fb, Jy, Jp, Jxt, et, False)  # the taught view
        _jacobians(R, Y, e, wh, info, n + i, fx, fy, fb, Jy, Jp, Jxl, el, True)  # the leaf's
        for a in range(3):
            for c in range(3):
                A[a, c] = (
                    Jxt[0, a] * Jxt[0, c]
                    + Jxt[1, a] * Jxt[1, c]
                    + Jxt[2, a] * Jxt[2, c]
                    + Jxl[0, a] * Jxl[0, c]
                    + Jxl[1, a] * Jxl[1, c]
                    + Jxl[2, a] * Jxl[2, c]
                )
            bl[a] = -(Jxt[0, a] * et[0] + Jxt[1, a] * et[1] + Jxt[2, a] * et[2])
            bl[a] -= Jxl[0, a] * el[0] + Jxl[1, a] * el[1] + Jxl[2, a] * el[2]
        scale = damping * ((A[0, 0] + A[1, 1] + A[2, 2]) / 3.0 + 1e-9)
        for a in range(3):
            A[a, a] += scale
        _inv3(A, Hinv, 0)
        for a in range(6):
            for c in range(3):
                W[a, c] = Jp[0, a] * Jxl[0, c] + Jp[1, a] * Jxl[1, c] + Jp[2, a] * Jxl[2, c]
        for a in range(3):
            for c in range(6):
                C[a, c] = Hinv[0, a, 0] * W[c, 0] + Hinv[0, a, 1] * W[c, 1] + Hinv[0, a, 2] * W[c, 2]
        k = cell[i]
        used[k] = True
        for a in range(6):
            ga = -(Jp[0, a] * el[0] + Jp[1, a] * el[1] + Jp[2, a] * el[2])
            gb[k, a] += ga - (C[0, a] * bl[0] + C[1, a] * bl[1] + C[2, a] * bl[2])
            for c in range(6):
                h = Jp[0, a] * Jp[0, c] + Jp[1, a] * Jp[1, c] + Jp[2, a] * Jp[2, c]
                Sb[k, a, c] += h - (W[a, 0] * C[0, c] + W[a, 1] * C[1, c] + W[a, 2] * C[2, c])
    S = np.zeros((6, 6))
    for k in range(n_cells):
        if used[k]:
            S += Sb[k]
    # CR2 (Bell & McCaffrey's bias-reduced cluster-robust sandwich): u_b = S^-1/2 (I - M_b)^-1/2 S^-1/2 g_b with
    # M_b = S^-1/2 S_b S^-1/2 the block's leverage; the plain delete-one-block step, (S - S_b)^-1 g_b =
    # S^-1/2 (I - M_b)^-1 S^-1/2 g_b, over-corrects it (CR3: the jackknife's known upward bias)
    lam, V = np.linalg.eigh(S)
    if lam[0] <= 0.0:
        return np.zeros((6, 6)), 0
    S_ih = (V / np.sqrt(lam)) @ V.T
    cov = np.zeros((6, 6))
    n_blocks = 0
    for k in range(n_cells):
        if not used[k]:
            continue
        M = S_ih @ Sb[k] @ S_ih
        mu, U = np.linalg.eigh(0.5 * (M + M.T))
        if mu[5] >= 1.0 - LEVERAGE_MARGIN:  # without block k nothing fixes some direction of the pose
            return np.zeros((6, 6)), 0
        y = U.T @ (S_ih @ gb[k])
        for a in range(6):
            y[a] /= np.sqrt(1.0 - max(mu[a], 0.0))
        u = S_ih @ (U @ y)
        for a in range(6):
            for c in range(6):
                cov[a, c] += u[a] * u[c]
        n_blocks += 1
    return cov, n_blocks


def warm_up() -> None:
    """Compile the leaf adjustment (``adjust``, ~15 s) and its jackknife on tiny inputs of the dtypes they are called
    with, so later processes load them from the cache (``.ci/setup`` runs this after ``python3 -m vtr.vo.kernels``;
    the place kernels are small and compile on first use)."""
    z, ones = np.array([[100.0, 100.0, 90.0], [100.0, 100.0, 90.0]]), np.ones((2, 3))
    cam = (500.0, 500.0, 100.0, 100.0, 50.0)
    R, t, X = np.eye(3)[None].copy(), np.zeros((1, 3)), np.array([[0.0, 0.0, 5.0]])
    slot = np.zeros(1, np.int64)
    adjust(R, t, slot, np.eye(4), X, z, ones, ones, 1.5, *cam, 3)
    jackknife(R, t, slot, np.eye(4), X, z, ones, ones, 1.5, *cam, slot, 1, 1e-7)
