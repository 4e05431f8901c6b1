"""Controller-facing state, path reference and path-tracking error (thesis §6.3.4).

Frames (``T_a_b`` maps b coordinates into a; all SI units):

* ``world``: the fixed frame of the smoother's measurements (:class:`vtr.state.smoothing.TrajectorySmoother`).
* ``t`` (trunk): vehicle frame of the privileged (taught) vertex closest to the vehicle; FLU (x forward,
  y left, z up on a level vehicle).
* ``a``: the vehicle frame now (FLU); the smoother may track another rigidly attached frame (the
  camera, "sensor"), related by ``T_sensor_vehicle``.
* ``o``: gravity-aligned frame at the trunk: origin at the trunk's origin, z up (opposite to gravity),
  x along the trunk's heading projected on the horizontal plane. ``T_o_t`` is a pure rotation
  (roll and pitch of the trunk), built by :func:`gravity_aligned_T_o_t`. The convention (frame o,
  yaw, camera mount) has one owner, :mod:`perception_model.frames`; ``yaw_of`` is that module's.

The controller state is ``z = (p, v, a, psi)`` and the output ``y = (p, psi)``: position, velocity and
acceleration of the vehicle origin relative to o, expressed in o, and the yaw of the vehicle's x axis
in o. With this choice of o the trunk's own yaw is 0, so ``psi`` is the heading error to the trunk.
The reference path is the polyline through consecutive privileged vertices, expressed in o.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from perception_model.frames import rot_z, wrap_angle, yaw_of

from ..errors import EstimationError
from ..geometry import check_se3, inv_T, skew
from .smoothing import TrajectoryState, adjoint

GRAVITY_UP = np.array([0.0, 0.0, 1.0])  # z axis of o and of any gravity-aligned frame g
MIN_SEGMENT_LENGTH_M = 1e-9  # shorter path segments are merged away
MIN_HORIZONTAL_FRACTION = 1e-9  # a segment steeper than this is treated as vertical
_ROT_AND_LINEAR_VEL = np.array([0, 1, 2, 9, 10, 11])  # (d theta, d v) inside [pose, twist] perturbations


def gravity_aligned_T_o_t(C_g_t: np.ndarray) -> np.ndarray:
    """``T_o_t`` (4x4) from the trunk's attitude ``C_g_t`` (3x3) in any gravity-aligned frame g (z up).

    g is e.g. ENU, or the smoother's world frame when it is gravity-aligned; the IMU attitude of the
    trunk vertex gives ``C_g_t``. o shares the trunk's origin and yaw and has z up:
    ``C_o_t = Rz(psi_t)^T C_g_t`` with ``psi_t`` the trunk's yaw in g.
    """
    C_g_t = np.asarray(C_g_t, float)
    if C_g_t.shape != (3, 3) or not np.all(np.isfinite(C_g_t)):
        raise EstimationError("C_g_t: expected a finite 3x3 rotation")
    T = np.eye(4)
    T[:3, :3] = rot_z(float(yaw_of(C_g_t))).T @ C_g_t
    return check_se3(T, "T_o_t")


class StateStatus(StrEnum):
    """What a controller state rests on (``ControllerState.status``, ``state.csv``'s ``status`` column)."""

    LOCALIZED = "localized"  # the localization chain holds a localization (its verdict): trust it
    DEAD_RECKONING = "dead_reckoning"  # localized before, now carried by odometry alone: the error grows
    OFF_ROUTE = "off_route"  # beyond either end of the taught route (or the chain said so)
    UNKNOWN = "unknown"  # not localized yet, or too long after the last frame (a pause)


@dataclass(frozen=True)
class ControllerState:
    """Vehicle state in the gravity-aligned trunk frame o (thesis eqs. 6.1-6.2).

    Attributes:
        t_ns: time of the state (int ns).
        position: ``p_o^{ao}`` (3,), m: vehicle origin relative to the trunk, in o.
        velocity: ``v_o^{ao}`` (3,), m/s, in o.
        acceleration: ``a_o^{ao}`` (3,), m/s², in o (from the smoother's acceleration estimate).
        yaw: ``psi`` (rad), heading of the vehicle x axis in o (0 = the trunk's heading).
        T_o_a: vehicle pose in o (4x4).
        position_covariance: (3x3) m², in o; None if the smoother state had no covariance.
        velocity_covariance: (3x3) (m/s)², in o; None likewise.
        yaw_variance: rad²; None likewise.
        status: what the state rests on (:class:`StateStatus`); a controller acts on ``localized`` only.
        direction: +1 the route travelled in taught order, -1 backward, 0 not yet decided.
        T_g_o: the trunk's frame o in the map's gravity-aligned frame g (4x4; None when not known), the frame of
            :class:`vtr.control.field.TaughtPathField`: see :meth:`in_map_gravity_frame`.
        acceleration_covariance: (3x3) (m/s²)², in o, of ``acceleration`` when it comes from a fit of the knots'
            velocities (``smoothing.acceleration_window_s``; infinite where too few knots); None otherwise.
    """

    t_ns: int
    position: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    yaw: float
    T_o_a: np.ndarray
    position_covariance: np.ndarray | None = None
    velocity_covariance: np.ndarray | None = None
    yaw_variance: float | None = None
    status: StateStatus = StateStatus.UNKNOWN
    direction: int = 0
    T_g_o: np.ndarray | None = None
    acceleration_covariance: np.ndarray | None = None

    @property
    def localized(self) -> bool:
        return self.status == StateStatus.LOCALIZED

    def in_map_gravity_frame(self) -> tuple[np.ndarray, float]:
        """``(p_g, psi_g)``: the vehicle's position (3,) and yaw in the map's gravity-aligned frame g, the output
        ``(p, psi)`` that :meth:`vtr.control.field.TaughtPathField.evaluate` takes (o is g turned by the trunk's
        yaw about z and moved to the trunk: ``p_g = T_g_o p_o``, ``psi_g = psi + psi_t``)."""
        if self.T_g_o is None:
            raise EstimationError("this controller state has no T_g_o (the trunk frame in the map's g)")
        p_g = self.T_g_o[:3, :3] @ self.position + self.T_g_o[:3, 3]
        return p_g, float(wrap_angle(self.yaw + float(yaw_of(self.T_g_o[:3, :3]))))

    @property
    def z(self) -> np.ndarray:
        """State ``z = (p, v, a, psi)`` (10,)."""
        return np.r_[self.position, self.velocity, self.acceleration, self.yaw]

    @property
    def y(self) -> np.ndarray:
        """Output ``y = (p, psi)`` (4,)."""
        return np.r_[self.position, self.yaw]


def trunk_in_world(T_world_leaf: np.ndarray, T_leaf_trunk: np.ndarray) -> np.ndarray:
    """``T_world_trunk`` from the leaf's smoothed pose and the localization chain's ``T_leaf_trunk``.

    ``T_world_leaf`` is the leaf keyframe's vehicle pose in the smoother's world frame (e.g.
    ``smoother.state_at(t_leaf).pose @ T_sensor_vehicle``); ``T_leaf_trunk`` comes from the chain
    (``T_l_t = T_l_w T_w_b T_b_t``).
    """
    return check_se3(T_world_leaf, "T_world_leaf") @ check_se3(T_leaf_trunk, "T_leaf_trunk")


def yaw_jacobian(C_o_a: np.ndarray) -> np.ndarray:
    """d psi / d theta (1x3) for a right rotation perturbation ``C_o_a Exp(theta)``."""
    x = C_o_a[:, 0]
    d_x = -C_o_a @ skew(np.array([1.0, 0.0, 0.0]))  # d(C Exp(theta) e1)/d theta
    den = x[0] ** 2 + x[1] ** 2
    return (x[0] * d_x[1] - x[1] * d_x[0]) / den


def controller_state(
    state: TrajectoryState,
    T_world_trunk: np.ndarray,
    T_o_t: np.ndarray,
    T_sensor_vehicle: np.ndarray | None = None,
) -> ControllerState:
    """Controller state z and output y of the vehicle in the gravity-aligned trunk frame o.

    Args:
        state: smoother state at the current time (pose ``T_world_sensor``, body twist and its rate in
            the sensor frame, covariance over ``[right pose perturbation, twist]``).
        T_world_trunk: trunk vehicle pose in the smoother's world frame (see :func:`trunk_in_world`).
        T_o_t: gravity alignment of the trunk (see :func:`gravity_aligned_T_o_t`).
        T_sensor_vehicle: vehicle frame in the sensor frame (identity when the smoother tracks the
            vehicle itself).

    The current pose relative to the trunk is ``T_a_t = inv(T_world_a) T_world_trunk`` and
    ``T_o_a = T_o_t inv(T_a_t)`` (thesis §6.3.4). Velocity and acceleration of the vehicle origin
    come from the body twist moved to the vehicle frame by the adjoint of ``T_vehicle_sensor``:
    ``v_o = C_o_a v_a`` and ``a_o = C_o_a (v_a' + omega_a x v_a)``. The covariances propagate the
    smoother's covariance to first order; the trunk pose and the gravity alignment are taken as exact.
    """
    if T_sensor_vehicle is None:
        T_sv, Ad_vs = None, np.eye(6)
    else:
        T_sv = check_se3(T_sensor_vehicle, "T_sensor_vehicle")
        Ad_vs = adjoint(inv_T(T_sv))
    T_world_trunk = check_se3(T_world_trunk, "T_world_trunk")
    return controller_state_unchecked(state, T_world_trunk, check_se3(T_o_t, "T_o_t"), T_sv, Ad_vs)


def controller_state_unchecked(
    state: TrajectoryState,
    T_world_trunk: np.ndarray,
    T_o_t: np.ndarray,
    T_sensor_vehicle: np.ndarray | None,
    Ad_vs: np.ndarray,
) -> ControllerState:
    """:func:`controller_state` on transforms the caller has validated (``check_se3``, float64), with
    ``Ad_vs = adjoint(inv_T(T_sensor_vehicle))`` (``np.eye(6)`` without one) computed once: the same arithmetic,
    for callers that query one route many times (:class:`~vtr.navigation.state_view.RouteFrames`)."""
    T_world_a = state.pose if T_sensor_vehicle is None else state.pose @ T_sensor_vehicle
    T_a_t = inv_T(T_world_a) @ T_world_trunk
    T_o_a = T_o_t @ inv_T(T_a_t)
    C_o_a = T_o_a[:3, :3]
    twist_a = Ad_vs @ state.velocity
    rate_a = Ad_vs @ state.acceleration
    w_a, v_a = twist_a[:3], twist_a[3:]
    position = T_o_a[:3, 3].copy()
    velocity = C_o_a @ v_a
    acceleration = C_o_a @ (rate_a[3:] + skew(w_a) @ v_a)
    yaw = float(yaw_of(C_o_a))
    pos_cov = vel_cov = yaw_var = None
    if state.covariance is not None:
        # Vehicle state perturbation (right on T_world_a, additive on its twist) from the sensor's.
        G = np.zeros((12, 12))
        G[:6, :6] = Ad_vs
        G[6:, 6:] = Ad_vs
        P = G @ state.covariance @ G.T
        # position p_o = T_o_world p_world(a): right perturbation moves it by C_o_a d_trans.
        pos_cov = C_o_a @ P[3:6, 3:6] @ C_o_a.T
        # v_o = C_o_a v_a: d v_o = C_o_a (d v - v^ d theta)
        Jv = np.hstack([-C_o_a @ skew(v_a), C_o_a])  # w.r.t. (d theta, d v)
        vel_cov = Jv @ P[_ROT_AND_LINEAR_VEL][:, _ROT_AND_LINEAR_VEL] @ Jv.T
        jy = yaw_jacobian(C_o_a)
        yaw_var = float(jy @ P[:3, :3] @ jy)
    return ControllerState(
        t_ns=state.t_ns,
        position=position,
        velocity=velocity,
        acceleration=acceleration,
        yaw=yaw,
        T_o_a=T_o_a,
        position_covariance=pos_cov,
        velocity_covariance=vel_cov,
        yaw_variance=yaw_var,
    )


def output_jacobian(T_o_a: np.ndarray, T_sensor_vehicle: np.ndarray | None = None) -> np.ndarray:
    """Jacobian (4x12) of the output ``y = (p_o, psi)`` of :func:`controller_state` w.r.t. the smoother's state
    perturbation ``[right pose perturbation (rot, trans), twist]`` of the sensor (the trunk taken as exact)."""
    T_o_a = np.asarray(T_o_a, float)
    Ad_vs = np.eye(6) if T_sensor_vehicle is None else adjoint(inv_T(check_se3(T_sensor_vehicle, "T_sensor_vehicle")))
    return output_jacobian_unchecked(T_o_a, Ad_vs)


def output_jacobian_unchecked(T_o_a: np.ndarray, Ad_vs: np.ndarray) -> np.ndarray:
    """:func:`output_jacobian` with ``Ad_vs = adjoint(inv_T(T_sensor_vehicle))`` computed once by the caller from a
    validated transform (``T_o_a`` float64)."""
    C_o_a = T_o_a[:3, :3]
    H = np.zeros((4, 12))
    Hv = np.zeros((4, 6))  # w.r.t. the vehicle's pose perturbation (rot, trans)
    Hv[:3, 3:6] = C_o_a
    Hv[3, :3] = yaw_jacobian(C_o_a)
    H[:, :6] = Hv @ Ad_vs
    return H


@dataclass(frozen=True)
class PathError:
    """Path-tracking error of positions against a :class:`ReferencePath` (arrays over the positions).

    Attributes:
        lateral: signed horizontal distance (m) from the closest segment's line, positive to the left
            of the direction of travel (unsigned for a vertical segment).
        vertical: signed distance (m) above the segment's line, measured in the vertical plane that
            contains the segment, perpendicular to it.
        along_track: arc length (m) from the path's first point to the projection of the position on the
            closest segment's line (negative before the start, beyond the length after the end).
        segment: index of the closest segment (int).
        reference_point: (..., 3) closest point on the path, in o (m).
        direction: (..., 3) unit direction of travel of the closest segment, in o.
    """

    lateral: np.ndarray
    vertical: np.ndarray
    along_track: np.ndarray
    segment: np.ndarray
    reference_point: np.ndarray
    direction: np.ndarray

    @property
    def cross_track(self) -> np.ndarray:
        """Distance (m) from the segment's line: ``hypot(lateral, vertical)``."""
        return np.hypot(self.lateral, self.vertical)


class ReferencePath:
    """Straight segments between consecutive privileged vertices, in the gravity-aligned frame o.

    Args:
        points_o: (N, 3) vertex positions in o (m), in the order of travel, N >= 2. Consecutive
            duplicates are dropped.
    """

    def __init__(self, points_o: np.ndarray) -> None:
        pts = np.asarray(points_o, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise EstimationError(f"points_o: expected shape (N, 3), got {pts.shape}")
        if not np.all(np.isfinite(pts)):
            raise EstimationError("points_o: contains NaN or infinity")
        keep = np.concatenate([[True], np.linalg.norm(np.diff(pts, axis=0), axis=1) > MIN_SEGMENT_LENGTH_M])
        pts = pts[keep]
        if len(pts) < 2:
            raise EstimationError("points_o: a path needs at least two distinct points")
        self.points = pts
        seg = np.diff(pts, axis=0)
        self.lengths = np.linalg.norm(seg, axis=1)
        self.directions = seg / self.lengths[:, None]
        self.cumulative = np.concatenate([[0.0], np.cumsum(self.lengths)])
        # Left normal (horizontal) and up normal (in the segment's vertical plane) of each segment:
        # left = up x d, up_n = d x left.
        d = self.directions
        left = np.zeros_like(d)
        left[:, 0], left[:, 1] = -d[:, 1], d[:, 0]
        norm = np.hypot(left[:, 0], left[:, 1])
        vertical_seg = norm < MIN_HORIZONTAL_FRACTION
        left[vertical_seg] = 0.0
        left[~vertical_seg] /= norm[~vertical_seg, None]
        self._vertical_seg = vertical_seg
        self.left_normals = left
        up = np.empty_like(d)
        up[:, 0] = d[:, 1] * left[:, 2] - d[:, 2] * left[:, 1]
        up[:, 1] = d[:, 2] * left[:, 0] - d[:, 0] * left[:, 2]
        up[:, 2] = d[:, 0] * left[:, 1] - d[:, 1] * left[:, 0]
        self.up_normals = up

    @property
    def length(self) -> float:
        """Total length (m)."""
        return float(self.cumulative[-1])

    @classmethod
    def from_vertices(cls, T_t_vertices: np.ndarray, T_o_t: np.ndarray) -> ReferencePath:
        """Path through privileged vertices given as poses ``T_t_v`` (N, 4, 4) relative to the trunk.

        ``p_o^{vt} = C_o_t p_t^{vt}`` (the origin of o is the trunk), i.e. ``(T_o_t @ T_t_v)[:3, 3]``.
        """
        T = np.asarray(T_t_vertices, dtype=float)
        if T.ndim != 3 or T.shape[1:] != (4, 4):
            raise EstimationError(f"T_t_vertices: expected shape (N, 4, 4), got {T.shape}")
        T_o_t = check_se3(T_o_t, "T_o_t")
        return cls(T[:, :3, 3] @ T_o_t[:3, :3].T + T_o_t[:3, 3])

    @classmethod
    def from_world(cls, T_world_vertices: np.ndarray, T_world_trunk: np.ndarray, T_o_t: np.ndarray) -> ReferencePath:
        """Path through privileged vertex poses ``T_world_v`` (N, 4, 4) known in the smoother's world frame."""
        T_t_world = inv_T(check_se3(T_world_trunk, "T_world_trunk"))
        return cls.from_vertices(T_t_world @ np.asarray(T_world_vertices, float), T_o_t)

    def error(self, p_o: np.ndarray) -> PathError:
        """Tracking error of positions ``p_o`` ((3,) or (M, 3), m, in o) against the closest segment."""
        p = np.asarray(p_o, dtype=float)
        single = p.ndim == 1
        P = np.atleast_2d(p)
        if P.shape[-1] != 3 or P.ndim != 2:
            raise EstimationError(f"p_o: expected shape (3,) or (M, 3), got {p.shape}")
        if not np.all(np.isfinite(P)):
            raise EstimationError("p_o: contains NaN or infinity")
        a = self.points[:-1]  # (S, 3)
        rel = P[:, None, :] - a[None]  # (M, S, 3)
        s = np.einsum("msk,sk->ms", rel, self.directions)  # along each segment
        s_clamped = np.clip(s, 0.0, self.lengths[None])
        closest = a[None] + s_clamped[..., None] * self.directions[None]
        dist2 = np.sum((P[:, None, :] - closest) ** 2, axis=-1)
        seg = np.argmin(dist2, axis=1)  # first on ties
        m = np.arange(len(P))
        d = rel[m, seg]
        lateral = np.einsum("mk,mk->m", d, self.left_normals[seg])
        vertical = np.einsum("mk,mk->m", d, self.up_normals[seg])
        vert_seg = self._vertical_seg[seg]
        if np.any(vert_seg):
            horiz = d[vert_seg].copy()
            horiz[:, 2] = 0.0
            lateral[vert_seg] = np.linalg.norm(horiz, axis=1)
        along = self.cumulative[seg] + s[m, seg]
        ref = closest[m, seg]
        out = PathError(lateral, vertical, along, seg, ref, self.directions[seg])
        if single:
            out = PathError(
                lateral=lateral[0],
                vertical=vertical[0],
                along_track=along[0],
                segment=seg[0],
                reference_point=ref[0],
                direction=self.directions[seg[0]],
            )
        return out


__all__ = [
    "ControllerState",
    "PathError",
    "ReferencePath",
    "StateStatus",
    "controller_state",
    "controller_state_unchecked",
    "gravity_aligned_T_o_t",
    "output_jacobian",
    "output_jacobian_unchecked",
    "trunk_in_world",
    "yaw_jacobian",
    "yaw_of",
]
