"""The localization's jackknife covariance kernel (vtr.navigation.leaf_adjustment.leaf_pose_jackknife) against the
vectorized numpy form it replaced, kept here as the oracle: the same covariance and block count to rounding on noisy
problems with outliers (Huber), missing and down-weighted disparity rows, few and many blocks, and at the solution of
the leaf adjustment on them."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vtr.camera import StereoCamera
from vtr.geometry import exp_se3, inv_T, log_se3
from vtr.navigation.leaf_adjustment import adjust_leaf, leaf_pose_jackknife
from vtr.vo.estimation import MIN_LM_DAMPING

CAMERA = StereoCamera(fx=718.856, fy=718.856, cx=607.19, cy=185.22, baseline=0.537, width=1226, height=370)

POSE_DIM = 6


def _stereo_jacobians(Y: np.ndarray, camera: StereoCamera) -> np.ndarray:
    """d(u_l, v, u_r)/d(Y) (N, 3, 3) at camera-frame points Y (N, 3)."""
    x, y, z = Y[:, 0], Y[:, 1], Y[:, 2]
    iz = 1.0 / z
    J = np.zeros((len(Y), 3, 3))
    J[:, 0, 0] = J[:, 2, 0] = camera.fx * iz
    J[:, 1, 1] = camera.fy * iz
    J[:, 0, 2] = -camera.fx * x * iz * iz
    J[:, 1, 2] = -camera.fy * y * iz * iz
    J[:, 2, 2] = -(camera.fx * x - camera.fb) * iz * iz
    return J


def _skews(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices (N, 3, 3) of vectors v (N, 3)."""
    K = np.zeros((len(v), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    return K - np.transpose(K, (0, 2, 1))


def _whitened(
    Y: np.ndarray, z: np.ndarray, w: np.ndarray, camera: StereoCamera, sigma_px: float, huber_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per observation of camera-frame points Y (N, 3) at z (N, 3) with row weights w (N, 3): d(whitened
    residual)/d(Y) (N, 3, 3) and the whitened residuals (N, 3), Huber-weighted as
    :func:`vtr.vo.estimation.bundle_adjust` weighs them."""
    info = w / sigma_px**2
    measured = w > 0
    e = np.where(measured, camera.project(Y) - np.where(measured, z, 0.0), 0.0)
    r = np.sqrt(np.sum(info * e**2, axis=1))
    k = huber_px / sigma_px
    huber = np.where(r <= k, 1.0, k / np.maximum(r, 1e-12))
    s = np.sqrt(huber[:, None] * info)
    return _stereo_jacobians(Y, camera) * s[:, :, None], e * s


def _reference_blocks(
    T_leaf: np.ndarray,
    T_taught: np.ndarray,
    points: np.ndarray,
    z_taught: np.ndarray,
    w_taught: np.ndarray,
    z_leaf: np.ndarray,
    w_leaf: np.ndarray,
    block: np.ndarray,
    camera: StereoCamera,
    sigma_px: float,
    huber_px: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Per block, its share of the reduced system of the free pose ``T_leaf`` ([rot, trans], left perturbation as the
    adjustment's) and of its gradient ((B, 6, 6) and (B, 6), blocks in label order)
    of an adjustment where each landmark (``points`` (N, 3) at the solution) is seen once from a held pose
    (``T_taught`` (N, 4, 4), the pose of its observer) and once from the leaf, with measurements and row weights as
    the adjustment had them, the landmarks free. ``block`` (N,) labels each landmark's block."""
    R_t = T_taught[:, :3, :3]
    Y_t = np.einsum("nij,nj->ni", R_t, points) + T_taught[:, :3, 3]
    Y_l = points @ T_leaf[:3, :3].T + T_leaf[:3, 3]
    Jyt, et = _whitened(Y_t, z_taught, w_taught, camera, sigma_px, huber_px)
    Jyl, el = _whitened(Y_l, z_leaf, w_leaf, camera, sigma_px, huber_px)
    Jxt = Jyt @ R_t  # d/d(point) of the taught observation
    Jxl = Jyl @ T_leaf[:3, :3]
    Jp = np.concatenate([-Jyl @ _skews(Y_l), Jyl], axis=2)  # (N, 3, 6): d/d(leaf pose), left perturbation
    Hll = np.einsum("nri,nrj->nij", Jxt, Jxt) + np.einsum("nri,nrj->nij", Jxl, Jxl)
    Wl = np.einsum("nri,nrj->nij", Jp, Jxl)  # (N, 6, 3)
    Hpp = np.einsum("nri,nrj->nij", Jp, Jp)
    bp = -np.einsum("nri,nr->ni", Jp, el)
    bl = -(np.einsum("nri,nr->ni", Jxt, et) + np.einsum("nri,nr->ni", Jxl, el))
    # the adjustment's smallest damping on the landmark blocks: a far landmark seen along one ray is ill-conditioned
    Hll = Hll + MIN_LM_DAMPING * (np.trace(Hll, axis1=1, axis2=2) / 3 + 1e-9)[:, None, None] * np.eye(3)
    C = np.linalg.solve(Hll, np.transpose(Wl, (0, 2, 1)))  # Hll^-1 W' (N, 3, 6)
    S_l = Hpp - Wl @ C  # each landmark's share of the reduced (leaf) system
    g_l = bp - np.einsum("nji,nj->ni", C, bl)
    labels, which = np.unique(np.asarray(block), return_inverse=True)
    B = len(labels)
    S_b = np.zeros((B, POSE_DIM, POSE_DIM))
    g_b = np.zeros((B, POSE_DIM))
    np.add.at(S_b, which, S_l)
    np.add.at(g_b, which, g_l)
    return S_b, g_b


def _reference_jackknife(*args, **kwargs) -> tuple[np.ndarray, int]:
    """:func:`_reference_blocks`' problem; returns the covariance and the number of non-empty blocks ``B``:
    ``sum_b u_b u_b'``, ``u_b = S^-1/2 (I - M_b)^-1/2 S^-1/2 g_b`` (CR2), ``S_b`` and ``g_b`` block b's share of the
    reduced system and gradient, ``S`` their sum, ``M_b = S^-1/2 S_b S^-1/2``."""
    S_b, g_b = _reference_blocks(*args, **kwargs)
    B = len(S_b)
    lam, V = np.linalg.eigh(S_b.sum(axis=0))
    S_ih = (V / np.sqrt(lam)) @ V.T  # S^-1/2
    mu, U = np.linalg.eigh(S_ih @ S_b @ S_ih)  # each block's leverage in the pose
    if mu.max() >= 1 - 1e-9:
        raise np.linalg.LinAlgError("a block holds all of some direction's information")
    F = np.einsum("bij,bj,bkj->bik", U, 1 / np.sqrt(1 - mu), U)  # (I - M_b)^-1/2
    u = np.einsum("ij,bjk,kl,bl->bi", S_ih, F, S_ih, g_b)
    return u.T @ u, B


def _problem(seed: int, n: int, cells: int):
    """Landmarks 3-60 m ahead seen from one of three taught poses and from a leaf near them, noisy stereo
    measurements with outliers on the leaf's side, some right rows missing, far disparities down-weighted, and each
    landmark's block the cell of its leaf pixel on a cells x cells grid."""
    rng = np.random.default_rng(seed)
    T_vertex = np.stack([np.eye(4) for _ in range(3)])
    for s in range(3):
        T_vertex[s, 2, 3] = -0.4 * (s - 1)
    T_leaf = exp_se3(np.r_[rng.normal(0, 0.02, 3), rng.normal(0, 0.3, 3)])
    depth = rng.uniform(3.0, 60.0, n)
    X = np.column_stack([rng.uniform(-0.5, 0.5, n) * depth, rng.uniform(-0.15, 0.15, n) * depth, depth])
    slot = rng.integers(0, 3, n)
    T_taught = T_vertex[slot]
    Y_t = np.einsum("nij,nj->ni", T_taught[:, :3, :3], X) + T_taught[:, :3, 3]
    z_t = CAMERA.project(Y_t) + rng.normal(0, 0.4, (n, 3))
    z_l = CAMERA.project(X @ T_leaf[:3, :3].T + T_leaf[:3, 3]) + rng.normal(0, 0.4, (n, 3))
    bad = rng.random(n) < 0.1
    z_l[bad] += rng.normal(0, 8.0, (int(bad.sum()), 3))
    w_t, w_l = np.ones((n, 3)), np.ones((n, 3))
    w_l[rng.random(n) < 0.1, 2] = 0.0
    w_t[depth > 40, 2] = 1e-4
    w_l[depth > 40, 2] = 1e-4
    uv = np.clip(z_l[:, :2] / [CAMERA.width, CAMERA.height], 0, 0.999)
    block = (uv * cells).astype(int) @ np.array([cells, 1])
    return T_vertex, slot, T_leaf, X, z_t, w_t, z_l, w_l, block


def _kernel(T_vertex, slot, T_leaf, X, z_t, w_t, z_l, w_l, block, sigma=0.5, huber=1.5):
    """leaf_pose_jackknife on adjust_leaf's layout (the taught rows, then the leaf's)."""
    z, w = np.concatenate([z_t, z_l]), np.concatenate([w_t, w_l])
    return leaf_pose_jackknife(T_vertex, slot, T_leaf, X, z, w, block, CAMERA, sigma, huber)


def _both(T_vertex, slot, T_leaf, X, z_t, w_t, z_l, w_l, block, sigma=0.5, huber=1.5):
    ref = _reference_jackknife(
        T_leaf,
        T_vertex[slot],
        X,
        np.where(w_t > 0, z_t, 0.0),
        w_t,
        np.where(w_l > 0, z_l, 0.0),
        w_l,
        block,
        CAMERA,
        sigma,
        huber,
    )
    return _kernel(T_vertex, slot, T_leaf, X, z_t, w_t, z_l, w_l, block, sigma, huber), ref


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(20, 400), cells=st.integers(2, 8))
def test_the_kernel_gives_the_reference_jackknife(seed, n, cells):
    T_vertex, slot, T_leaf, X, z_t, w_t, z_l, w_l, block = _problem(seed, n, cells)
    (cov, b), (ref, b_ref) = _both(T_vertex, slot, T_leaf, X, z_t, w_t, z_l, w_l, block)
    assert b == b_ref == len(np.unique(block))
    np.testing.assert_allclose(cov, ref, rtol=1e-8, atol=1e-12 * np.abs(ref).max())


def test_at_the_leaf_adjustment_s_solution_as_the_localization_calls_it():
    T_vertex, slot, T_leaf, X, z_t, w_t, z_l, w_l, block = _problem(7, 600, 8)
    z = np.concatenate([z_t, z_l])
    w = np.concatenate([w_t, w_l])
    res = adjust_leaf(T_vertex, slot, np.eye(4), X + 0.05, z, w, CAMERA, 0.5, 1.5, 10)
    (cov, b), (ref, b_ref) = _both(T_vertex, slot, res.T_leaf_trunk, res.points, z_t, w_t, z_l, w_l, block)
    assert b == b_ref and b >= 16
    np.testing.assert_allclose(cov, ref, rtol=1e-8, atol=1e-12 * np.abs(ref).max())
    assert np.all(np.linalg.eigvalsh(cov) >= -1e-15)


def test_labels_need_not_be_consecutive_and_one_block_leaves_nothing():
    T_vertex, slot, T_leaf, X, z_t, w_t, z_l, w_l, _ = _problem(3, 50, 1)
    cov, b = _kernel(T_vertex, slot, T_leaf, X, z_t, w_t, z_l, w_l, np.zeros(50, int))
    assert b == 0  # without its one block the system is empty
    block = np.where(np.arange(50) < 25, 3, 40)  # two blocks labelled 3 and 40
    (cov, b), (ref, b_ref) = _both(T_vertex, slot, T_leaf, X, z_t, w_t, z_l, w_l, block)
    assert b == b_ref == 2
    np.testing.assert_allclose(cov, ref, rtol=1e-8, atol=1e-12 * np.abs(ref).max())


def test_a_singular_system_without_a_block_counts_no_blocks():
    """A block holding every landmark but one leaves a system without enough landmarks to fix the pose: the
    localization then falls back to the adjustment's own covariance (fewer blocks than covariance_min_blocks)."""
    T_vertex, slot, T_leaf, X, z_t, w_t, z_l, w_l, _ = _problem(5, 40, 1)
    block = np.r_[np.zeros(39, int), 1]
    w_l[39] = 0.0  # the lone landmark's leaf view is not measured: nothing fixes the pose without block 0
    cov, b = _kernel(T_vertex, slot, T_leaf, X, z_t, w_t, z_l, w_l, block)
    with pytest.raises(np.linalg.LinAlgError):
        _both(T_vertex, slot, T_leaf, X, z_t, w_t, z_l, w_l, block)
    assert b == 0


def _plain_jackknife(*args) -> np.ndarray:
    """The plain delete-one-block jackknife the kernel computed before CR2 (``(B - 1) / B sum_b (d_b - mean)(d_b -
    mean)'``, ``d_b = (S - S_b)^-1 (g - g_b)`` the step without block b), from the oracle's blocks."""
    S_b, g_b = _reference_blocks(*args)
    d = np.linalg.solve(S_b.sum(axis=0)[None] - S_b, (g_b.sum(axis=0)[None] - g_b)[:, :, None])[:, :, 0]
    d = d - d.mean(axis=0)
    return (len(d) - 1) / len(d) * d.T @ d


def test_cr2_is_right_on_average_where_the_plain_jackknife_overstates():
    """Under the working model (independent pixel noise of the modelled sigma, no outliers) the covariance the kernel
    reports is, on average over noise draws, the spread of the leaf poses the adjustment returns (Bell & McCaffrey's
    CR2 is unbiased there); the plain delete-one-block jackknife it replaced reads it larger by about the blocks'
    leverage (CR3). Whitened by the empirical covariance: the mean reported covariance's eigenvalues near 1."""
    rng = np.random.default_rng(11)
    n, cells, sigma = 240, 5, 0.5
    T_vertex, slot, T_leaf, X, *_ = _problem(2, n, cells)
    Y_t = np.einsum("nij,nj->ni", T_vertex[slot][:, :3, :3], X) + T_vertex[slot][:, :3, 3]
    Y_l = X @ T_leaf[:3, :3].T + T_leaf[:3, 3]
    block = (np.clip(CAMERA.project(Y_l)[:, :2] / [CAMERA.width, CAMERA.height], 0, 0.999) * cells).astype(int)
    block = block @ np.array([cells, 1])
    w = np.ones((2 * n, 3))
    errors, covs, plain = [], [], []
    for _ in range(300):
        z = np.concatenate([CAMERA.project(Y_t), CAMERA.project(Y_l)]) + rng.normal(0, sigma, (2 * n, 3))
        res = adjust_leaf(T_vertex, slot, T_leaf, X, z, w, CAMERA, sigma, 100.0, 10)
        errors.append(log_se3(res.T_leaf_trunk @ inv_T(T_leaf)))
        cov, _ = leaf_pose_jackknife(T_vertex, slot, res.T_leaf_trunk, res.points, z, w, block, CAMERA, sigma, 100.0)
        covs.append(cov)
        args = (res.T_leaf_trunk, T_vertex[slot], res.points, z[:n], w[:n], z[n:], w[n:], block, CAMERA, sigma, 100.0)
        plain.append(_plain_jackknife(*args))
    E = np.array(errors)
    whiten = np.linalg.inv(np.linalg.cholesky(E.T @ E / len(E)))  # the empirical covariance's
    cr2 = np.linalg.eigvalsh(whiten @ np.mean(covs, axis=0) @ whiten.T)
    cr3 = np.linalg.eigvalsh(whiten @ np.mean(plain, axis=0) @ whiten.T)
    assert 0.9 < np.mean(cr2) < 1.1, cr2
    assert np.mean(cr3) > 1.1 * np.mean(cr2), (cr3, cr2)
