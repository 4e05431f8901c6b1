"""Continuous-time trajectory smoothing with a white-noise-on-acceleration (WNOA) Gaussian-process prior.

The state at every keyframe time ``t_k`` (a *knot*) is the pose ``T_world_sensor`` (GTSAM ``Pose3``) and
the body-frame twist ``varpi_k = [omega, v]`` of the sensor (rad/s, m/s, in the sensor frame, GTSAM's
tangent order). Between knots the trajectory follows the WNOA prior (thesis §6.3.4, "STEAM"; Anderson
& Barfoot 2015) with power spectral density ``Qc = diag(qc_rot I3, qc_trans I3)`` (rad²/s³, m²/s³,
from :class:`vtr.config.SmoothingConfig`). GTSAM's own ``WnoaMotionFactorPose3`` carries the prior
(no Python factor in the hot path); its error between knots 1 and 2, ``dt = t2 - t1`` (s), is::

    xi_21 = Log(T1^-1 T2)                     (right / body-side convention)
    e     = [ xi_21 - dt varpi_1 ;  Jr^-1(xi_21) varpi_2 - varpi_1 ]
    cov   = [[dt³/3, dt²/2], [dt²/2, dt]] ⊗ Qc

The estimator is GTSAM's ``IncrementalFixedLagSmoother`` (ISAM2 inside) over ``config.lag_s``
seconds, so the cost per keyframe does not grow with the run (ISAM2 is told to reuse the slots of
marginalized factors, which it otherwise keeps forever).

Queries (:meth:`TrajectorySmoother.state_at`) use only cached knot states and GTSAM's closed-form
``Pose3`` maps, never the factor graph:

* inside the knots: GP interpolation in the local variable ``xi(tau) = Log(T1^-1 T(tau))``, whose
  posterior mean is the cubic Hermite curve through ``(0, varpi_1)`` at ``tau = 0`` and
  ``(xi_21, Jr^-1(xi_21) varpi_2)`` at ``tau = dt``; ``T(tau) = T1 Exp(xi(tau))`` and
  ``varpi(tau) = Jr(xi(tau)) xi'(tau)``;
* after the last knot: constant-velocity extrapolation ``T(t) = T_k Exp((t - t_k) varpi_k)`` (the
  thesis' ``Exp((t - t_k) varpi_k) T_k`` written for GTSAM's right-hand convention).

The WNOA algebra itself (transition matrix, process covariance, interpolation matrices, the Hermite
mean) is :mod:`vtr.state.wnoa` (numpy only); this module holds the GTSAM smoother and its queries.

Covariances are 12x12 over ``[pose perturbation (rot, trans), twist]`` where the pose perturbation is
GTSAM's right (body-frame) one, ``T = T_hat Exp(delta)``, as for every ``Pose3`` marginal in GTSAM.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, cast, overload

import gtsam
import numpy as np
from gtsam.symbol_shorthand import V, X

from ..config import SmoothingConfig, check_section
from ..conventions import NS_PER_S
from ..errors import ConfigError, EstimationError
from ..geometry import POSE_DIM, check_covariance, check_se3, inv_T, skew
from .wnoa import (
    STATE_DIM,
    hermite_matrix,
    kron_basis,
    kron_qc,
    local_variable,
    noise_map,
    wnoa_conditional_Q,
    wnoa_Q,
)

# Weak prior on the first knot's twist: only there so a single keyframe is a determined problem.
INITIAL_ANGULAR_VELOCITY_SIGMA = 10.0    # rad/s
INITIAL_LINEAR_VELOCITY_SIGMA = 100.0    # m/s

# ISAM2: relinearize any variable whose update exceeds this (rad, m, rad/s, m/s), at every update.
RELINEARIZE_THRESHOLD = 1e-6
RELINEARIZE_SKIP = 1
# ISAM2 back-substitution stops where the change falls below this (same units).
WILDFIRE_THRESHOLD = 1e-7
# Gauss-Newton iterations (ISAM2 updates) spent on each keyframe (the first adds it, the rest refine).
ITERATIONS_PER_KEYFRAME = 1
# Number of most recent knots whose joint covariance is recomputed after each keyframe; older
# segments keep their last snapshot (conservative: more data only shrinks a Gaussian posterior).
COVARIANCE_REFRESH_KNOTS = 2

# Input validation.

# Central-difference step for the derivative of Jr(xi) w with respect to xi (only in covariances
# and the acceleration estimate): truncation error O(step²), round-off O(1e-16 / step) ≈ 1e-10.
JACOBIAN_STEP = 1e-6

_INITIAL_CAPACITY = 256
_VELOCITY_SYMBOL = "v"           # gtsam symbol character of the twist keys V(i)


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
def _frozen(a: np.ndarray) -> np.ndarray: ...


@overload
def _frozen(a: None) -> None: ...


def _frozen(a: np.ndarray | None) -> np.ndarray | None:
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


def _check_time(t_ns: object, what: str = "t_ns") -> int:
    if isinstance(t_ns, bool) or not isinstance(t_ns, int | np.integer):
        raise EstimationError(f"{what}: expected an integer time in nanoseconds, got {type(t_ns).__name__}")
    t = int(t_ns)
    if not _T_NS_MIN <= t <= _T_NS_MAX:    # times are stored as int64: checked before anything is inserted
        raise EstimationError(f"{what}={t}: outside the int64 nanosecond range [{_T_NS_MIN}, {_T_NS_MAX}]")
    return t




# ----------------------------------------------------------------------------------------------
# Cache of knot states (numpy, growable, whole history)


class _KnotCache:
    """Numpy copies of knot means, their latest joint segment covariances and lazily built segment data."""

    def __init__(self) -> None:
        n = _INITIAL_CAPACITY
        self.n = 0
        self.times_ns = np.zeros(n, dtype=np.int64)
        self.poses = np.zeros((n, 4, 4))
        self.vels = np.zeros((n, POSE_DIM))
        # seg_cov[i]: joint covariance (24x24) of knots i and i+1, last snapshot.
        self.seg_cov = np.zeros((n, 2 * STATE_DIM, 2 * STATE_DIM))
        self.last_cov = np.zeros((STATE_DIM, STATE_DIM))     # marginal of the newest knot
        self.segments: dict[int, Segment] = {}

    def grow(self) -> None:
        cap = 2 * len(self.times_ns)
        for name in ("times_ns", "poses", "vels", "seg_cov"):
            old = getattr(self, name)
            new = np.zeros((cap,) + old.shape[1:], dtype=old.dtype)
            new[: self.n] = old[: self.n]
            setattr(self, name, new)


class Segment:
    """Per-segment quantities that depend only on the two knot states (computed on first use).

    ``M`` stacks the Hermite control vectors ``[dt v1, xi21, dt g21]`` (3x6) of the local variable; the
    derivative tensor ``S`` (3x6x24) holds ``d(v1, xi21, g21)/d(delta1, dv1, delta2, dv2)`` and is built
    only when a covariance is asked for.
    """

    __slots__ = ("dt", "T1", "v1", "v2", "xi21", "g21", "Jr_inv21", "Jl_inv21", "M", "_S")

    def __init__(self, T1: np.ndarray, v1: np.ndarray, T2: np.ndarray, v2: np.ndarray, dt: float) -> None:
        self.dt = dt
        self.T1, self.v1, self.v2 = T1, v1, v2
        T21 = inv_T(T1) @ T2
        self.xi21, self.Jr_inv21 = logmap(T21)
        self.g21 = self.Jr_inv21 @ v2                      # xi'(dt) in the local variable
        # Jl^-1(xi) = Jr^-1(xi) Ad(Exp(-xi))
        self.Jl_inv21 = self.Jr_inv21 @ adjoint_inv(T21)
        self.M = np.stack([dt * v1, self.xi21, dt * self.g21])
        self._S: np.ndarray | None = None

    @property
    def S(self) -> np.ndarray:
        """Derivatives (3x6x24) of ``(v1, xi21, g21)`` w.r.t. the segment's knot perturbations."""
        if self._S is None:
            S = np.zeros((3, POSE_DIM, 2 * STATE_DIM))
            S[0, :, 6:12] = np.eye(POSE_DIM)
            S[1, :, 0:6] = -self.Jl_inv21
            S[1, :, 12:18] = self.Jr_inv21
            D = d_jr_inv_times(self.xi21, self.v2)       # d(Jr^-1(xi) v2)/d xi at xi21
            S[2] = D @ S[1]
            S[2, :, 18:24] += self.Jr_inv21
            self._S = S
        return self._S


