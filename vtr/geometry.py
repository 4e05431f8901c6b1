"""SE(3) helpers on 4x4 numpy matrices (``T_a_b`` maps frame-b coordinates into frame a).

Thin wrappers over GTSAM's Lie-group maps (``Pose3.Expmap``/``Logmap``) and SciPy's rotations,
so the rest of the package stays in plain float64 arrays. Tangent vectors follow GTSAM's
ordering ``xi = [omega, v]`` (rotation first, radians; translation second, metres).

Pose covariances (6x6, same tangent order) have one owner here: :func:`check_covariance` (the
validation the map and the smoother apply) and :func:`usable_covariance` (the one repair rule for
estimates that are degenerate or unknown). See ``docs/frames.md``.
"""

from __future__ import annotations

from typing import overload

import gtsam
import numpy as np

from .errors import EstimationError, VtrError

#: Below this rotation angle (rad) ``log_se3_batch`` uses the series form of V^-1.
SMALL_ANGLE_RAD = 1e-4

SE3_TOLERANCE = 1e-6  # max deviation of R R^T from I and of the last row from [0 0 0 1]
COVARIANCE_SYMMETRY_RTOL = 1e-9  # |C - C^T| allowed, relative to max |C|
COVARIANCE_PSD_RTOL = 1e-9  # negative eigenvalue allowed (semi-definite check), relative to the largest
MAX_COVARIANCE_CONDITION = 1e14  # larger condition numbers are treated as singular (definite check)
MIN_EIGENVALUE_RATIO = 1e-12  # usable_covariance floors eigenvalues at this fraction of the largest
# the largest variance of a covariance that carries information: below it (far below any physical variance)
# the floored eigenvalues would sink into subnormal numbers, where the floor no longer keeps them positive
MIN_INFORMATIVE_VARIANCE = 1e-200
POSE_DIM = 6  # pose tangent dimension [rot, trans]
QUATERNION_NORM_TOLERANCE = 1e-3  # a quaternion read from a text file is unit to this (else: malformed)
_I3 = np.eye(3)
_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Build a 4x4 transform from a 3x3 rotation and a translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, float).reshape(3)
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of one (4, 4) or a stack (..., 4, 4) of rigid transforms, without a general inverse."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def transform_points(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply T_a_b to points p_b of shape (N, 3); returns p_a (N, 3)."""
    return p @ T[:3, :3].T + T[:3, 3]


def exp_se3(xi: np.ndarray) -> np.ndarray:
    """Exponential map of a twist ``[omega, v]`` (6,) to a 4x4 transform (GTSAM convention)."""
    return gtsam.Pose3.Expmap(np.asarray(xi, float)).matrix()


def log_se3(T: np.ndarray) -> np.ndarray:
    """Logarithm of a 4x4 transform as a twist ``[omega, v]`` (GTSAM convention)."""
    return gtsam.Pose3.Logmap(gtsam.Pose3(np.asarray(T, float)))


#: rotations closer than this to a half turn (rad) take scipy's rotation vector (the closed form loses the axis there)
NEAR_HALF_TURN_RAD = 1e-2


