"""Controller-facing state of a repeat run (thesis §6.3.4): :class:`RepeatStateEstimator` feeds the continuous-time
smoother one knot per repeat vertex (odometry between vertices, the localization at a localized one; vertices before
the first success wait), with the chain's verdict on validity and direction carried by each step, and answers queries
in the gravity-aligned trunk frame o from immutable views (:mod:`vtr.navigation.state_view`). What is fed and why,
gravity, pauses and queries: docs/smoother.md, "Feeding it from a repeat" and "Controller state"."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from perception_model.frames import LEVEL_CAMERA_UP, T_g_map_from_up, T_vehicle_camera_from_up

from ..config import LocalizationConfig, SmoothingConfig, check_setting
from ..conventions import NS_PER_S
from ..errors import DataError, EstimationError
from ..geometry import inv_T, usable_covariance
from ..map import TaughtPath
from ..state.controller import ControllerState
from ..state.smoothing import KnotTrajectory, TrajectorySmoother, adjoint, logmap
from ..state.wnoa import MotionPsd
from .localization import LocalizationStatus
from .state_view import (
    CommandLog,
    OutputWindow,
    RepeatStateView,
    RouteFrames,
    SegmentedTrajectory,
    StateTable,
)

if TYPE_CHECKING:
    from .repeat import RepeatStep

# Absolute prior on the first knot of a run that never localizes (at the chain's assumption): a single
# absolute prior does not move the means, it only fixes the gauge. Not weaker: GTSAM declares a system whose
# information spans more than ~1e7 (odometry rotation variances are ~1e-8 rad^2) indeterminate.
UNLOCALIZED_ROTATION_SIGMA_RAD = 0.01
UNLOCALIZED_TRANSLATION_SIGMA_M = 0.1


def check_rate(rate_hz: float) -> float:
    """The state output rate (Hz) as a float; ConfigError unless inside the domain of smoothing.rate_hz."""
    return float(check_setting("smoothing", "rate_hz", rate_hz, "state rate"))


def output_times(t_first_ns: int, t_last_ns: int, rate_hz: float) -> np.ndarray:
    """Times (int64 ns) ``t_first + k / rate`` for k = 0, 1, ... up to ``t_last`` (inclusive)."""
    rate = check_rate(rate_hz)
    span = int(t_last_ns) - int(t_first_ns)
    if span < 0:
        return np.zeros(0, np.int64)
    k = np.arange(int(math.floor(span * rate / NS_PER_S)) + 2, dtype=np.int64)
    t = np.round(k * (NS_PER_S / rate)).astype(np.int64)
    return int(t_first_ns) + t[t <= span]


def vehicle_from_sensor(T_vehicle_sensor: np.ndarray, gravity_up: np.ndarray | None = None) -> np.ndarray:
    """``T_vehicle_sensor`` with the identity (a source that knows no mount) read as a camera rigidly mounted on a
    level vehicle whose up direction, seen from the first teach camera, is ``gravity_up`` (default: a level,
    forward-looking camera; see module doc)."""
    T = np.asarray(T_vehicle_sensor, float)
    if not np.allclose(T, np.eye(4)):
        return T
    return T_vehicle_camera_from_up(LEVEL_CAMERA_UP if gravity_up is None else gravity_up)


@dataclass
class _Vertex:
    t_ns: int
    T_world_leaf: np.ndarray  # repeat world
    relative_covariance: np.ndarray | None
    T_teach_leaf: np.ndarray | None  # localization, teach world
    localization_covariance: np.ndarray | None
    T_teach_chain: np.ndarray  # the chain's estimate (used only if the run never localizes)


class RepeatStateEstimator:
    """The controller-facing state of a repeat: feeds a :class:`~vtr.state.smoothing.TrajectorySmoother` from
    repeat steps and answers controller states at any time, each with its status and direction.

    Args:
        path: the taught path the repeat follows (ids, camera poses in the teach world).
        smoothing: the smoother's settings (Qc, lag, ``max_extrapolation_s``) and the odometry drift per metre.
        T_vehicle_sensor: the camera on the vehicle (identity: a camera rigidly mounted on a level vehicle, see
            ``gravity_up``).
        trunk_window: ``(back, forward)`` taught vertices around the trunk, in the direction of travel, that make
            the reference path.
        off_route_distance_m: a state further than this beyond either end of the taught route is ``off_route``.
        gravity_up: up in the first teach camera's frame (the map's gravity, ``Map.gravity_up``); None: that
            camera was level (or the mount ``T_vehicle_sensor`` says where up is).
    """

    def __init__(
        self,
        path: TaughtPath,
        smoothing: SmoothingConfig,
        T_vehicle_sensor: np.ndarray,
        *,
        trunk_window: tuple[int, int],
        off_route_distance_m: float,
        gravity_up: np.ndarray | None = None,
    ):
        self.path = path
        self.smoothing = smoothing
        self.smoother = TrajectorySmoother(smoothing)
        # the motion prior's Qc from the repeat's own odometry steps (kept across pauses: the vehicle is the same),
        # starting from the taught path's motion (the configured Qc when the taught path is too short to say)
        psd = MotionPsd(
            self.smoother.q_psd,
            smoothing.qc_window_s,
            smoothing.qc_min_samples,
            smoothing.qc_floor_share,
            smoothing.qc_long_steps,
        )
        self.taught_qc = psd.of_poses(path.t_ns, path.T_world_vertex, smoothing.max_extrapolation_s)
        self.motion_psd = MotionPsd(
            self.taught_qc,
            smoothing.qc_window_s,
            smoothing.qc_min_samples,
            smoothing.qc_floor_share,
            smoothing.qc_long_steps,
            configured=self.smoother.q_psd,
        )
        self.trunk_window = (int(trunk_window[0]), int(trunk_window[1]))
        self.off_route_distance_m = float(off_route_distance_m)
        self.gravity_up = None if gravity_up is None else np.asarray(gravity_up, float)
        self.T_vehicle_sensor = vehicle_from_sensor(T_vehicle_sensor, self.gravity_up)
        self.T_sensor_vehicle = inv_T(self.T_vehicle_sensor)
        # the gravity-aligned frame g of the teach world: from the map's up, else the vehicle at the first camera
        self.C_g_world = (
            self.T_vehicle_sensor[:3, :3] if self.gravity_up is None else T_g_map_from_up(self.gravity_up)[:3, :3]
        )
        self.route = RouteFrames(
            path,
            self.T_sensor_vehicle,
            self.C_g_world,
            self.trunk_window,
            self.off_route_distance_m,
            smoothing.max_extrapolation_s,
            smoothing.acceleration_window_s,
        )
        self._full_view: RepeatStateView | None = None
        self._pending: list[_Vertex] = []
        self._anchored = False
        self._last: _Vertex | None = None
        self._past_segments: list[TrajectorySmoother] = []  # closed by pauses, oldest first
        self.pauses_s: list[float] = []  # the length of each pause (s)
        self.vertex_t_ns: list[int] = []
        self.vertex_trunk: list[int] = []  # index along the privileged path
        self.vertex_localized: list[bool] = []  # the chain's verdict after the vertex's attempt
        self.vertex_direction: list[int] = []  # the chain's direction of travel after it
        self.vertex_off_route: list[bool] = []  # the attempt found the vertex beyond an end of the route
        # the map's placement error (6x6, leaf camera) of the latest localization at or before the vertex
        self.vertex_frame_covariance: list[np.ndarray] = []
        self.frame_t_ns: list[int] = []  # every frame fed (a state long after the last one is unknown)
        # the taught spacing at each path index (m, mean of its steps to its neighbours): the correlation length of
        # the map's placement error along the path; and the repeat pose of the last localized vertex
        step = np.linalg.norm(np.diff(path.positions, axis=0), axis=1)
        self._vertex_spacing_m = (
            0.5 * (np.r_[step[:1], step] + np.r_[step, step[-1:]]) if len(step) else np.zeros(len(path))
        )
        self._last_localized_world: np.ndarray | None = None
        self._ever = False
        self.unknown: str | None = None  # why the state of a never-localized run is unknown
        self.first_t_ns: int | None = None
        self.last_t_ns: int | None = None
        self.seconds = 0.0  # time spent feeding the smoother and answering queries

    @classmethod
    def for_route(
        cls,
        path: TaughtPath,
        smoothing: SmoothingConfig,
        localization: LocalizationConfig,
        T_vehicle_sensor: np.ndarray,
        gravity_up: np.ndarray | None = None,
    ) -> RepeatStateEstimator:
        """The estimator of a repeat along ``path`` with ``smoothing``, the ``localization``'s trunk window and
        off-route distance, and the map's ``gravity_up``."""
        loc = localization
        return cls(
            path,
            smoothing,
            T_vehicle_sensor,
            trunk_window=(loc.trunk_window_back, loc.trunk_window_forward),
            off_route_distance_m=loc.off_route_distance_m,
            gravity_up=gravity_up,
        )

    # -- feeding ------------------------------------------------------------------------------------

    def add(self, step: RepeatStep) -> None:
        """Take one :class:`~vtr.navigation.repeat.RepeatStep`; a new vertex becomes a smoother knot (or waits for
        the first successful localization). Whether the repeat is localized, and its direction, are the chain's
        verdict carried by the step."""
        t0 = time.perf_counter()
        self._full_view = None
        r = step.odometry
        if self.first_t_ns is None:
            self.first_t_ns = int(r.t_ns)
        if self.last_t_ns is not None and int(r.t_ns) - self.last_t_ns > self.smoothing.max_extrapolation_s * NS_PER_S:
            self._pause(int(r.t_ns) - self.last_t_ns)
        self.last_t_ns = int(r.t_ns)
        self.frame_t_ns.append(int(r.t_ns))
        kf, loc = r.new_keyframe, step.localization
        if kf is not None:
            rel_cov = None
            previous = self._pending[-1] if self._pending else self._last
            if previous is not None:
                # the keyframe's edge covariance (usable as odometry hands it out) plus drift with distance
                rel_cov = kf.edge_covariance + self._drift_covariance(previous.T_world_leaf, kf.T_world_kf)
            T_teach_leaf = loc_cov = None
            frame_cov = self.vertex_frame_covariance[-1] if self.vertex_frame_covariance else np.zeros((6, 6))
            if loc is not None and loc.success:
                # the map's placement part F of a localization is a first-order Gauss-Markov error along the path:
                # consecutive leaves share rho F, rho = exp(-d / L) with d the distance between them and L the
                # taught vertex spacing (the distance over which the trunk, whose placement F is, is replaced). The
                # smoother, which averages localizations as independent, is fed the measurements' part plus the
                # part that differs, (1 - rho) F; every state after it adds the shared part rho F once
                # (RepeatStateView.frame_output_covariance). Exact for one leaf and for a pair, conservative for
                # any average of more (docs/smoother.md "Feeding it from a repeat")
                F = np.zeros((6, 6)) if loc.frame_covariance is None else np.asarray(loc.frame_covariance, float)
                rho = self._map_error_correlation(loc.trunk_id, np.asarray(kf.T_world_kf, float))
                loc_cov = usable_covariance(np.asarray(loc.covariance, float) - rho * F)
                if loc_cov is not None:
                    T_teach_leaf = self.path.T_world_localized(loc.trunk_id, loc.T_leaf_trunk)
                    frame_cov = rho * F
                    self._last_localized_world = np.asarray(kf.T_world_kf, float)
            self.vertex_frame_covariance.append(frame_cov)
            v = _Vertex(
                int(r.t_ns),
                np.asarray(kf.T_world_kf, float),
                rel_cov,
                T_teach_leaf,
                loc_cov,
                np.asarray(step.T_teach_frame, float),
            )
            self.vertex_t_ns.append(v.t_ns)
            self._ever = self._ever or (loc is not None and loc.success)
            self.vertex_localized.append(bool(step.localized))
            self.vertex_direction.append(int(step.direction))
            self.vertex_off_route.append(loc is not None and loc.status == LocalizationStatus.OFF_ROUTE)
            trunk = loc.trunk_id if loc is not None else None
            self.vertex_trunk.append(
                self.path.index(trunk) if trunk is not None else (self.vertex_trunk[-1] if self.vertex_trunk else 0)
            )
            if self._anchored:
                self._feed(v)
            else:
                self._pending.append(v)
                if T_teach_leaf is not None:
                    self._flush_localized()
        self.seconds += time.perf_counter() - t0

    def _pause(self, gap_ns: int) -> None:
        """No frame for longer than ``smoothing.max_extrapolation_s``: nothing measured bridges the pause, so the
        smoother's motion prior must not either. The current segment is closed (vertices still waiting for a
        localization are placed by the chain's assumption, as at the end of a run) and the next vertex starts a new
        one, anchored again by the next localization; the states across the pause are ``unknown``."""
        self.pauses_s.append(gap_ns / NS_PER_S)
        self._close_pending()
        if self.smoother.num_keyframes:
            self._past_segments.append(self.smoother)
        self.smoother = TrajectorySmoother(self.smoothing)
        self._anchored = False
        self._last = None
        self._last_localized_world = None

    def _map_error_correlation(self, trunk_id: int, T_world_leaf: np.ndarray) -> float:
        """The correlation of the map's placement error between this leaf and the previous localized one (1 for
        the first of a segment: all of it is then added at the output, the same total for a single leaf):
        ``exp(-d / L)``, d the distance travelled between them (repeat odometry), L the taught spacing at the trunk
        (the mean of its steps to its neighbours on the path)."""
        if self._last_localized_world is None:
            return 1.0
        d = float(np.linalg.norm(T_world_leaf[:3, 3] - self._last_localized_world[:3, 3]))
        spacing = float(self._vertex_spacing_m[self.path.index(trunk_id)])
        return math.exp(-d / spacing) if spacing > 0.0 else 0.0

    def _drift_covariance(self, T_world_a: np.ndarray, T_world_b: np.ndarray) -> np.ndarray:
        """Odometry drift between two vertices, growing with the distance travelled ([rot, trans])."""
        c = self.smoothing
        d = float(np.linalg.norm(T_world_b[:3, 3] - T_world_a[:3, 3]))
        return np.diag(
            np.r_[[(c.odometry_rotation_sigma_per_m * d) ** 2] * 3, [(c.odometry_translation_sigma_per_m * d) ** 2] * 3]
        )

    def finish(self) -> None:
        """End of the run: vertices still waiting for a localization are fed with the chain's assumption. When
        that cannot be solved (a run that never localized, with odometry failures in it, leaves the knots after a
        failure unconstrained) the state stays unknown: :meth:`states` reports NaN, not a failure of the run."""
        self._full_view = None
        self._close_pending()

    def _close_pending(self) -> None:
        if self._pending:
            first = self._pending[0]
            sig = np.r_[[UNLOCALIZED_ROTATION_SIGMA_RAD] * 3, [UNLOCALIZED_TRANSLATION_SIGMA_M] * 3]
            first.T_teach_leaf, first.localization_covariance = first.T_teach_chain, np.diag(sig**2)
            try:
                self._flush()
            except EstimationError as err:
                if self._ever:
                    raise
                self.unknown = str(err)

    def _flush_localized(self) -> None:
        """The newest waiting vertex is the first one localized: move its localization to the first waiting
        vertex through repeat odometry, ``T_teach_first = T_teach_s @ T_s_first`` with the covariance moved
        by ``Ad(inv(T_s_first))`` (right perturbations), so that the chain starts there, counted once."""
        first, s = self._pending[0], self._pending[-1]
        if s is not first:
            T_s_first = inv_T(s.T_world_leaf) @ first.T_world_leaf
            A = adjoint(inv_T(T_s_first))
            first.T_teach_leaf = s.T_teach_leaf @ T_s_first
            first.localization_covariance = usable_covariance(A @ s.localization_covariance @ A.T)
            s.T_teach_leaf = s.localization_covariance = None
        self._flush()

    def _flush(self) -> None:
        pending, self._pending = self._pending, []
        self._anchored = True
        for v in pending:
            self._feed(v)

    def _feed(self, v: _Vertex) -> None:
        if self._last is not None and v.t_ns <= self._last.t_ns:
            return  # a repeated timestamp: one knot per time (the next vertex's odometry spans both)
        kw = {}
        if self._last is not None and v.relative_covariance is not None:
            kw["T_prev_cur"] = T_prev_cur = inv_T(self._last.T_world_leaf) @ v.T_world_leaf
            kw["relative_covariance"] = v.relative_covariance
            self.motion_psd.add(logmap(T_prev_cur)[0], (v.t_ns - self._last.t_ns) / NS_PER_S)
        else:
            self.motion_psd.broken()
        if v.T_teach_leaf is not None:
            kw["T_world_sensor"], kw["covariance"] = v.T_teach_leaf, v.localization_covariance
        self.smoother.add_knot(v.t_ns, qc=self.motion_psd.qc, **kw)
        self._last = v

    # -- queries ------------------------------------------------------------------------------------

    def view(self, history_s: float | None = None) -> RepeatStateView:
        """The state as of the last step fed, immutable: every query of a controller answered from it, on any
        thread, while this estimator goes on. ``history_s`` keeps only the last seconds (a copy of a few knots: what
        an online controller reads); None keeps the whole run (no copy; the estimator's own offline queries)."""
        if history_s is None:
            if self._full_view is None:
                self._full_view = self._make_view(None)
            return self._full_view
        return self._make_view(float(history_s))

    def _make_view(self, history_s: float | None) -> RepeatStateView:
        t_v = np.asarray(self.vertex_t_ns, np.int64)
        frames = np.asarray(self.frame_t_ns, np.int64)
        localized = np.asarray(self.vertex_localized, bool)
        ever = np.logical_or.accumulate(localized) if len(localized) else localized
        lo_v = lo_f = 0
        since = None
        if history_s is not None and self.last_t_ns is not None:
            since = self.last_t_ns - int(history_s * NS_PER_S)
            lo_v = max(0, int(np.searchsorted(t_v, since, side="right")) - 1)
            lo_f = max(0, int(np.searchsorted(frames, since, side="right")) - 1)
        trajectory: KnotTrajectory | SegmentedTrajectory
        if history_s is not None:
            trajectory = self.smoother.snapshot(since)
        elif self._past_segments:
            trajectory = SegmentedTrajectory(
                [sm._view() for sm in (*self._past_segments, self.smoother) if sm.num_keyframes]
            )
        else:
            trajectory = self.smoother._view()
        return RepeatStateView(
            route=self.route,
            trajectory=trajectory,
            vertex_t_ns=t_v[lo_v:],
            vertex_trunk=np.asarray(self.vertex_trunk, np.int64)[lo_v:],
            vertex_localized=localized[lo_v:],
            vertex_ever=ever[lo_v:],
            vertex_direction=np.asarray(self.vertex_direction, np.int64)[lo_v:],
            vertex_off_route=np.asarray(self.vertex_off_route, bool)[lo_v:],
            frame_t_ns=frames[lo_f:],
            vertex_frame_covariance=np.asarray(self.vertex_frame_covariance, float).reshape(-1, 6, 6)[lo_v:],
            unknown=self.unknown,
        )

    def trunk_frame(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """``(T_world_trunk, T_o_t)`` of the taught vertex at path index k (vehicle frame, teach world)."""
        return self.route.trunk_frame(k)

    def trunk_index_at(self, t_ns: np.ndarray) -> np.ndarray:
        """Path index of the chain's trunk at the latest vertex at or before each time."""
        return self.view().trunk_index_at(t_ns)

    def direction_at(self, t_ns: np.ndarray) -> np.ndarray:
        """The chain's direction of travel (+1, -1; 0 undecided) at the latest vertex at or before each time."""
        return self.view().direction_at(t_ns)

    def controller_state_at(
        self, t_ns: int, trunk_index: int | None = None, *, with_covariance: bool = False
    ) -> ControllerState:
        """:meth:`RepeatStateView.controller_state_at` on the whole run so far."""
        return self.view().controller_state_at(t_ns, trunk_index, with_covariance=with_covariance)

    def states(self, t_ns: np.ndarray, *, with_covariance: bool = True) -> StateTable:
        """Controller states and path errors at the given times (int64 ns, not before the first vertex)."""
        t0 = time.perf_counter()
        out = self.view().states(t_ns, with_covariance=with_covariance)
        self.seconds += time.perf_counter() - t0
        return out

    def output(self, rate_hz: float) -> StateTable:
        """States at ``rate_hz`` over the run's span (first to last frame processed)."""
        if self.first_t_ns is None or self.last_t_ns is None:
            raise DataError("no repeat frame was processed: no state to report")
        return self.states(output_times(self.first_t_ns, self.last_t_ns, rate_hz))


__all__ = [
    "CommandLog",
    "SegmentedTrajectory",
    "OutputWindow",
    "RepeatStateEstimator",
    "RepeatStateView",
    "RouteFrames",
    "StateTable",
    "check_rate",
    "output_times",
    "vehicle_from_sensor",
]
