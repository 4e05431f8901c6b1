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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import StereoCamera
from ..errors import EstimationError
from .kernels import adjust


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
    T_vertex_trunk = np.asarray(T_vertex_trunk, np.float64)
    w = np.asarray(row_weight, np.float64)
    measured = (w > 0).astype(np.float64)
    zz = np.ascontiguousarray(np.where(w > 0, z, 0.0), dtype=np.float64)
    T, X, err_sq, cov, cost, ok = adjust(
        np.ascontiguousarray(T_vertex_trunk[:, :3, :3]),
        np.ascontiguousarray(T_vertex_trunk[:, :3, 3]),
        np.ascontiguousarray(slot, dtype=np.int64),
        np.ascontiguousarray(T_leaf_trunk, dtype=np.float64),
        np.ascontiguousarray(points, dtype=np.float64),
        zz,
        measured,
        np.ascontiguousarray(w / sigma_px**2),
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


__all__ = ["LeafAdjustment", "adjust_leaf"]
