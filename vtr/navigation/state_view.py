"""What a controller reads of a repeat, immutable: the taught route's frames (:class:`RouteFrames`), the state as of
one step (:class:`RepeatStateView`: the smoother's knots, the chain's verdict per vertex, the frame times) and the
records its queries return (:class:`StateTable`, :class:`OutputWindow`), with the commands a controller sent
(:class:`CommandLog`). :class:`~vtr.navigation.repeat_state.RepeatStateEstimator` builds the views; any thread may
query one (docs/smoother.md, docs/online.md).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import numpy as np

from ..conventions import NS_PER_S
from ..errors import DataError, EstimationError, NotLocalizedError
from ..geometry import check_se3, inv_T
from ..map import TaughtPath
from ..state.controller import (
    ControllerState,
    PathError,
    ReferencePath,
    StateStatus,
    controller_state_unchecked,
    gravity_aligned_T_o_t,
    output_jacobian_unchecked,
)
from ..state.trajectory import KnotTrajectory, TrajectoryState, adjoint
from .trunk import BACKWARD


@dataclass(frozen=True)
class StateTable:
    """Controller states at a list of times (arrays over the rows; written as ``state.csv`` by
    :mod:`vtr.app.runfiles.state_csv`).

    ``position``, ``velocity``, ``acceleration`` (N, 3) of the vehicle origin in o (m, m/s, m/s²), ``yaw``
    (N,) rad, ``trunk_id`` (N,) map ids, ``lateral``/``vertical``/``along_track`` (N,) m (lateral positive to the
    left of the direction of travel), ``localized`` (N,) bool (``status == "localized"``), ``direction`` (N,)
    +1/-1/0 and ``status`` (N,) :class:`~vtr.state.controller.StateStatus` values.
    """

    t_ns: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    yaw: np.ndarray
    trunk_id: np.ndarray
    lateral: np.ndarray
    vertical: np.ndarray
    along_track: np.ndarray
    localized: np.ndarray | None = None  # (N,) bool: the chain held a localization at that time
    direction: np.ndarray | None = None  # (N,) int: +1 taught order, -1 backward, 0 not decided
    status: np.ndarray | None = None  # (N,) str: StateStatus values
    position_sigma: np.ndarray | None = None  # (N, 3) m: standard deviations of position in o
    velocity_sigma: np.ndarray | None = None  # (N, 3) m/s: likewise of velocity

    def __len__(self) -> int:
        return len(self.t_ns)


class SegmentedTrajectory:
    """The knots of a run cut by pauses: one :class:`~vtr.state.smoothing.KnotTrajectory` per segment, each time
    answered by the segment it falls in (the latest that starts at or before it); no segment bridges a pause."""

    def __init__(self, segments: list[KnotTrajectory]) -> None:
        self.segments = [seg for seg in segments if seg.n]
        self.starts = np.array([seg.first_time_ns for seg in self.segments], np.int64)
        self.n = sum(seg.n for seg in self.segments)

    @property
    def first_time_ns(self) -> int | None:
        return self.segments[0].first_time_ns if self.segments else None

    @property
    def last_time_ns(self) -> int | None:
        return self.segments[-1].last_time_ns if self.segments else None

    def _segment(self, t_ns: int) -> KnotTrajectory:
        if not self.segments:
            raise EstimationError("state_at: no measurement yet")
        return self.segments[max(0, int(np.searchsorted(self.starts, int(t_ns), side="right")) - 1)]

    def state_at(self, t_ns: int, *, with_covariance: bool = True) -> TrajectoryState:
        return self._segment(t_ns).state_at(t_ns, with_covariance=with_covariance)

    def fitted_acceleration(
        self, t_ns: int, window_s: float, T_sensor_point: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        return self._segment(t_ns).fitted_acceleration(t_ns, window_s, T_sensor_point)

    def joint_covariance(self, t_ns: np.ndarray) -> np.ndarray:
        """Per segment (:meth:`KnotTrajectory.joint_covariance`); states in different segments are independent."""
        t = np.atleast_1d(np.asarray(t_ns, np.int64))
        which = np.maximum(np.searchsorted(self.starts, t, side="right") - 1, 0)
        cov = np.zeros((12 * len(t), 12 * len(t)))
        for k in np.unique(which):
            rows = np.flatnonzero(which == k)
            block = self.segments[int(k)].joint_covariance(t[rows])
            idx = (12 * rows[:, None] + np.arange(12)).ravel()
            cov[np.ix_(idx, idx)] = block
        return cov


@dataclass(frozen=True)
class CommandLog:
    """Accelerations a controller commanded (the vehicle origin's, in the map's gravity frame g, m/s²), each held
    from its time to the next one's (zero-order hold): ``t_ns`` (N,) increasing, ``acceleration_g`` (N, 3)."""

    t_ns: np.ndarray
    acceleration_g: np.ndarray

    def integrate(self, t0_ns: int, t1_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(dp, dv, a)``: the displacement and velocity change (g) the commands add between ``t0`` and ``t1`` over
        constant velocity (zeros when ``t1 <= t0``), and the command in force at ``t1`` (zero before the first
        command): differences of :meth:`motion`."""
        p1, v1, a1 = self.motion(t1_ns)
        if t1_ns <= t0_ns:
            return np.zeros(3), np.zeros(3), a1
        p0, v0, _ = self.motion(t0_ns)
        return p1 - p0 - v0 * ((t1_ns - t0_ns) / NS_PER_S), v1 - v0, a1

    @functools.cached_property
    def _at_commands(self) -> tuple[np.ndarray, np.ndarray]:
        """Position and velocity (N, 3) of the commanded motion alone at each command's time (from rest)."""
        a = np.asarray(self.acceleration_g, float).reshape(-1, 3)
        d = np.diff(np.asarray(self.t_ns, np.int64)).astype(float)[:, None] / NS_PER_S
        v = np.vstack([np.zeros((1, 3)), np.cumsum(a[:-1] * d, axis=0)])
        p = np.vstack([np.zeros((1, 3)), np.cumsum(v[:-1] * d + 0.5 * a[:-1] * d * d, axis=0)])
        return p, v

    def motion(self, t_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(p, v, a)`` (g) of the commanded motion alone at ``t_ns``: at rest at the origin until the first
        command, then each acceleration held to the next (``integrate(t0, t1)`` is its difference from the constant
        velocity it had at ``t0``). Zeros before the first command."""
        j = int(np.searchsorted(self.t_ns, t_ns, side="right")) - 1
        if j < 0:
            return np.zeros(3), np.zeros(3), np.zeros(3)
        p, v = self._at_commands
        a = np.asarray(self.acceleration_g, float).reshape(-1, 3)[j]
        d = (int(t_ns) - int(self.t_ns[j])) / NS_PER_S
        return p[j] + v[j] * d + 0.5 * a * d * d, v[j] + a * d, a.copy()


@dataclass(frozen=True)
class OutputWindow:
    """Outputs ``y = (p, psi)`` at ``t_ns`` (n,) in one frame: the o of trunk ``trunk_id`` (``T_g_o`` places it in the
    map's gravity frame g). ``position`` (n, 3) m, ``yaw`` (n,) rad (unwrapped), ``covariance`` (4n, 4n) over
    ``(p_x, p_y, p_z, psi)`` per sample, sample after sample; ``status`` (n,) :class:`StateStatus` values."""

    t_ns: np.ndarray
    position: np.ndarray
    yaw: np.ndarray
    covariance: np.ndarray
    trunk_id: int
    T_g_o: np.ndarray
    status: np.ndarray

    @property
    def outputs(self) -> np.ndarray:
        """``y`` (n, 4): position and yaw per sample."""
        return np.column_stack([self.position, self.yaw])


class RouteFrames:
    """The taught route as the controller state sees it (immutable once built; the memos of each trunk's frames and
    reference path and of the vehicle's mount fill on first use, from any thread: entries are pure functions of the
    route, built whole before they are stored, so a race at worst builds one twice). The memo's transforms are
    read-only and validated once (``check_se3``, as :func:`~vtr.state.controller.controller_state` does on every
    call)."""

    def __init__(
        self,
        path: TaughtPath,
        T_sensor_vehicle: np.ndarray,
        C_g_world: np.ndarray,
        trunk_window: tuple[int, int],
        off_route_distance_m: float,
        max_gap_s: float,
        acceleration_window_s: float = 0.0,
    ) -> None:
        self.path = path
        self.T_sensor_vehicle = T_sensor_vehicle
        self.C_g_world = C_g_world
        self.trunk_window = trunk_window
        self.off_route_distance_m = off_route_distance_m
        self.max_gap_s = max_gap_s
        self.acceleration_window_s = float(acceleration_window_s)
        self.T_world_trunk = path.T_world_vertex @ T_sensor_vehicle  # taught vehicle poses, teach world
        self.arc = path.arc_length_m(T_sensor_vehicle)
        self._memo: dict[tuple[int, int], tuple[np.ndarray, ReferencePath | None, float]] = {}
        self._frames: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}  # k: (T_world_trunk, T_o_t, T_g_o)
        self._mount: tuple[np.ndarray, np.ndarray] | None = None  # (T_sensor_vehicle, its Ad_vs), validated

    def trunk_frame(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """``(T_world_trunk, T_o_t)`` of the taught vertex at path index k (vehicle frame, teach world; ``T_o_t``
        read-only, from the memo)."""
        T_wt = self.T_world_trunk[k]
        return T_wt, self.trunk_frames(k)[1]

    def T_g_o(self, k: int) -> np.ndarray:
        """The frame o of trunk k in the map's gravity-aligned frame g (4x4): ``T_g_world T_world_t inv(T_o_t)``
        (a copy of the memo's)."""
        return self.trunk_frames(k)[2].copy()

    def trunk_frames(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(T_world_trunk, T_o_t, T_g_o)`` of trunk k, read-only, ``T_world_trunk`` validated (memo)."""
        hit = self._frames.get(k)
        if hit is None:
            T_wt = self.T_world_trunk[k]
            T_o_t = gravity_aligned_T_o_t(self.C_g_world @ T_wt[:3, :3])
            T_g_world = np.eye(4)
            T_g_world[:3, :3] = self.C_g_world
            T_g_o = T_g_world @ T_wt @ inv_T(T_o_t)
            T_wt = check_se3(T_wt, "T_world_trunk").copy()
            for T in (T_wt, T_o_t, T_g_o):
                T.setflags(write=False)
            hit = self._frames.setdefault(k, (T_wt, T_o_t, T_g_o))
        return hit

    def mount(self) -> tuple[np.ndarray, np.ndarray]:
        """``(T_sensor_vehicle, Ad_vs)``: the mount validated and the adjoint ``adjoint(inv_T(T_sensor_vehicle))``
        that moves a sensor twist to the vehicle (memo)."""
        hit = self._mount
        if hit is None:
            T_sv = check_se3(self.T_sensor_vehicle, "T_sensor_vehicle")
            hit = self._mount = (T_sv, adjoint(inv_T(T_sv)))
        return hit

    def trunk(self, k: int, direction: int = 1) -> tuple[np.ndarray, ReferencePath | None, float]:
        """``T_o_t``, the reference path in o around trunk k (its window mirrored for a route travelled backward),
        and the arc length at the path's first point."""
        key = (k, BACKWARD if direction == BACKWARD else 1)
        hit = self._memo.get(key)
        if hit is None:
            T_wt, T_o_t = self.trunk_frame(k)
            back, forward = self.trunk_window if key[1] == 1 else self.trunk_window[::-1]
            lo, hi = self.path.window(k, back, forward)
            try:
                path = ReferencePath.from_world(self.T_world_trunk[lo:hi], T_wt, T_o_t)
            except EstimationError:  # fewer than two distinct taught vertices
                path = None
            hit = self._memo.setdefault(key, (T_o_t, path, float(self.arc[lo])))
        return hit


@dataclass(frozen=True)
class RepeatStateView:
    """The repeat's controller state as of one step, immutable (:meth:`RepeatStateEstimator.view`): the smoother's
    knots (a :class:`~vtr.state.smoothing.KnotTrajectory`), the chain's verdict per vertex and the frame times."""

    route: RouteFrames
    trajectory: KnotTrajectory | SegmentedTrajectory
    vertex_t_ns: np.ndarray
    vertex_trunk: np.ndarray
    vertex_localized: np.ndarray
    vertex_ever: np.ndarray  # a localization at or before the vertex (the whole run's, not the view's)
    vertex_direction: np.ndarray
    vertex_off_route: np.ndarray
    frame_t_ns: np.ndarray
    unknown: str | None = None
    # per vertex the map's placement error (6x6, right perturbation of the sensor pose, as the localization's) of the
    # latest localization at or before it: an error of the frame the state is localized in, added to every state
    # (not averaged by the smoother, docs/online.md "Covariance"); None: nothing added
    vertex_frame_covariance: np.ndarray | None = None

    @property
    def last_frame_t_ns(self) -> int | None:
        return int(self.frame_t_ns[-1]) if len(self.frame_t_ns) else None

    def _vertex_at(self, t_ns: np.ndarray) -> np.ndarray:
        """Index of the latest vertex at or before each time (-1 before the first)."""
        return np.searchsorted(self.vertex_t_ns, np.asarray(t_ns, np.int64), side="right") - 1

    def trunk_index_at(self, t_ns: np.ndarray) -> np.ndarray:
        """Path index of the chain's trunk at the latest vertex at or before each time."""
        t = np.atleast_1d(np.asarray(t_ns, np.int64))
        if not len(self.vertex_t_ns):
            return np.zeros(len(t), np.int64)
        return self.vertex_trunk[np.maximum(self._vertex_at(t), 0)]

    def direction_at(self, t_ns: np.ndarray) -> np.ndarray:
        """The chain's direction of travel (+1, -1; 0 undecided) at the latest vertex at or before each time."""
        t = np.atleast_1d(np.asarray(t_ns, np.int64))
        if not len(self.vertex_t_ns):
            return np.zeros(len(t), np.int64)
        i = self._vertex_at(t)
        return np.where(i >= 0, self.vertex_direction[np.maximum(i, 0)], 0)

    def status_at(self, t_ns: np.ndarray, along_track_m: np.ndarray) -> np.ndarray:
        """:class:`StateStatus` values (N,) of states at ``t_ns`` whose arc length along the taught path is
        ``along_track_m``: ``unknown`` before the chain first held a localization or more than
        ``smoothing.max_extrapolation_s`` after the latest frame (a pause: no measurement bridges it);
        ``off_route`` beyond either end of the route by more than ``off_route_distance_m`` (or where the chain's
        attempt said so); ``localized`` where the chain's verdict at the latest vertex is localized; otherwise
        ``dead_reckoning``."""
        t = np.atleast_1d(np.asarray(t_ns, np.int64))
        along = np.atleast_1d(np.asarray(along_track_m, float))
        loc = ever = off = np.zeros(len(t), bool)
        if len(self.vertex_t_ns):
            i = self._vertex_at(t)
            has, ii = i >= 0, np.maximum(i, 0)
            loc, ever, off = (
                self.vertex_localized[ii] & has,
                self.vertex_ever[ii] & has,
                self.vertex_off_route[ii] & has,
            )
        f = np.searchsorted(self.frame_t_ns, t, side="right") - 1
        gap_ns = self.route.max_gap_s * NS_PER_S
        latest = self.frame_t_ns[np.maximum(f, 0)] if len(self.frame_t_ns) else t
        stale = (f < 0) | (t - latest > gap_ns)
        d = self.route.off_route_distance_m
        with np.errstate(invalid="ignore"):
            off = off | (along < -d) | (along > float(self.route.arc[-1]) + d)
        out = np.full(len(t), StateStatus.DEAD_RECKONING.value, dtype=object)
        out[loc] = StateStatus.LOCALIZED.value
        out[off] = StateStatus.OFF_ROUTE.value
        out[stale | ~ever] = StateStatus.UNKNOWN.value
        return out.astype(str)

    def _check_state_at(self, t_ns: int) -> None:
        """NotLocalizedError unless the smoother holds a state at ``t_ns`` (it has knots only once the repeat was
        localized, from the first waiting vertex on)."""
        first = self.trajectory.first_time_ns
        if first is None:
            raise NotLocalizedError("no state yet: the repeat has not been localized")
        if int(t_ns) < first:
            raise NotLocalizedError(f"no state at t_ns={int(t_ns)}: before the repeat's first state ({first})")

    def _state(self, t_ns: int, k: int, with_covariance: bool, fit_acceleration: bool = True) -> ControllerState:
        """The smoother's state at ``t_ns`` in trunk k's frame o, without validity (``fit_acceleration`` False: the
        WNOA mean's, for callers that read only the outputs)."""
        self._check_state_at(t_ns)
        T_world_trunk, T_o_t, _ = self.route.trunk_frames(k)
        s = self.trajectory.state_at(int(t_ns), with_covariance=with_covariance)
        cs = controller_state_unchecked(s, T_world_trunk, T_o_t, *self.route.mount())
        if cs.position_covariance is not None and cs.yaw_variance is not None:
            F = self.frame_output_covariance(int(t_ns), cs.T_o_a)
            cs = dataclasses.replace(
                cs,
                position_covariance=cs.position_covariance + F[:3, :3],
                yaw_variance=cs.yaw_variance + float(F[3, 3]),
            )
        window = self.route.acceleration_window_s
        if window <= 0.0 or not fit_acceleration:
            return cs
        # the acceleration of the vehicle origin from a fit of the knots' velocities (smoothing.acceleration_window_s)
        a_world, cov_world = self.trajectory.fitted_acceleration(int(t_ns), window, self.route.T_sensor_vehicle)
        C_o_world = T_o_t[:3, :3] @ self.route.T_world_trunk[k][:3, :3].T
        cov_o = C_o_world @ cov_world @ C_o_world.T if np.all(np.isfinite(cov_world)) else cov_world
        return dataclasses.replace(cs, acceleration=C_o_world @ a_world, acceleration_covariance=cov_o)

    def frame_output_covariance(self, t_ns: int, T_o_a: np.ndarray) -> np.ndarray:
        """The map's placement error of the latest localization at or before ``t_ns`` in the outputs ``(p_o, psi)``
        (4x4) of a vehicle at ``T_o_a``: what the localizations of consecutive leaves share (the taught vertices and
        experiences they were localized against, :func:`vtr.navigation.experiences.taught_covariance`), so the
        smoother, which averages them as independent, does not shrink it. Zero before the first localization."""
        i = int(self._vertex_at(np.array([t_ns]))[0])
        if self.vertex_frame_covariance is None or i < 0 or i >= len(self.vertex_frame_covariance):
            return np.zeros((4, 4))
        H = output_jacobian_unchecked(np.asarray(T_o_a, float), self.route.mount()[1])[:, :6]
        F = H @ self.vertex_frame_covariance[i] @ H.T
        return 0.5 * (F + F.T)

    def controller_state_at(
        self,
        t_ns: int,
        trunk_index: int | None = None,
        *,
        with_covariance: bool = False,
        commands: CommandLog | None = None,
    ) -> ControllerState:
        """Controller state (vehicle in o at the trunk) at ``t_ns``, with its status, the direction of travel, the
        trunk frame in the map's g (``T_g_o``) and, ``with_covariance``, the position, velocity and yaw
        covariances in o. After the newest knot the state is extrapolated at constant velocity, or, given the
        ``commands`` a controller sent (:class:`CommandLog`), with them (thesis eq. 8.15). Raises
        :class:`~vtr.errors.NotLocalizedError` before the first localization."""
        self._check_state_at(int(t_ns))
        t = np.array([t_ns], np.int64)
        k = int(self.trunk_index_at(t)[0]) if trunk_index is None else int(trunk_index)
        direction = int(self.direction_at(t)[0])
        cs = self._state(int(t_ns), k, with_covariance)
        last = self.trajectory.last_time_ns
        if commands is not None and last is not None and int(t_ns) > last:
            cs = self._with_commands(cs, k, last, int(t_ns), commands)
        _, path, offset = self.route.trunk(k, direction)
        along = path.error(cs.position).along_track + offset if path is not None else math.nan
        status = StateStatus(self.status_at(t, np.array([along]))[0])
        return dataclasses.replace(cs, status=status, direction=direction, T_g_o=self.route.T_g_o(k))

    def _with_commands(
        self, cs: ControllerState, k: int, t_knot_ns: int, t_ns: int, commands: CommandLog
    ) -> ControllerState:
        """``cs`` (extrapolated at constant velocity from the knot at ``t_knot_ns``) moved by the commanded
        accelerations since that knot: ``dv = int a``, ``dp = int (t - tau) a`` (zero-order hold)."""
        dp_g, dv_g, a_g = commands.integrate(t_knot_ns, t_ns)
        C_o_g = self.route.T_g_o(k)[:3, :3].T
        return dataclasses.replace(
            cs,
            position=cs.position + C_o_g @ dp_g,
            velocity=cs.velocity + C_o_g @ dv_g,
            acceleration=C_o_g @ a_g,
            acceleration_covariance=None,
        )

    def window(self, t_end_ns: int, n: int, dt_s: float, *, commands: CommandLog | None = None) -> OutputWindow:
        """The outputs ``y = (p, psi)`` of ``n`` samples ``dt_s`` apart ending at ``t_end_ns``, all in the frame o of
        the trunk at ``t_end_ns`` (one fixed frame: no jump where the trunk moves on), with their joint covariance
        (:meth:`~vtr.state.smoothing.KnotTrajectory.joint_covariance` mapped through each output's Jacobian).
        Samples after the newest knot are extrapolated as :meth:`controller_state_at` does: at constant velocity,
        or moved by the ``commands`` sent (the same positions ``controller_state_at(t, k, commands=...)`` gives;
        the covariance stays the constant-velocity extrapolation's, the commands being known inputs)."""
        if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 1:
            raise EstimationError(f"window: n must be a whole number >= 1, got {n!r}")
        if not (isinstance(dt_s, int | float) and math.isfinite(dt_s) and dt_s > 0):
            raise EstimationError(f"window: dt_s must be a finite time > 0 s, got {dt_s!r}")
        step_ns = int(round(dt_s * NS_PER_S))
        t = int(t_end_ns) - step_ns * np.arange(n - 1, -1, -1, dtype=np.int64)
        self._check_state_at(int(t[0]))
        k = int(self.trunk_index_at(np.array([t_end_ns]))[0])
        P, yaw, H = np.zeros((n, 3)), np.zeros(n), np.zeros((4 * n, 12 * n))
        last = self.trajectory.last_time_ns
        for j, tj in enumerate(t):
            cs = self._state(int(tj), k, with_covariance=False, fit_acceleration=False)
            if commands is not None and last is not None and int(tj) > last:
                cs = self._with_commands(cs, k, last, int(tj), commands)
            P[j], yaw[j] = cs.position, cs.yaw
            H[4 * j : 4 * j + 4, 12 * j : 12 * j + 12] = output_jacobian_unchecked(cs.T_o_a, self.route.mount()[1])
        _, path, offset = self.route.trunk(k, int(self.direction_at(np.array([t_end_ns]))[0]))
        along = path.error(P).along_track + offset if path is not None else np.full(n, math.nan)
        cov = H @ self.trajectory.joint_covariance(t) @ H.T
        # the frame's placement error is one error for every sample (all in the same o): every block gets it
        # (np.tile: the same blocks as np.kron(np.ones((n, n)), F), exactly, without the products by 1.0)
        cov = cov + np.tile(self.frame_output_covariance(int(t_end_ns), cs.T_o_a), (n, n))  # cs: t_end's
        return OutputWindow(
            t_ns=t,
            position=P,
            yaw=np.unwrap(yaw),
            covariance=0.5 * (cov + cov.T),
            trunk_id=int(self.route.path.ids[k]),
            T_g_o=self.route.T_g_o(k),
            status=self.status_at(t, np.atleast_1d(along)),
        )

    def states(self, t_ns: np.ndarray, *, with_covariance: bool = True) -> StateTable:
        """Controller states and path errors at the given times (int64 ns, not before the first vertex); with
        ``with_covariance`` the standard deviations of position and velocity in o too."""
        t_ns = np.asarray(t_ns, np.int64)
        n = len(t_ns)
        if self.unknown is not None:
            nan3, nan = np.full((n, 3), np.nan), np.full(n, np.nan)
            trunks = self.trunk_index_at(t_ns)
            return StateTable(
                t_ns=t_ns,
                position=nan3,
                velocity=nan3.copy(),
                acceleration=nan3.copy(),
                yaw=nan,
                trunk_id=self.route.path.ids[trunks],
                lateral=nan.copy(),
                vertical=nan.copy(),
                along_track=nan.copy(),
                localized=np.zeros(n, bool),
                direction=self.direction_at(t_ns),
                status=np.full(n, StateStatus.UNKNOWN.value),
                position_sigma=nan3.copy() if with_covariance else None,
                velocity_sigma=nan3.copy() if with_covariance else None,
            )
        if n and self.trajectory.n == 0:
            raise DataError("no repeat vertex was processed: no state to report")
        trunks = self.trunk_index_at(t_ns)
        direction = self.direction_at(t_ns)
        P, Vel, A = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))
        sig_p, sig_v = np.full((n, 3), np.nan), np.full((n, 3), np.nan)
        yaw = np.zeros(n)
        for j in range(n):
            try:
                cs = self._state(int(t_ns[j]), int(trunks[j]), with_covariance)
            except EstimationError:  # a pause: no segment reaches this time (the row is unknown)
                P[j] = Vel[j] = A[j] = np.nan
                yaw[j] = np.nan
                continue
            P[j], Vel[j], A[j], yaw[j] = cs.position, cs.velocity, cs.acceleration, cs.yaw
            if cs.position_covariance is not None and cs.velocity_covariance is not None:
                sig_p[j] = np.sqrt(np.clip(np.diag(cs.position_covariance), 0.0, None))
                sig_v[j] = np.sqrt(np.clip(np.diag(cs.velocity_covariance), 0.0, None))
        lat, ver, along = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
        backward = direction == BACKWARD
        for k, b in {(int(k), bool(b)) for k, b in zip(trunks, backward, strict=True)}:
            sel = (trunks == k) & (backward == b)
            _, path, offset = self.route.trunk(k, BACKWARD if b else 1)
            sel &= np.all(np.isfinite(P), axis=1)
            if path is not None and sel.any():
                e: PathError = path.error(P[sel])
                # lateral is to the left of the direction of travel: the taught path's left, mirrored going back
                lat[sel] = -e.lateral if b else e.lateral
                ver[sel], along[sel] = e.vertical, e.along_track + offset
        status = self.status_at(t_ns, along)
        localized = status == StateStatus.LOCALIZED.value
        lat[~localized] = ver[~localized] = np.nan  # no path error where the repeat is not localized
        return StateTable(
            t_ns=t_ns,
            position=P,
            velocity=Vel,
            acceleration=A,
            yaw=yaw,
            trunk_id=self.route.path.ids[trunks],
            lateral=lat,
            vertical=ver,
            along_track=along,
            localized=localized,
            direction=direction,
            status=status,
            position_sigma=sig_p if with_covariance else None,
            velocity_sigma=sig_v if with_covariance else None,
        )


__all__ = [
    "CommandLog",
    "OutputWindow",
    "RepeatStateView",
    "RouteFrames",
    "SegmentedTrajectory",
    "StateTable",
]