# ----------------------------------------------------------------------------------------------


class TrajectorySmoother:
    """Incremental WNOA trajectory smoother fed with keyframe pose measurements.

    Measurements at each keyframe time (int64 ns, strictly increasing) are either an absolute pose
    ``T_world_sensor`` (from localization, or the first keyframe of odometry) or a relative pose
    ``T_prev_cur`` from the previous keyframe (visual odometry), each with a 6x6 covariance in GTSAM's
    tangent order ``[rot (rad), trans (m)]`` (right perturbation). The first keyframe needs an
    absolute pose. Invalid input raises :class:`~vtr.errors.EstimationError` and leaves the smoother
    unchanged.

    Not thread-safe: if measurements and queries come from different threads, guard both with one
    lock (a query takes ~0.1 ms, an update a few ms). Memory grows by ~5 kB per keyframe (knot means
    and one 24x24 segment covariance), so that any past time can be queried.

    Args:
        config: ``qc_rotation`` (rad²/s³), ``qc_translation`` (m²/s³) and ``lag_s`` (s) are used.
        initial_velocity_sigma: standard deviations of the weak zero-mean prior on the first knot's
            twist, ``(angular rad/s, linear m/s)``.
    """

    def __init__(
        self,
        config: SmoothingConfig,
        *,
        initial_velocity_sigma: tuple[float, float] = (
            INITIAL_ANGULAR_VELOCITY_SIGMA,
            INITIAL_LINEAR_VELOCITY_SIGMA,
        ),
    ) -> None:
        check_section(config, "smoothing")
        if not all(s > 0 for s in initial_velocity_sigma):
            raise ConfigError("smoothing: initial velocity sigmas must be positive")
        self.config = config
        self.qc = np.array([config.qc_rotation] * 3 + [config.qc_translation] * 3)
        self._qc_basis = kron_basis(self.qc)
        self._velocity_prior_sigmas = np.array(
            [initial_velocity_sigma[0]] * 3 + [initial_velocity_sigma[1]] * 3
        )
        self._smoother = self._new_smoother()
        self._cache = _KnotCache()
        self._t0_ns: int | None = None
        self._window_start = 0            # index of the oldest knot still in the solver
        self._broken: str | None = None

    # -- public properties ---------------------------------------------------------------------

    @property
    def num_keyframes(self) -> int:
        """Number of knots added so far."""
        return self._cache.n

    @property
    def first_time_ns(self) -> int | None:
        return int(self._cache.times_ns[0]) if self._cache.n else None

    @property
    def last_time_ns(self) -> int | None:
        return int(self._cache.times_ns[self._cache.n - 1]) if self._cache.n else None

    @property
    def window_start_ns(self) -> int | None:
        """Time of the oldest knot still being optimized (older knots are final)."""
        return int(self._cache.times_ns[self._window_start]) if self._cache.n else None

    @property
    def q_psd(self) -> np.ndarray:
        """Diagonal of Qc in GTSAM order ``[rot x3 (rad²/s³), trans x3 (m²/s³)]``."""
        return self.qc.copy()

    @property
    def velocity_prior_sigmas(self) -> np.ndarray:
        """Standard deviations of the first knot's twist prior ``[angular x3 (rad/s), linear x3 (m/s)]``."""
        return self._velocity_prior_sigmas.copy()

    def knots(self) -> KnotStates:
        """Copies of all knot states (final ones and those still in the window)."""
        c = self._cache
        return KnotStates(c.times_ns[: c.n].copy(), c.poses[: c.n].copy(), c.vels[: c.n].copy())

    # -- measurements ----------------------------------------------------------------------------

    def add_pose(self, t_ns: int, T_world_sensor: np.ndarray, covariance: np.ndarray) -> None:
        """Add a keyframe at ``t_ns`` with an absolute pose measurement ``T_world_sensor`` (6x6 covariance)."""
        self.add_knot(t_ns, T_world_sensor=T_world_sensor, covariance=covariance)

    def add_relative_pose(self, t_ns: int, T_prev_cur: np.ndarray, covariance: np.ndarray) -> None:
        """Add a keyframe at ``t_ns`` measured by odometry ``T_prev_cur`` from the previous keyframe."""
        self.add_knot(t_ns, T_prev_cur=T_prev_cur, relative_covariance=covariance)

    def add_knot(
        self,
        t_ns: int,
        *,
        T_world_sensor: np.ndarray | None = None,
        covariance: np.ndarray | None = None,
        T_prev_cur: np.ndarray | None = None,
        relative_covariance: np.ndarray | None = None,
    ) -> None:
        """Add one knot at ``t_ns`` with an absolute and/or a relative (odometry) pose measurement.

        Args:
            t_ns: keyframe time (int ns), strictly after the previous keyframe.
            T_world_sensor: absolute pose (4x4), with ``covariance`` (6x6, ``[rot, trans]``, right
                perturbation).
            T_prev_cur: pose of this keyframe's sensor frame in the previous keyframe's (4x4), with
                ``relative_covariance`` (6x6).
        Raises:
            EstimationError: on any invalid input (the smoother is left unchanged), or if the solver
                fails (the smoother is then unusable).
        """
        if self._broken:
            raise EstimationError(f"smoother unusable after an earlier solver failure: {self._broken}")
        t_ns = _check_time(t_ns)
        c = self._cache
        if c.n:
            last = int(c.times_ns[c.n - 1])
            if t_ns == last:
                raise EstimationError(f"t_ns={t_ns}: duplicate keyframe time (one measurement set per time)")
            if t_ns < last:
                raise EstimationError(f"t_ns={t_ns}: out of order (last keyframe at {last})")
        if T_world_sensor is None and T_prev_cur is None:
            raise EstimationError("add_knot: needs T_world_sensor and/or T_prev_cur")
        if (T_world_sensor is None) != (covariance is None):
            raise EstimationError("add_knot: T_world_sensor and covariance go together")
        if (T_prev_cur is None) != (relative_covariance is None):
            raise EstimationError("add_knot: T_prev_cur and relative_covariance go together")
        if c.n == 0 and T_world_sensor is None:
            raise EstimationError("the first keyframe needs an absolute pose (T_world_sensor)")
        if T_world_sensor is not None:
            T_world_sensor = check_se3(T_world_sensor, "T_world_sensor")
            covariance = check_covariance(cast(np.ndarray, covariance), "covariance", definite=True)
        if T_prev_cur is not None:
            T_prev_cur = check_se3(T_prev_cur, "T_prev_cur")
            relative_covariance = check_covariance(cast(np.ndarray, relative_covariance), "relative_covariance",
                                                   definite=True)
        # -- all input valid: nothing below may leave a half-applied state except a solver failure.
        self._insert(t_ns, T_world_sensor, covariance, T_prev_cur, relative_covariance)

    def refine(self, iterations: int = 1) -> None:
        """Spend ``iterations`` more Gauss-Newton iterations (ISAM2 updates) on the current window."""
        if self._broken:
            raise EstimationError(f"smoother unusable after an earlier solver failure: {self._broken}")
        if self._cache.n == 0:
            return
        try:
            for _ in range(iterations):
                self._smoother.update()
        except RuntimeError as err:  # pragma: no cover - gtsam failure on valid input
            self._broken = str(err)
            raise EstimationError(f"smoother failed: {err}") from err
        self._refresh_cache()

    # -- queries ---------------------------------------------------------------------------------

    def state_at(self, t_ns: int, *, with_covariance: bool = True) -> TrajectoryState:
        """State at ``t_ns`` (int ns): GP interpolation between knots, extrapolation after the last one.

        Uses cached knot states only (no solver work): ~40 us without covariance, ~150 us with it.
        Times before the window (older than ``lag_s``) are answered from the final estimates of their
        knots. The covariance of the newest segment and knot is the current posterior; older segments
        keep the joint covariance computed when they were the newest (an over-estimate: later data only
        shrink it). Raises EstimationError for a time before the first keyframe, more than
        ``max_extrapolation_s`` after the newest one, or when nothing has been measured yet.
        """
        t_ns = _check_time(t_ns)
        c = self._cache
        if c.n == 0:
            raise EstimationError("state_at: no measurement yet")
        t_first = int(c.times_ns[0])
        if t_ns < t_first:
            raise EstimationError(f"state_at: t_ns={t_ns} is before the first keyframe ({t_first})")
        i = int(np.searchsorted(c.times_ns[: c.n], t_ns, side="right")) - 1
        if int(c.times_ns[i]) == t_ns:
            return self._knot_state(i, t_ns, with_covariance)
        if i == c.n - 1:
            ahead_s = (t_ns - int(c.times_ns[i])) / NS_PER_S
            if ahead_s > self.config.max_extrapolation_s:
                raise EstimationError(
                    f"state_at: t_ns={t_ns} is {ahead_s:.6g} s after the newest keyframe, beyond "
                    f"smoothing.max_extrapolation_s={self.config.max_extrapolation_s:g} s")
            return self._extrapolate(i, t_ns, with_covariance)
        return self._interpolate(i, t_ns, with_covariance)

    # -- internals: solver -----------------------------------------------------------------------

    def _new_smoother(self) -> gtsam.IncrementalFixedLagSmoother:
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(RELINEARIZE_THRESHOLD)
        params.relinearizeSkip = RELINEARIZE_SKIP
        params.setOptimizationParams(gtsam.ISAM2GaussNewtonParams(WILDFIRE_THRESHOLD))
        # Reuse the slots of marginalized factors: otherwise ISAM2's factor list grows with the run and
        # so does the cost of each update.
        params.findUnusedFactorSlots = True
        return gtsam.IncrementalFixedLagSmoother(self.config.lag_s, params)

    def _insert(self, t_ns, T_ws, cov, T_pc, rel_cov) -> None:
        c = self._cache
        k = c.n
        first = k == 0
        t0_ns = t_ns if first else cast(int, self._t0_ns)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        # Initial guess of the new knot.
        if T_ws is not None:
            T_init = T_ws
        else:
            T_init = c.poses[k - 1] @ T_pc
        if first:
            v_init = np.zeros(POSE_DIM)
        else:
            dt = (t_ns - int(c.times_ns[k - 1])) / NS_PER_S
            v_init = logmap(inv_T(c.poses[k - 1]) @ T_init)[0] / dt
        t_s = (t_ns - t0_ns) / NS_PER_S
        timestamps: dict[Any, float] = {X(k): t_s, V(k): t_s}
        values.insert(X(k), gtsam.Pose3(T_init))
        values.insert(V(k), v_init)
        if T_ws is not None:
            graph.add(gtsam.PriorFactorPose3(X(k), gtsam.Pose3(T_ws), gtsam.noiseModel.Gaussian.Covariance(cov)))
        if T_pc is not None:
            graph.add(
                gtsam.BetweenFactorPose3(
                    X(k - 1), X(k), gtsam.Pose3(T_pc), gtsam.noiseModel.Gaussian.Covariance(rel_cov)
                )
            )
        if first:
            graph.add(
                gtsam.PriorFactorVector6(
                    V(k), np.zeros(POSE_DIM), gtsam.noiseModel.Diagonal.Sigmas(self._velocity_prior_sigmas)
                )
            )
        else:
            t_prev_s = (int(c.times_ns[k - 1]) - t0_ns) / NS_PER_S
            graph.add(
                gtsam.WnoaMotionFactorPose3(
                    gtsam.StateData(X(k - 1), V(k - 1), t_prev_s), gtsam.StateData(X(k), V(k), t_s), self.qc
                )
            )
            # Keep the previous knot alive for as long as the new one (it is tied to it by the prior).
            timestamps[X(k - 1)] = t_s
            timestamps[V(k - 1)] = t_s
        try:
            self._smoother.update(graph, values, timestamps)
            for _ in range(ITERATIONS_PER_KEYFRAME - 1):
                self._smoother.update()
        except RuntimeError as err:  # pragma: no cover - gtsam failure on validated input
            self._broken = str(err)
            raise EstimationError(f"smoother failed at t_ns={t_ns}: {err}") from err
        # Commit the new knot to the cache.
        if first:
            self._t0_ns = t_ns
        if c.n == len(c.times_ns):
            c.grow()
        c.times_ns[k] = t_ns
        c.n += 1
        self._refresh_cache()

    def _refresh_cache(self) -> None:
        """Copy the window's knot estimates and the newest joint covariances into the numpy cache."""
        c = self._cache
        est = self._smoother.calculateEstimate()
        # One call each for all poses / twists of the window, in key (= knot index) order.
        poses = gtsam.utilities.extractPose3(est)                  # rows: R (row-major 9), t (3)
        vels = gtsam.utilities.extractVectors(est, _VELOCITY_SYMBOL)
        m = len(poses)
        start = c.n - m
        if m != len(vels) or start < self._window_start:  # pragma: no cover - gtsam contract
            raise EstimationError("smoother window is not a contiguous run of knots")
        c.poses[start : c.n, :3, :3] = poses[:, :9].reshape(m, 3, 3)
        c.poses[start : c.n, :3, 3] = poses[:, 9:]
        c.poses[start : c.n, 3] = (0.0, 0.0, 0.0, 1.0)
        c.vels[start : c.n] = vels
        for i in range(self._window_start - 1, c.n):
            c.segments.pop(i, None)
        self._window_start = start
        # Joint covariance of the newest knots (one ISAM2 query), split into segment blocks.
        lo = max(self._window_start, c.n - COVARIANCE_REFRESH_KNOTS)
        keys = []
        for i in range(lo, c.n):
            keys += [X(i), V(i)]
        joint = self._smoother.getISAM2().jointMarginalCovariance(keys).fullMatrix()
        joint = 0.5 * (joint + joint.T)
        for j, i in enumerate(range(lo, c.n - 1)):
            s = j * STATE_DIM
            c.seg_cov[i] = joint[s : s + 2 * STATE_DIM, s : s + 2 * STATE_DIM]
        c.last_cov = joint[-STATE_DIM:, -STATE_DIM:].copy()

    # -- internals: queries ----------------------------------------------------------------------

    def _segment(self, i: int) -> Segment:
        c = self._cache
        seg = c.segments.get(i)
        if seg is None:
            dt = (int(c.times_ns[i + 1]) - int(c.times_ns[i])) / NS_PER_S
            seg = Segment(c.poses[i].copy(), c.vels[i].copy(), c.poses[i + 1], c.vels[i + 1].copy(), dt)
            c.segments[i] = seg
        return seg

    def _knot_cov(self, i: int) -> np.ndarray:
        c = self._cache
        if i == c.n - 1:
            return c.last_cov
        return c.seg_cov[i][:STATE_DIM, :STATE_DIM]

    def _knot_state(self, i: int, t_ns: int, with_cov: bool) -> TrajectoryState:
        c = self._cache
        if i < c.n - 1:
            seg = self._segment(i)
            acc = self._segment_acceleration(seg, 0.0)
        elif i > 0:
            seg = self._segment(i - 1)
            acc = self._segment_acceleration(seg, seg.dt)
        else:
            acc = np.zeros(POSE_DIM)
        cov = self._knot_cov(i) if with_cov else None
        return TrajectoryState(t_ns, _frozen(c.poses[i]), _frozen(c.vels[i]), _frozen(acc), _frozen(cov), "knot")

    def _segment_acceleration(self, seg: Segment, tau: float) -> np.ndarray:
        """``d/dt [Jr(xi) xi']`` at ``tau`` = ``Jr(xi) xi'' + (d(Jr(xi) xi')/d xi) xi'``."""
        xi, dxi, ddxi = local_variable(tau, seg.dt, seg.M)
        return jr(xi) @ ddxi + directional_d_jr(xi, dxi)

    def _interpolate(self, i: int, t_ns: int, with_cov: bool) -> TrajectoryState:
        c = self._cache
        seg = self._segment(i)
        tau = (t_ns - int(c.times_ns[i])) / NS_PER_S
        xi, dxi, ddxi = local_variable(tau, seg.dt, seg.M)
        E_xi, Jr = expmap(xi)
        T = seg.T1 @ E_xi
        vel = Jr @ dxi
        cov = None
        if with_cov:
            E = d_jr_times(xi, dxi)
            acc = Jr @ ddxi + E @ dxi
            A = interpolation_jacobian(seg, tau, xi, dxi, E_xi, Jr, E)
            B = noise_map(Jr, E)
            cov = A @ c.seg_cov[i] @ A.T + B @ kron_qc(wnoa_conditional_Q(tau, seg.dt), self._qc_basis) @ B.T
            cov = 0.5 * (cov + cov.T)
        else:
            acc = Jr @ ddxi + directional_d_jr(xi, dxi)
        return TrajectoryState(t_ns, _frozen(T), _frozen(vel), _frozen(acc), _frozen(cov), "interpolated")

    def _extrapolate(self, i: int, t_ns: int, with_cov: bool) -> TrajectoryState:
        c = self._cache
        dt = (t_ns - int(c.times_ns[i])) / NS_PER_S
        v = c.vels[i]
        xi = dt * v
        E_xi, Jr = expmap(xi)
        T = c.poses[i] @ E_xi
        if i > 0:
            seg = self._segment(i - 1)
            acc = self._segment_acceleration(seg, seg.dt)
        else:
            acc = np.zeros(POSE_DIM)
        cov = None
        if with_cov:
            F = extrapolation_jacobian(dt, v, E_xi, Jr)
            B = noise_map(Jr, d_jr_times(xi, v))
            cov = F @ c.last_cov @ F.T + B @ kron_qc(wnoa_Q(dt), self._qc_basis) @ B.T
            cov = 0.5 * (cov + cov.T)
        return TrajectoryState(t_ns, _frozen(T), _frozen(v), _frozen(acc), _frozen(cov), "extrapolated")


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
    W = hermite_matrix(tau, seg.dt)[:2] * np.array([seg.dt, 1.0, seg.dt])   # weights of (v1, xi21, g21)
    d = (W @ seg.S.reshape(3, -1)).reshape(2, POSE_DIM, 2 * STATE_DIM)
    if E is None:
        E = d_jr_times(xi, dxi)
    A = np.empty((STATE_DIM, 2 * STATE_DIM))
    A[:6] = Jr @ d[0]
    A[:6, 0:6] += adjoint_inv(E_xi)
    A[6:] = Jr @ d[1] + E @ d[0]
    return A


__all__ = [
    "KnotStates",
    "Segment",
    "TrajectorySmoother",
    "TrajectoryState",
    "adjoint",
    "adjoint_inv",
    "d_jr_inv_times",
    "d_jr_times",
    "directional_d_jr",
    "expmap",
    "extrapolation_jacobian",
    "interpolation_jacobian",
    "jr",
    "jr_inv",
    "logmap",
]
