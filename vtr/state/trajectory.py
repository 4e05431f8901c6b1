"""Queries over the knots of a continuous-time WNOA trajectory (numpy, no solver): the Lie-group helpers, the state
value types, GP interpolation between knots and extrapolation after the last one, their Jacobians, joint covariances
and a fitted acceleration. :class:`~vtr.state.smoothing.TrajectorySmoother` answers its own queries through a
:class:`KnotTrajectory` over its cache and publishes immutable copies of one (docs/smoother.md, docs/online.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import overload

import gtsam
import numpy as np

from ..conventions import NS_PER_S
from ..errors import EstimationError
from ..geometry import POSE_DIM, inv_T, skew
from .wnoa import (
    STATE_DIM,
    hermite_matrix,
    kron_qc,
    local_variable,
    noise_map,
    wnoa_conditional_Q,
    wnoa_Q,
)

# Input validation.

# Central-difference step for the derivative of Jr(xi) w with respect to xi (only in covariances
# and the acceleration estimate): truncation error O(step²), round-off O(1e-16 / step) ≈ 1e-10.
JACOBIAN_STEP = 1e-6

# ----------------------------------------------------------------------------------------------
# Lie-group helpers (GTSAM conventions: tangent [omega, v], right Jacobians)


def expmap(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Exp(xi)`` as a 4x4 matrix and the right Jacobian ``Jr(xi)`` (6x6)."""
    H = np.empty((POSE_DIM, POSE_DIM), order="F")
    T = gtsam.Pose3.Expmap(xi, H).matrix()
    return T, H