def rotvec_batch(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (K, 3) of rotation matrices (K, 3, 3): ``theta / (2 sin theta) vee(R - R')`` with ``theta``
    from the trace (series near 0), scipy's for rotations within ``NEAR_HALF_TURN_RAD`` of a half turn. Numpy only
    in the common case: a few microseconds a call instead of scipy's object construction."""
    R = np.asarray(R, float).reshape(-1, 3, 3)
    c = np.clip((R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2] - 1.0) / 2.0, -1.0, 1.0)
    th = np.arccos(c)
    v = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    small = th < SMALL_ANGLE_RAD
    ths = np.where(small, 1.0, th)
    w = np.where(small, 0.5 + th**2 / 12.0, ths / (2.0 * np.sin(ths)))[:, None] * v
    half = th > np.pi - NEAR_HALF_TURN_RAD
    if np.any(half):
        from scipy.spatial.transform import Rotation  # here: scipy.spatial costs ~0.3 s to import

        w[half] = Rotation.from_matrix(R[half]).as_rotvec()
    return w


def log_se3_batch(T: np.ndarray) -> np.ndarray:
    """Logarithms (K, 6) ``[omega, v]`` of transforms (K, 4, 4): the vectorized ``log_se3`` (same convention).

    ``v = V(omega)^-1 t`` with ``V^-1 = I - W/2 + (1/th^2) (1 - th sin th / (2 (1 - cos th))) W^2``,
    ``W = skew(omega)``, ``th = |omega|`` (series near 0).
    """
    T = np.asarray(T, float).reshape(-1, 4, 4)
    w = rotvec_batch(T[:, :3, :3])
    th = np.linalg.norm(w, axis=1)
    W = np.zeros((len(T), 3, 3))
    W[:, 0, 1], W[:, 0, 2], W[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    W[:, 1, 0], W[:, 2, 0], W[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
    small = th < SMALL_ANGLE_RAD
    ths = np.where(small, 1.0, th)
    coef = np.where(small, 1.0 / 12.0 + th**2 / 720.0, (1.0 - ths * np.sin(ths) / (2.0 * (1.0 - np.cos(ths)))) / ths**2)
    t = T[:, :3, 3]
    Wt = np.einsum("kij,kj->ki", W, t)
    WWt = np.einsum("kij,kj->ki", W, Wt)
    return np.hstack([w, t - 0.5 * Wt + coef[:, None] * WWt])


def distance_to_polyline(points: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    """Distance of each point (N, D) to the polyline through ``polyline`` (M, D) vertices, any D."""
    points, polyline = np.atleast_2d(points), np.atleast_2d(polyline)
    if len(polyline) == 1:
        return np.linalg.norm(points - polyline[0], axis=1)
    a, ab = polyline[:-1], np.diff(polyline, axis=0)
    t = np.einsum("nmk,mk->nm", points[:, None, :] - a[None], ab) / np.maximum((ab**2).sum(1), 1e-12)
    closest = a[None] + np.clip(t, 0, 1)[..., None] * ab[None]
    return np.linalg.norm(points[:, None, :] - closest, axis=2).min(axis=1)


def skew(w: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrices of vectors of shape (..., 3) -> (..., 3, 3)."""
    w = np.asarray(w, float)
    S = np.zeros(w.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -w[..., 2], w[..., 1]
    S[..., 1, 0], S[..., 1, 2] = w[..., 2], -w[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -w[..., 1], w[..., 0]
    return S


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Angle (rad) of rotation matrices (..., 3, 3)."""
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(c, -1.0, 1.0))


def T_to_tum(T: np.ndarray) -> np.ndarray:
    """4x4 transform(s) (..., 4, 4) -> (..., 7) ``x y z qx qy qz qw``."""
    T = np.asarray(T, float)
    from scipy.spatial.transform import Rotation  # here: scipy.spatial costs ~0.3 s to import

    q = Rotation.from_matrix(T[..., :3, :3].reshape(-1, 3, 3)).as_quat()
    return np.concatenate([T[..., :3, 3].reshape(-1, 3), q], axis=1).reshape(T.shape[:-2] + (7,))


def tum_to_T(xyzq: np.ndarray) -> np.ndarray:
    """(..., 7) ``x y z qx qy qz qw`` -> (..., 4, 4) transforms."""
    xyzq = np.asarray(xyzq, float)
    flat = xyzq.reshape(-1, 7)
    T = np.tile(np.eye(4), (len(flat), 1, 1))
    from scipy.spatial.transform import Rotation  # here: scipy.spatial costs ~0.3 s to import

    T[:, :3, :3] = Rotation.from_quat(flat[:, 3:]).as_matrix()
    T[:, :3, 3] = flat[:, :3]
    return T.reshape(xyzq.shape[:-1] + (4, 4))


def check_se3(
    T: np.ndarray, what: str = "transform", tol: float = SE3_TOLERANCE, error: type[VtrError] = EstimationError
) -> np.ndarray:
    """Validate a 4x4 rigid transform; return it as float64 or raise ``error`` naming ``what``.

    Checks shape, finiteness, the last row ``[0 0 0 1]`` and an orthonormal rotation block with
    determinant +1 (to ``tol``). Scalar arithmetic keeps it cheap enough for per-measurement use.
    """
    try:
        T = np.asarray(T, dtype=float)
    except (TypeError, ValueError) as err:
        raise error(f"{what}: not a numeric 4x4 matrix ({err})") from err
    if T.shape != (4, 4):
        raise error(f"{what}: expected a 4x4 matrix, got shape {T.shape}")
    if not np.isfinite(T).all():
        raise error(f"{what}: contains NaN or infinity")
    if np.abs(T[3] - _LAST_ROW).max() > tol:
        raise error(f"{what}: last row is {T[3].tolist()}, not [0 0 0 1]")
    R = T[:3, :3]
    (a, b, c), (d, e, f), (g, h, i) = R.tolist()
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    if np.abs(R @ R.T - _I3).max() > tol or det < 0:
        raise error(f"{what}: rotation block is not orthonormal with det +1")
    return T


def check_covariance(
    C: np.ndarray, what: str = "covariance", error: type[VtrError] = EstimationError, definite: bool = False
) -> np.ndarray:
    """Validate a 6x6 pose covariance; return its symmetric part as float64 or raise ``error`` naming ``what``.

    Checks shape, finiteness and symmetry (to ``COVARIANCE_SYMMETRY_RTOL`` of its largest entry); then
    positive semi-definiteness (to ``COVARIANCE_PSD_RTOL``), or with ``definite`` a non-zero matrix that is
    positive definite with condition number at most ``MAX_COVARIANCE_CONDITION`` (an invertible
    measurement covariance).
    """
    try:
        C = np.array(C, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise error(f"{what}: not a numeric 6x6 matrix ({err})") from err
    if C.shape != (POSE_DIM, POSE_DIM):
        raise error(f"{what}: expected a 6x6 matrix, got shape {C.shape}")
    if not np.all(np.isfinite(C)):
        raise error(f"{what}: contains NaN or infinity")
    scale = float(np.max(np.abs(C)))
    if definite and scale == 0.0:
        raise error(f"{what}: not a symmetric non-zero matrix")
    if np.max(np.abs(C - C.T)) > COVARIANCE_SYMMETRY_RTOL * max(scale, 1e-300):
        raise error(f"{what}: not symmetric")
    C = 0.5 * (C + C.T)
    eig = np.linalg.eigvalsh(C)
    if definite:
        if eig[0] <= 0.0 or eig[-1] / eig[0] > MAX_COVARIANCE_CONDITION:
            raise error(
                f"{what}: not positive definite (eigenvalues {eig[0]:.3g} … {eig[-1]:.3g}); "
                "a measurement covariance must be invertible"
            )
    elif eig[0] < -COVARIANCE_PSD_RTOL * max(float(eig[-1]), 0.0):
        raise error(f"{what}: not positive semi-definite (smallest eigenvalue {eig[0]:.3g})")
    return C


@overload
def usable_covariance(C: np.ndarray, unknown_variance: None = None) -> np.ndarray | None: ...


@overload
def usable_covariance(C: np.ndarray, unknown_variance: float) -> np.ndarray: ...


def usable_covariance(C: np.ndarray, unknown_variance: float | None = None) -> np.ndarray | None:
    """The nearest covariance every consumer accepts: symmetric, eigenvalues floored at
    ``MIN_EIGENVALUE_RATIO`` times the largest (so it is invertible with a bounded condition number).

    An estimate that carries no information (not a finite 6x6 matrix, e.g. NaN from a singular
    solve, or without an eigenvalue of at least ``MIN_INFORMATIVE_VARIANCE``) gives ``unknown_variance * I``
    when ``unknown_variance`` is given (the variance of an edge nothing measured), else ``None``.
    """
    C = np.asarray(C, float)
    unknown = None if unknown_variance is None else np.eye(POSE_DIM) * float(unknown_variance)
    if C.shape != (POSE_DIM, POSE_DIM) or not np.all(np.isfinite(C)):
        return unknown
    C = 0.5 * (C + C.T)
    w, V = np.linalg.eigh(C)
    if not w[-1] >= MIN_INFORMATIVE_VARIANCE:
        return unknown
    C = (V * np.maximum(w, w[-1] * MIN_EIGENVALUE_RATIO)) @ V.T
    return 0.5 * (C + C.T)
