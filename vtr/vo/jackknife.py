"""The covariance of one pose of a stereo bundle adjustment by the delete-one-block jackknife: the pose's shift when
the landmarks of one block (a cell of the image) are left out, over the blocks. Feature errors that share a cell
(texture, the detector's position on a pattern, a rectification error over a region) move the pose together, which
the adjustment's own inverse Hessian, with independent pixel noise, does not see (docs/localization.md, "What the
covariance holds"). Linearized at the solution: one Gauss-Newton step of the reduced system without the block."""

from __future__ import annotations

import numpy as np

from ..camera import StereoCamera
from .estimation import MIN_LM_DAMPING

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


def leaf_pose_jackknife(
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
) -> tuple[np.ndarray, int]:
    """Jackknife covariance (6x6, [rot, trans], left perturbation as the adjustment's) of the free pose ``T_leaf``
    of an adjustment where each landmark (``points`` (N, 3) at the solution) is seen once from a held pose
    (``T_taught`` (N, 4, 4), the pose of its observer) and once from the leaf, with measurements and row weights as
    the adjustment had them, the landmarks free. ``block`` (N,) labels each landmark's block. Returns the covariance
    and the number of non-empty blocks ``B``: ``(B - 1) / B * sum_b (d_b - mean)(d_b - mean)'``, ``d_b`` the leaf's
    step when block b is left out."""
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
    S, g = S_b.sum(axis=0), g_b.sum(axis=0)
    d = np.linalg.solve(S[None] - S_b, (g[None] - g_b)[:, :, None])[:, :, 0]
    d = d - d.mean(axis=0)
    return (B - 1) / B * d.T @ d, B