def logmap(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Log(T)`` (6,) and the inverse right Jacobian ``Jr^-1(Log T)`` (6x6)."""
    H = np.empty((POSE_DIM, POSE_DIM), order="F")
    xi = gtsam.Pose3.Logmap(gtsam.Pose3(T), H)
    return xi, H


def adjoint(T: np.ndarray) -> np.ndarray:
    """Adjoint (6x6) of a 4x4 transform in GTSAM's twist order ``[omega, v]``: ``[[R, 0], [t^ R, R]]``."""
    R = T[:3, :3]
    Ad = np.zeros((POSE_DIM, POSE_DIM))
    Ad[:3, :3] = R
    Ad[3:, 3:] = R
    Ad[3:, :3] = skew(T[:3, 3]) @ R
    return Ad


def jr(xi: np.ndarray) -> np.ndarray:
    """The right Jacobian ``Jr(xi)`` (6x6) of ``Exp``."""
    return gtsam.Pose3.ExpmapDerivative(xi)


def jr_inv(xi: np.ndarray) -> np.ndarray:
    """The inverse right Jacobian ``Jr^-1(xi)`` (6x6)."""
    return gtsam.Pose3.LogmapDerivative(xi)


_STEPS = JACOBIAN_STEP * np.eye(POSE_DIM)


def d_jr_times(xi: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``d(Jr(xi) w)/d xi`` (6x6) by central differences of GTSAM's closed-form ``Jr``."""
    plus = np.array([gtsam.Pose3.ExpmapDerivative(xi + d) for d in _STEPS])
    minus = np.array([gtsam.Pose3.ExpmapDerivative(xi - d) for d in _STEPS])
    return ((plus - minus) @ w).T / (2.0 * JACOBIAN_STEP)


def d_jr_inv_times(xi: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``d(Jr^-1(xi) w)/d xi`` (6x6) by central differences of GTSAM's closed-form ``Jr^-1``."""
    plus = np.array([gtsam.Pose3.LogmapDerivative(xi + d) for d in _STEPS])
    minus = np.array([gtsam.Pose3.LogmapDerivative(xi - d) for d in _STEPS])
    return ((plus - minus) @ w).T / (2.0 * JACOBIAN_STEP)


def directional_d_jr(xi: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``(d(Jr(xi) w)/d xi) w`` by a central difference along ``w``."""
    h = JACOBIAN_STEP
    return (jr(xi + h * w) @ w - jr(xi - h * w) @ w) / (2.0 * h)


def adjoint_inv(T: np.ndarray) -> np.ndarray:
    """Adjoint of ``T^-1`` (6x6) without inverting T: ``[[R^T, 0], [-R^T t^, R^T]]``."""
    Rt = T[:3, :3].T
    Ad = np.zeros((POSE_DIM, POSE_DIM))
    Ad[:3, :3] = Rt
    Ad[3:, 3:] = Rt
    Ad[3:, :3] = -Rt @ skew(T[:3, 3])
    return Ad


# ----------------------------------------------------------------------------------------------
# Public value types


@overload
def frozen(a: np.ndarray) -> np.ndarray: ...


@overload
def frozen(a: None) -> None: ...


def frozen(a: np.ndarray | None) -> np.ndarray | None:
    if a is None:
        return None
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class TrajectoryState:
    """The smoothed state of the sensor at one time.

    Attributes:
        t_ns: query time (int64 ns, same clock as the measurements).
        pose: ``T_world_sensor`` (4x4): sensor coordinates to the measurements' fixed frame (m).
        velocity: body twist ``[omega, v]`` (6,) of the sensor relative to world, expressed in the sensor
            frame (rad/s, m/s).
        acceleration: time derivative of ``velocity`` (6,), sensor frame (rad/s², m/s²). Inside the knots
            it is the derivative of the GP posterior mean; after the last knot it is the value at the last
            knot, held (the WNOA prior's own mean acceleration there is zero).
        covariance: 12x12 covariance of ``[pose perturbation (rot rad, trans m), twist]`` with the pose
            perturbation on the right (``T = T_hat Exp(delta)``, sensor frame), or None if not requested.
        kind: ``"knot"``, ``"interpolated"`` or ``"extrapolated"``.
    """

    t_ns: int
    pose: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    covariance: np.ndarray | None
    kind: str

    @property
    def position(self) -> np.ndarray:
        """Sensor origin in world (m), shape (3,)."""
        return self.pose[:3, 3]

    @property
    def linear_velocity_world(self) -> np.ndarray:
        """Velocity of the sensor origin expressed in world (m/s), shape (3,)."""
        return self.pose[:3, :3] @ self.velocity[3:]

    @property
    def linear_acceleration_world(self) -> np.ndarray:
        """Acceleration of the sensor origin expressed in world (m/s²): ``R (v' + omega x v)``."""
        w, v = self.velocity[:3], self.velocity[3:]
        return self.pose[:3, :3] @ (self.acceleration[3:] + skew(w) @ v)


@dataclass(frozen=True)
class KnotStates:
    """Copies of the estimated knot states, oldest first.

    ``times_ns`` (N,) int64 ns; ``poses`` (N, 4, 4) ``T_world_sensor``; ``velocities`` (N, 6) body twists
    ``[omega, v]`` (rad/s, m/s, sensor frame).
    """

    times_ns: np.ndarray
    poses: np.ndarray
    velocities: np.ndarray


# ----------------------------------------------------------------------------------------------
# Validation helpers


_T_NS_MIN, _T_NS_MAX = int(np.iinfo(np.int64).min), int(np.iinfo(np.int64).max)


def check_time(t_ns: object, what: str = "t_ns") -> int:
    if isinstance(t_ns, bool) or not isinstance(t_ns, int | np.integer):
        raise EstimationError(f"{what}: expected an integer time in nanoseconds, got {type(t_ns).__name__}")
    t = int(t_ns)
    if not _T_NS_MIN <= t <= _T_NS_MAX:  # times are stored as int64: checked before anything is inserted
        raise EstimationError(f"{what}={t}: outside the int64 nanosecond range [{_T_NS_MIN}, {_T_NS_MAX}]")
    return t


class Segment:
    """Per-segment quantities that depend only on the two knot states (computed on first use).

    ``M`` stacks the Hermite control vectors ``[dt v1, xi21, dt g21]`` (3x6) of the local variable; the
    derivative tensor ``S`` (3x6x24) holds ``d(v1, xi21, g21)/d(delta1, dv1, delta2, dv2)`` and is built
    only when a covariance is asked for. The memo slots ``acc_start``/``acc_end`` (the mean acceleration at the
    segment's ends, functions of ``M`` and ``dt`` alone) are filled by :class:`KnotTrajectory` on first use; any
    thread may fill one: a race computes the same value twice and stores it whole.
    """

    __slots__ = (
        "dt",
        "T1",
        "v1",
        "v2",
        "xi21",
        "g21",
        "Jr_inv21",
        "Jl_inv21",
        "M",
        "_S",
        "acc_start",
        "acc_end",
    )

    def __init__(self, T1: np.ndarray, v1: np.ndarray, T2: np.ndarray, v2: np.ndarray, dt: float) -> None:
        self.dt = dt
        self.T1, self.v1, self.v2 = T1, v1, v2
        T21 = inv_T(T1) @ T2
        self.xi21, self.Jr_inv21 = logmap(T21)
        self.g21 = self.Jr_inv21 @ v2  # xi'(dt) in the local variable
        # Jl^-1(xi) = Jr^-1(xi) Ad(Exp(-xi))
        self.Jl_inv21 = self.Jr_inv21 @ adjoint_inv(T21)
        self.M = np.stack([dt * v1, self.xi21, dt * self.g21])
        self._S: np.ndarray | None = None
        self.acc_start: np.ndarray | None = None
        self.acc_end: np.ndarray | None = None

    @property
    def S(self) -> np.ndarray:
        """Derivatives (3x6x24) of ``(v1, xi21, g21)`` w.r.t. the segment's knot perturbations."""
        if self._S is None:
            S = np.zeros((3, POSE_DIM, 2 * STATE_DIM))
            S[0, :, 6:12] = np.eye(POSE_DIM)
            S[1, :, 0:6] = -self.Jl_inv21
            S[1, :, 12:18] = self.Jr_inv21
            D = d_jr_inv_times(self.xi21, self.v2)  # d(Jr^-1(xi) v2)/d xi at xi21
            S[2] = D @ S[1]
            S[2, :, 18:24] += self.Jr_inv21
            self._S = S
        return self._S


class KnotTrajectory:
    """Read-only queries over knot states: GP interpolation between knots, extrapolation after the last one.

    The smoother answers its own queries through one over its live cache (:meth:`TrajectorySmoother.state_at`) and
    publishes immutable copies (:meth:`TrajectorySmoother.snapshot`) for readers on other threads. ``times_ns``
    (N,), ``poses`` (N, 4, 4), ``vels`` (N, 6), ``seg_cov`` (N, 24, 24) (joint covariance of knots i, i+1),
    ``last_cov`` (12, 12) (the newest knot's marginal).

    Memos: per segment in :attr:`segments` (see :class:`Segment`; the live cache drops a segment whenever its knots
    change); with ``immutable`` (a snapshot: arrays nobody writes), per knot the square roots and correlations of
    the knots' covariances that :meth:`joint_covariance` uses (over the live cache they are recomputed: its
    covariances are updated in place). A memo entry is built whole before it is stored: readers on several threads
    at worst build one twice.
    """

    def __init__(
        self,
        times_ns: np.ndarray,
        poses: np.ndarray,
        vels: np.ndarray,
        seg_cov: np.ndarray,
        last_cov: np.ndarray,
        qc: np.ndarray,
        max_extrapolation_s: float,
        segments: dict[int, Segment] | None = None,
        immutable: bool = False,
    ) -> None:
        self.times_ns, self.poses, self.vels, self.seg_cov, self.last_cov = times_ns, poses, vels, seg_cov, last_cov
        self.n = len(times_ns)
        self.qc = qc  # (N, 6): per knot the PSD of the prior into it (the newest's: the extrapolation's)
        self.max_extrapolation_s = float(max_extrapolation_s)
        self.segments: dict[int, Segment] = {} if segments is None else segments
        # knot i: _psd_sqrt of its marginal; (knots i, i+1): their whitened correlation (None: no memo)
        self._roots: dict[int, np.ndarray] | None = {} if immutable else None
        self._corrs: dict[int, np.ndarray] | None = {} if immutable else None

    @property
    def first_time_ns(self) -> int | None:
        return int(self.times_ns[0]) if self.n else None

    @property
    def last_time_ns(self) -> int | None:
        return int(self.times_ns[self.n - 1]) if self.n else None

    def state_at(self, t_ns: int, *, with_covariance: bool = True) -> TrajectoryState:
        """State at ``t_ns`` (see :meth:`TrajectorySmoother.state_at`)."""
        t_ns = check_time(t_ns)
        i, at_knot = self._locate(t_ns)
        if at_knot:
            return self._knot_state(i, t_ns, with_covariance)
        if i == self.n - 1:
            return self._extrapolate(i, t_ns, with_covariance)
        return self._interpolate(i, t_ns, with_covariance)

    def _locate(self, t_ns: int) -> tuple[int, bool]:
        """``(i, at_knot)``: the last knot at or before ``t_ns`` and whether ``t_ns`` is its time; the range checks
        of :meth:`state_at` (EstimationError before the first knot or beyond the extrapolation limit)."""
        if self.n == 0:
            raise EstimationError("state_at: no measurement yet")
        t_first = int(self.times_ns[0])
        if t_ns < t_first:
            raise EstimationError(f"state_at: t_ns={t_ns} is before the first keyframe ({t_first})")
        i = int(np.searchsorted(self.times_ns[: self.n], t_ns, side="right")) - 1
        if int(self.times_ns[i]) == t_ns:
            return i, True
        if i == self.n - 1:
            ahead_s = (t_ns - int(self.times_ns[i])) / NS_PER_S
            if ahead_s > self.max_extrapolation_s:
                raise EstimationError(
                    f"state_at: t_ns={t_ns} is {ahead_s:.6g} s after the newest keyframe, beyond "
                    f"smoothing.max_extrapolation_s={self.max_extrapolation_s:g} s"
                )
        return i, False

    def fitted_acceleration(
        self, t_ns: int, window_s: float, T_sensor_point: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """World-frame acceleration (3,) of a point on the sensor at ``t_ns`` (default its origin; ``T_sensor_point``
        places another, e.g. the vehicle's origin) and its covariance (3x3): the slope of a weighted linear fit of
        the point's world-frame velocity at the knots within ``window_s`` of ``t_ns`` (tricube weights, continuous
        in time), each knot's velocity weighted by the inverse of its variance too. The covariance is the fit's,
        from the knots' velocity covariances (taken as independent: a conservative figure for neighbours the
        posterior correlates positively). Fewer than two knots in the window: zero with an infinite covariance.
        """
        t = check_time(t_ns)
        lo = int(np.searchsorted(self.times_ns[: self.n], t - int(window_s * NS_PER_S), side="left"))
        hi = int(np.searchsorted(self.times_ns[: self.n], t + int(window_s * NS_PER_S), side="right"))
        if hi - lo < 2:
            return np.zeros(3), np.full((3, 3), np.inf)
        dt = (self.times_ns[lo:hi] - t) / NS_PER_S
        w = np.clip(1.0 - np.abs(dt / window_s) ** 3, 0.0, None) ** 3
        R = self.poses[lo:hi, :3, :3]
        tw = self.vels[lo:hi]
        if T_sensor_point is not None:
            Ad = adjoint_inv(np.asarray(T_sensor_point, float))  # twist moved to the point's frame
            tw = tw @ Ad.T
            R = R @ np.asarray(T_sensor_point, float)[:3, :3]
        v_world = np.einsum("kij,kj->ki", R, tw[:, 3:])
        # each knot's linear-velocity covariance (the newest's marginal, the others' from their segment's joint)
        V = self.seg_cov[lo:hi, 9:12, 9:12].copy()
        if hi == self.n:
            V[-1] = self.last_cov[9:12, 9:12]
        var = np.trace(V, axis1=1, axis2=2) / 3.0
        w = w / np.maximum(var, PSD_RELATIVE_FLOOR)
        if np.count_nonzero(w > 0) < 2:
            return np.zeros(3), np.full((3, 3), np.inf)
        tbar = float(np.sum(w * dt) / np.sum(w))
        sxx = float(np.sum(w * (dt - tbar) ** 2))
        if sxx <= 0.0:
            return np.zeros(3), np.full((3, 3), np.inf)
        c = w * (dt - tbar) / sxx  # slope = sum c_k v_k
        acc = c @ v_world
        cov = np.einsum("k,kij,k->ij", c, np.einsum("kab,kbc,kdc->kad", R, V, R), c)
        return acc, 0.5 * (cov + cov.T)

    def joint_covariance(self, t_ns: np.ndarray) -> np.ndarray:
        """Joint covariance (12n x 12n) of the states at ``t_ns`` (n times, each within :meth:`state_at`'s range).

        Each state is a linear map (to first order) of the knots it is built from (its segment's two, or the newest
        one after the last knot) plus its own process noise: ``J Sigma_K J' + N``. ``Sigma_K``, the knots' joint
        covariance, is assembled from the joint covariance of consecutive knots (the posterior of a WNOA chain is a
        Markov chain: ``cov(x_a, x_c) = cov(x_a, x_b) cov(x_b)^-1 cov(x_b, x_c)`` for ``a < b < c``); the GP's
        conditional noise of each state enters its own block only (its cross-time terms are left out: within one
        segment they are smaller than the knots' part, across segments zero). The diagonal blocks are the covariances
        of :meth:`state_at` exactly and the cross-time blocks keep the correlations of ``J Sigma_K J'`` (a
        congruence: the matrix stays positive semi-definite).
        """
        times = [check_time(int(t)) for t in np.atleast_1d(np.asarray(t_ns))]
        maps: list[list[tuple[int, np.ndarray]]] = []
        owns: list[np.ndarray] = []  # each state's own covariance: state_at's, from the same Jacobian
        for t in times:
            i, at_knot = self._locate(t)  # the same range checks as state_at
            if at_knot:
                maps.append([(i, np.eye(STATE_DIM))])
                owns.append(self._knot_cov(i))
            elif i == self.n - 1:
                dt = (t - int(self.times_ns[i])) / NS_PER_S
                v = self.vels[i]
                E_xi, Jr = expmap(dt * v)
                F = extrapolation_jacobian(dt, v, E_xi, Jr)
                maps.append([(i, F)])
                owns.append(self._extrapolated_covariance(i, dt, v, Jr, F))
            else:
                seg = self._segment(i)
                tau = (t - int(self.times_ns[i])) / NS_PER_S
                xi, dxi, _ = local_variable(tau, seg.dt, seg.M)
                E_xi, Jr = expmap(xi)
                E = d_jr_times(xi, dxi)
                A = interpolation_jacobian(seg, tau, xi, dxi, E_xi, Jr, E)
                maps.append([(i, A[:, :STATE_DIM]), (i + 1, A[:, STATE_DIM:])])
                owns.append(self._interpolated_covariance(i, seg, tau, Jr, E, A))
        knots = [k for m in maps for k, _ in m]
        lo, hi = min(knots), max(knots)
        K = self._knot_joint(lo, hi)
        J = np.zeros((STATE_DIM * len(times), STATE_DIM * (hi - lo + 1)))
        for r, m in enumerate(maps):
            for k, Jk in m:
                J[r * STATE_DIM : (r + 1) * STATE_DIM, (k - lo) * STATE_DIM : (k - lo + 1) * STATE_DIM] = Jk
        C = J @ K @ J.T
        # the diagonal blocks become the marginals of state_at exactly (a state's own covariance, with its GP
        # noise), the cross-time blocks keep the correlations of J K J': a congruence, so the result stays PSD
        d = STATE_DIM
        L = np.zeros_like(C)
        for r, own in enumerate(owns):
            blk = slice(r * d, (r + 1) * d)
            L[blk, blk] = _psd_sqrt(own) @ _psd_sqrt(C[blk, blk], inverse=True)
        cov = L @ C @ L.T
        return 0.5 * (cov + cov.T)

    def _knot_joint(self, lo: int, hi: int) -> np.ndarray:
        """Joint covariance of knots ``lo..hi`` (see :meth:`joint_covariance`): each knot's marginal, and between
        knots the chain of consecutive pairs' correlations (each pair's from its own joint covariance), so that the
        matrix is positive semi-definite although the pairs were computed when different knots were the newest."""
        m, d = hi - lo + 1, STATE_DIM
        marg = [self._knot_cov(lo + a) for a in range(m)]
        roots = [self._knot_root(lo + a) for a in range(m)]
        corr = [self._knot_corr(lo + b - 1) for b in range(1, m)]  # whitened cross-correlation of knots (b-1, b)
        K = np.zeros((m * d, m * d))
        for a in range(m):
            K[a * d : (a + 1) * d, a * d : (a + 1) * d] = marg[a]
            R = np.eye(d)
            for b in range(a + 1, m):
                R = R @ corr[b - 1]
                blk = roots[a] @ R @ roots[b]
                K[a * d : (a + 1) * d, b * d : (b + 1) * d] = blk
                K[b * d : (b + 1) * d, a * d : (a + 1) * d] = blk.T
        return K

    def _knot_root(self, i: int) -> np.ndarray:
        """``_psd_sqrt`` of knot i's marginal (memo on an immutable instance)."""
        memo = self._roots
        root = None if memo is None else memo.get(i)
        if root is None:
            root = _psd_sqrt(self._knot_cov(i))
            if memo is not None:
                root = memo.setdefault(i, root)
        return root

    def _knot_corr(self, i: int) -> np.ndarray:
        """Whitened cross-correlation (12x12) of knots i and i+1 from their joint covariance (memo on an immutable
        instance)."""
        memo = self._corrs
        corr = None if memo is None else memo.get(i)
        if corr is None:
            d, P = STATE_DIM, self.seg_cov[i]
            corr = _psd_sqrt(P[:d, :d], inverse=True) @ P[:d, d:] @ _psd_sqrt(P[d:, d:], inverse=True)
            if memo is not None:
                corr = memo.setdefault(i, corr)
        return corr

    def _segment(self, i: int) -> Segment:
        seg = self.segments.get(i)
        if seg is None:
            dt = (int(self.times_ns[i + 1]) - int(self.times_ns[i])) / NS_PER_S
            seg = Segment(self.poses[i].copy(), self.vels[i].copy(), self.poses[i + 1], self.vels[i + 1].copy(), dt)
            self.segments[i] = seg
        return seg

    def _knot_cov(self, i: int) -> np.ndarray:
        if i == self.n - 1:
            return self.last_cov
        return self.seg_cov[i][:STATE_DIM, :STATE_DIM]

    def _knot_state(self, i: int, t_ns: int, with_cov: bool) -> TrajectoryState:
        if i < self.n - 1:
            acc = self._start_acceleration(self._segment(i))
        elif i > 0:
            acc = self._end_acceleration(self._segment(i - 1))
        else:
            acc = np.zeros(POSE_DIM)
        cov = self._knot_cov(i) if with_cov else None
        return TrajectoryState(t_ns, frozen(self.poses[i]), frozen(self.vels[i]), frozen(acc), frozen(cov), "knot")

    def _start_acceleration(self, seg: Segment) -> np.ndarray:
        """The mean acceleration at the segment's first knot (memo: on the segment; callers copy it)."""
        if seg.acc_start is None:
            seg.acc_start = self._segment_acceleration(seg, 0.0)
        return seg.acc_start

    def _end_acceleration(self, seg: Segment) -> np.ndarray:
        """The mean acceleration at the segment's second knot (memo: on the segment; callers copy it)."""
        if seg.acc_end is None:
            seg.acc_end = self._segment_acceleration(seg, seg.dt)
        return seg.acc_end

    def _segment_acceleration(self, seg: Segment, tau: float) -> np.ndarray:
        """``d/dt [Jr(xi) xi']`` at ``tau`` = ``Jr(xi) xi'' + (d(Jr(xi) xi')/d xi) xi'``."""
        xi, dxi, ddxi = local_variable(tau, seg.dt, seg.M)
        return jr(xi) @ ddxi + directional_d_jr(xi, dxi)

    def _interpolate(self, i: int, t_ns: int, with_cov: bool) -> TrajectoryState:
        seg = self._segment(i)
        tau = (t_ns - int(self.times_ns[i])) / NS_PER_S
        xi, dxi, ddxi = local_variable(tau, seg.dt, seg.M)
        E_xi, Jr = expmap(xi)
        T = seg.T1 @ E_xi
        vel = Jr @ dxi
        cov = None
        if with_cov:
            E = d_jr_times(xi, dxi)
            acc = Jr @ ddxi + E @ dxi
            A = interpolation_jacobian(seg, tau, xi, dxi, E_xi, Jr, E)
            cov = self._interpolated_covariance(i, seg, tau, Jr, E, A)
        else:
            acc = Jr @ ddxi + directional_d_jr(xi, dxi)
        return TrajectoryState(t_ns, frozen(T), frozen(vel), frozen(acc), frozen(cov), "interpolated")

    def _extrapolate(self, i: int, t_ns: int, with_cov: bool) -> TrajectoryState:
        dt = (t_ns - int(self.times_ns[i])) / NS_PER_S
        v = self.vels[i]
        xi = dt * v
        E_xi, Jr = expmap(xi)
        T = self.poses[i] @ E_xi
        acc = self._end_acceleration(self._segment(i - 1)) if i > 0 else np.zeros(POSE_DIM)
        cov = None
        if with_cov:
            cov = self._extrapolated_covariance(i, dt, v, Jr, extrapolation_jacobian(dt, v, E_xi, Jr))
        return TrajectoryState(t_ns, frozen(T), frozen(v), frozen(acc), frozen(cov), "extrapolated")

    def _interpolated_covariance(
        self, i: int, seg: Segment, tau: float, Jr: np.ndarray, E: np.ndarray, A: np.ndarray
    ) -> np.ndarray:
        """Covariance (12x12) of the state ``tau`` into segment i: the knots' part through ``A``
        (:func:`interpolation_jacobian`) plus the GP's conditional noise through ``noise_map(Jr, E)``."""
        B = noise_map(Jr, E)
        cov = A @ self.seg_cov[i] @ A.T + B @ kron_qc(wnoa_conditional_Q(tau, seg.dt), self.qc[i + 1]) @ B.T
        return 0.5 * (cov + cov.T)

    def _extrapolated_covariance(self, i: int, dt: float, v: np.ndarray, Jr: np.ndarray, F: np.ndarray) -> np.ndarray:
        """Covariance (12x12) of the state ``dt`` after the newest knot i at its twist ``v``: the knot's marginal
        through ``F`` (:func:`extrapolation_jacobian`) plus the prior's noise over ``dt``."""
        B = noise_map(Jr, d_jr_times(dt * v, v))
        cov = F @ self.last_cov @ F.T + B @ kron_qc(wnoa_Q(dt), self.qc[i]) @ B.T
        return 0.5 * (cov + cov.T)


#: eigenvalues of a covariance below this share of its largest are floored when it is inverted


PSD_RELATIVE_FLOOR = 1e-12


def _psd_sqrt(M: np.ndarray, inverse: bool = False) -> np.ndarray:
    """Symmetric square root (or its inverse) of a symmetric positive semi-definite matrix."""
    w, U = np.linalg.eigh(0.5 * (M + M.T))
    w = np.clip(w, PSD_RELATIVE_FLOOR * max(float(w.max()), 0.0) if inverse else 0.0, None)
    if inverse:
        w = np.where(w > 0.0, 1.0 / np.sqrt(np.where(w > 0.0, w, 1.0)), 0.0)
    else:
        w = np.sqrt(w)
    return (U * w) @ U.T


# ----------------------------------------------------------------------------------------------
# Jacobians of the query maps (checked against numerical differences in tests/state/test_smoothing.py)


def extrapolation_jacobian(
    dt: float, v: np.ndarray, E_xi: np.ndarray | None = None, Jr: np.ndarray | None = None
) -> np.ndarray:
    """Jacobian (12x12) of the extrapolated state ``(T_k Exp(dt v), v)`` w.r.t. the knot state ``(T_k, v)``.

    Perturbations: right on poses (``T Exp(delta)``), additive on twists. With ``xi = dt v``:
    ``delta_t = Ad(Exp(-xi)) delta_k + Jr(xi) dt dv`` and
    ``d varpi_t = dv`` (the extrapolated twist is ``Jr(xi) v = v`` since ``ad(xi) v = 0``).
    """
    xi = dt * v
    if E_xi is None or Jr is None:
        E_xi, Jr = expmap(xi)
    F = np.zeros((STATE_DIM, STATE_DIM))
    F[:6, :6] = adjoint_inv(E_xi)
    F[:6, 6:] = dt * Jr
    F[6:, 6:] = np.eye(POSE_DIM)
    return F


def interpolation_jacobian(
    seg: Segment,
    tau: float,
    xi: np.ndarray,
    dxi: np.ndarray,
    E_xi: np.ndarray,
    Jr: np.ndarray,
    E: np.ndarray | None = None,
) -> np.ndarray:
    """Jacobian (12x24) of the interpolated state at ``tau`` w.r.t. ``(T1, v1, T2, v2)`` of the segment.

    Perturbations: right on poses, additive on twists. With ``xi = Lam01 v1 + Psi00 xi21 + Psi01 g21``,
    ``xi' = Lam11 v1 + Psi10 xi21 + Psi11 g21``, ``g21 = Jr^-1(xi21) v2``:
    ``d xi21 = -Jl^-1(xi21) delta1 + Jr^-1(xi21) delta2``; ``d g21 = Jr^-1(xi21) dv2 + D d xi21``;
    ``delta_tau = Ad(Exp(-xi)) delta1 + Jr(xi) d xi``; ``d varpi = Jr(xi) d xi' + E d xi``, where
    ``D = d(Jr^-1(xi) v2)/d xi`` at ``xi21`` and ``E = d(Jr(xi) w)/d xi`` at ``(xi, xi')``.
    ``xi``, ``dxi`` are ``xi(tau)``, ``xi'(tau)``; ``E_xi``, ``Jr`` are ``Exp(xi)`` and ``Jr(xi)``.
    """
    W = hermite_matrix(tau, seg.dt)[:2] * np.array([seg.dt, 1.0, seg.dt])  # weights of (v1, xi21, g21)
    d = (W @ seg.S.reshape(3, -1)).reshape(2, POSE_DIM, 2 * STATE_DIM)
    if E is None:
        E = d_jr_times(xi, dxi)
    A = np.empty((STATE_DIM, 2 * STATE_DIM))
    A[:6] = Jr @ d[0]
    A[:6, 0:6] += adjoint_inv(E_xi)
    A[6:] = Jr @ d[1] + E @ d[0]
    return A


__all__ = [
    "JACOBIAN_STEP",
    "PSD_RELATIVE_FLOOR",
    "KnotStates",
    "KnotTrajectory",
    "Segment",
    "TrajectoryState",
    "adjoint",
    "adjoint_inv",
    "check_time",
    "d_jr_inv_times",
    "d_jr_times",
    "directional_d_jr",
    "expmap",
    "extrapolation_jacobian",
    "frozen",
    "interpolation_jacobian",
    "jr",
    "jr_inv",
    "logmap",
]
