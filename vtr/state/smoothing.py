"""Continuous-time trajectory smoothing with a white-noise-on-acceleration (WNOA) Gaussian-process prior (thesis
§6.3.4, "STEAM"). Each knot holds the pose ``T_world_sensor`` and the body-frame twist ``[omega, v]``; GTSAM's own
``WnoaMotionFactorPose3`` links consecutive knots with ``Qc`` (:class:`vtr.config.SmoothingConfig`), inside GTSAM's
``IncrementalFixedLagSmoother`` over ``lag_s`` seconds. Queries (:meth:`TrajectorySmoother.state_at`) use cached knot
states only: GP interpolation between knots, constant-velocity extrapolation after the last; covariances are 12x12
over ``[pose (rot, trans) as GTSAM's right perturbation, twist]``. The WNOA algebra is :mod:`vtr.state.wnoa`; the
factor, the queries and their covariances: docs/smoother.md."""

from __future__ import annotations

from typing import Any, cast

import gtsam
import numpy as np
from gtsam.symbol_shorthand import V, X

from ..config import SmoothingConfig
from ..conventions import NS_PER_S
from ..errors import ConfigError, EstimationError
from ..geometry import POSE_DIM, check_covariance, check_se3, inv_T
from .trajectory import (
    JACOBIAN_STEP,
    KnotStates,
    KnotTrajectory,
    Segment,
    TrajectoryState,
    adjoint,
    adjoint_inv,
    check_time,
    d_jr_inv_times,
    d_jr_times,
    directional_d_jr,
    expmap,
    extrapolation_jacobian,
    interpolation_jacobian,
    jr,
    jr_inv,
    logmap,
)
from .wnoa import STATE_DIM

# Weak prior on the first knot's twist: only there so a single keyframe is a determined problem.
INITIAL_ANGULAR_VELOCITY_SIGMA = 10.0  # rad/s
INITIAL_LINEAR_VELOCITY_SIGMA = 100.0  # m/s

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

_INITIAL_CAPACITY = 256
_VELOCITY_SYMBOL = "v"  # gtsam symbol character of the twist keys V(i)


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
        self.qc = np.zeros((n, POSE_DIM))  # qc[i]: the PSD of the prior factor into knot i (knot 0: configured)
        self.last_cov = np.zeros((STATE_DIM, STATE_DIM))  # marginal of the newest knot
        self.segments: dict[int, Segment] = {}

    def grow(self) -> None:
        cap = 2 * len(self.times_ns)
        for name in ("times_ns", "poses", "vels", "seg_cov", "qc"):
            old = getattr(self, name)
            new = np.zeros((cap,) + old.shape[1:], dtype=old.dtype)
            new[: self.n] = old[: self.n]
            setattr(self, name, new)


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
        if not all(s > 0 for s in initial_velocity_sigma):
            raise ConfigError("smoothing: initial velocity sigmas must be positive")
        self.config = config
        self.qc = np.array([config.qc_rotation] * 3 + [config.qc_translation] * 3)
        self._velocity_prior_sigmas = np.array([initial_velocity_sigma[0]] * 3 + [initial_velocity_sigma[1]] * 3)
        self._smoother = self._new_smoother()
        self._cache = _KnotCache()
        self._t0_ns: int | None = None
        self._window_start = 0  # index of the oldest knot still in the solver
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
        qc: np.ndarray | None = None,
    ) -> None:
        """Add one knot at ``t_ns`` with an absolute and/or a relative (odometry) pose measurement.

        Args:
            t_ns: keyframe time (int ns), strictly after the previous keyframe.
            T_world_sensor: absolute pose (4x4), with ``covariance`` (6x6, ``[rot, trans]``, right
                perturbation).
            T_prev_cur: pose of this keyframe's sensor frame in the previous keyframe's (4x4), with
                ``relative_covariance`` (6x6).
            qc: the PSD (6,) of the motion prior from the previous knot to this one and of the extrapolation
                after it (e.g. :class:`~vtr.state.wnoa.MotionPsd`); None: the configured ``Qc``.
        Raises:
            EstimationError: on any invalid input (the smoother is left unchanged), or if the solver
                fails (the smoother is then unusable).
        """
        if self._broken:
            raise EstimationError(f"smoother unusable after an earlier solver failure: {self._broken}")
        t_ns = check_time(t_ns)
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
            relative_covariance = check_covariance(
                cast(np.ndarray, relative_covariance), "relative_covariance", definite=True
            )
        if qc is None:
            qc = self.qc
        else:
            qc = np.asarray(qc, float)
            if qc.shape != (POSE_DIM,) or not np.all(np.isfinite(qc)) or not np.all(qc > 0):
                raise EstimationError(f"add_knot: qc must be 6 positive finite numbers, got {qc!r}")
        # -- all input valid: nothing below may leave a half-applied state except a solver failure.
        self._insert(t_ns, T_world_sensor, covariance, T_prev_cur, relative_covariance, qc)

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
        return self._view().state_at(t_ns, with_covariance=with_covariance)

    def snapshot(self, since_ns: int | None = None) -> KnotTrajectory:
        """An immutable copy of the knots from the last one at or before ``since_ns`` (all knots when None) to
        the newest, with their covariances: the same queries as :meth:`state_at`, answerable on any thread while
        the smoother goes on (the copy is ~5 kB per knot)."""
        c = self._cache
        lo = 0
        if since_ns is not None and c.n:
            lo = max(0, int(np.searchsorted(c.times_ns[: c.n], int(since_ns), side="right")) - 1)
        return KnotTrajectory(
            c.times_ns[lo : c.n].copy(),
            c.poses[lo : c.n].copy(),
            c.vels[lo : c.n].copy(),
            c.seg_cov[lo : c.n].copy(),
            c.last_cov.copy(),
            c.qc[lo : c.n].copy(),
            self.config.max_extrapolation_s,
            immutable=True,
        )

    def _view(self) -> KnotTrajectory:
        """The queries over the live cache (no copy; the segment memo is the cache's)."""
        c = self._cache
        return KnotTrajectory(
            c.times_ns[: c.n],
            c.poses[: c.n],
            c.vels[: c.n],
            c.seg_cov[: c.n],
            c.last_cov,
            c.qc[: c.n],
            self.config.max_extrapolation_s,
            segments=c.segments,
        )

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

    def _insert(
        self,
        t_ns: int,
        T_ws: np.ndarray | None,
        cov: np.ndarray | None,
        T_pc: np.ndarray | None,
        rel_cov: np.ndarray | None,
        qc: np.ndarray,
    ) -> None:
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
        if T_ws is not None and cov is not None:  # given together (add_knot checked)
            graph.add(gtsam.PriorFactorPose3(X(k), gtsam.Pose3(T_ws), gtsam.noiseModel.Gaussian.Covariance(cov)))
        if T_pc is not None and rel_cov is not None:
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
                    gtsam.StateData(X(k - 1), V(k - 1), t_prev_s), gtsam.StateData(X(k), V(k), t_s), qc
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
        c.qc[k] = qc
        c.n += 1
        self._refresh_cache()

    def _refresh_cache(self) -> None:
        """Copy the window's knot estimates and the newest joint covariances into the numpy cache."""
        c = self._cache
        est = self._smoother.calculateEstimate()
        # One call each for all poses / twists of the window, in key (= knot index) order.
        poses = gtsam.utilities.extractPose3(est)  # rows: R (row-major 9), t (3)
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


__all__ = [
    "JACOBIAN_STEP",
    "KnotStates",
    "KnotTrajectory",
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
