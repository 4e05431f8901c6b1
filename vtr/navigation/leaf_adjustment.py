"""The localization's submap adjustment in one compiled kernel: :func:`adjust_leaf` is
:func:`vtr.vo.estimation.bundle_adjust` for the one shape a localization gives it (docs/localization.md, "Cost").

A localization refines one pose, the leaf's, against landmarks that are free and each observed exactly twice: by the
taught vertex that stored it (held where the taught path puts it) and by the leaf. ``bundle_adjust`` solves any
graph (any poses free, any number of observations per landmark) with a Python loop around its kernels, assembling the
full pose system each iteration; here the whole Levenberg-Marquardt loop runs in one kernel and keeps per landmark
only what this shape needs (the leaf's 6x6 block, one coupling block), at about 60 % of the cost on kitti06. The
algorithm is the same step for step: the same residuals, Huber weights, normal equations, damping of the pose and
landmark blocks, Schur complement, acceptance and stopping rules (``RELATIVE_COST_TOLERANCE``,
``POSE_STEP_TOLERANCE``, ``MAX_LM_ATTEMPTS``, ``MIN_LM_DAMPING``), and the covariance is the inverse of the last
reduced system, so the results agree with ``bundle_adjust`` to rounding (tests/navigation/test_leaf_adjustment.py).

:func:`leaf_pose_jackknife` is the covariance of the leaf pose that the localization reports: the delete-one-block
jackknife over cells of the leaf's image, linearized at the adjustment's solution, in one kernel too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import StereoCamera
from ..errors import EstimationError
from ..vo.estimation import MIN_LM_DAMPING
from .kernels import adjust, jackknife


@dataclass(frozen=True)
class LeafAdjustment:
    """The adjusted ``T_leaf_trunk``, the landmarks (N, 3; trunk frame), per observation the squared reprojection
    error (2N: the taught views first, then the leaf's; px^2 over the measured rows), the leaf pose's 6x6
    covariance ([rot, trans], left perturbation, in units of the modelled pixel noise) and the robust cost."""

    T_leaf_trunk: np.ndarray
    points: np.ndarray
    error_sq: np.ndarray
    covariance: np.ndarray
    cost: float


def adjust_leaf(
    T_vertex_trunk: np.ndarray,
    slot: np.ndarray,
    T_leaf_trunk: np.ndarray,
    points: np.ndarray,
    z: np.ndarray,
    row_weight: np.ndarray,
    camera: StereoCamera,
    sigma_px: float,
    huber_px: float,
    iterations: int,
) -> LeafAdjustment:
    """Stereo bundle adjustment of ``T_leaf_trunk`` with N free landmarks (``points``, trunk frame), landmark i seen
    by taught vertex ``slot[i]`` (held at ``T_vertex_trunk[slot[i]]``) and by the leaf. ``z`` (2N, 3) holds the
    measurements (u_l, v, u_r): the taught views first, then the leaf's, in landmark order; ``row_weight`` (2N, 3) a
    weight per row (0: not measured). The same problem and result as
    ``bundle_adjust(concat(T_vertex_trunk, T_leaf_trunk), fixed=[True]*V + [False], ...)``."""
    Rt, tt, zz, measured, info = _kernel_rows(T_vertex_trunk, z, row_weight, sigma_px)
    T, X, err_sq, cov, cost, ok = adjust(
        Rt,
        tt,
        np.ascontiguousarray(slot, dtype=np.int64),
        np.ascontiguousarray(T_leaf_trunk, dtype=np.float64),
        np.ascontiguousarray(points, dtype=np.float64),
        zz,
        measured,
        info,
        huber_px / sigma_px,
        camera.fx,
        camera.fy,
        camera.cx,
        camera.cy,
        camera.fb,
        int(iterations),
    )
    if not ok:
        raise EstimationError("adjust_leaf: a landmark starts behind its camera")
    return LeafAdjustment(T, X, err_sq, cov, float(cost))


def leaf_pose_jackknife(
    T_vertex_trunk: np.ndarray,
    slot: np.ndarray,
    T_leaf_trunk: np.ndarray,
    points: np.ndarray,
    z: np.ndarray,
    row_weight: np.ndarray,
    block: np.ndarray,
    camera: StereoCamera,
    sigma_px: float,
    huber_px: float,
) -> tuple[np.ndarray, int]:
    """The covariance of the leaf pose by the delete-one-block jackknife: the pose's shift when the landmarks of one
    block (a cell of the image) are left out, over the blocks. Feature errors that share a cell (texture, the
    detector's position on a pattern, a rectification error over a region) move the pose together, which the
    adjustment's own inverse Hessian, with independent pixel noise, does not see (docs/localization.md, "What the
    covariance holds"). Linearized at the solution: one Gauss-Newton step of the reduced system without the block.

    The problem is :func:`adjust_leaf`'s, at its solution (``T_leaf_trunk``, ``points``), with its inputs
    (``T_vertex_trunk``, ``slot``, ``z`` and ``row_weight`` (2N, 3): the taught views first, then the leaf's) and
    linearized as it linearizes; ``block`` (N,) labels each landmark's block (non-negative integers). Returns the
    covariance (6x6, [rot, trans], left perturbation as the adjustment's) and the number of non-empty blocks ``B``:
    ``(B - 1) / B * sum_b (d_b - mean)(d_b - mean)'``, ``d_b`` the leaf's step when block b is left out; B = 0 when
    a system without one block is singular."""
    block = np.asarray(block, dtype=np.int64)
    if len(block) == 0:
        return np.zeros((6, 6)), 0
    Rt, tt, zz, measured, info = _kernel_rows(T_vertex_trunk, z, row_weight, sigma_px)
    cov, blocks = jackknife(
        Rt,
        tt,
        np.ascontiguousarray(slot, dtype=np.int64),
        np.ascontiguousarray(T_leaf_trunk, dtype=np.float64),
        np.ascontiguousarray(points, dtype=np.float64),
        zz,
        measured,
        info,
        huber_px / sigma_px,
        camera.fx,
        camera.fy,
        camera.cx,
        camera.cy,
        camera.fb,
        block,
        int(block.max()) + 1,
        MIN_LM_DAMPING,
    )
    return cov, int(blocks)


def _kernel_rows(
    T_vertex_trunk: np.ndarray, z: np.ndarray, row_weight: np.ndarray, sigma_px: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The kernels' view of the held poses and the observations: rotations and translations of ``T_vertex_trunk``,
    the measurements with unmeasured rows zeroed, a 0/1 mask of the measured rows and each row's information
    (weight / sigma^2)."""
    T_vertex_trunk = np.asarray(T_vertex_trunk, np.float64)
    w = np.asarray(row_weight, np.float64)
    return (
        np.ascontiguousarray(T_vertex_trunk[:, :3, :3]),
        np.ascontiguousarray(T_vertex_trunk[:, :3, 3]),
        np.ascontiguousarray(np.where(w > 0, z, 0.0), dtype=np.float64),
        (w > 0).astype(np.float64),
        np.ascontiguousarray(w / sigma_px**2),
    )


__all__ = ["LeafAdjustment", "adjust_leaf", "leaf_pose_jackknife"]
