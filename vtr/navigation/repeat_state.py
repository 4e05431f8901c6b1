"""Controller-facing state of a repeat run: the continuous-time smoother fed with the localization chain,
queried at a fixed rate in the gravity-aligned trunk frame o (docs/smoother.md; thesis §6.3.4).

**Feeding the smoother** (:meth:`RepeatStateEstimator.add`, one :class:`~vtr.navigation.repeat.RepeatStep` at a
time). The smoother tracks the left camera in the teach world (the teach run's first camera frame). It gets one knot
per repeat *vertex* (keyframe), not per frame:

* a relative pose from repeat odometry between consecutive vertices, ``inv(T_world_prev) @ T_world_leaf``
  (repeat world), with the odometry covariance of the leaf (the same measurement and covariance as the
  map's temporal edge);
* at a successfully localized vertex, an absolute pose in the teach world,
  ``T_teach_leaf = T_teach_trunk @ inv(T_leaf_trunk)`` (``TaughtPath.T_world_localized``; =
  ``RepeatStep.T_teach_frame`` there), with the
  localization covariance. Privileged poses are taken as exact (the repeat is expressed relative to the
  taught path, as the chain does).

Why vertices and these two measurements: (1) localization, the only measurement of the pose in the teach
frame, exists only at vertices; the chain's ``T_teach_frame`` of the other frames is localization composed
with odometry, and feeding it as an absolute pose would count the same localization again at every frame;
(2) a non-keyframe frame's pose is measured against the same landmarks as the next keyframe's, so adding it
as an independent measurement would count the same landmark errors twice; (3) the
smoother's states sit at keyframe times (≈1–15 Hz) with bounded cost per keyframe; the WNOA prior interpolates
between them (and extrapolates after the last one) at the output rate. Both covariances use the left
perturbation of ``T_cam_world`` / ``T_leaf_trunk`` (vtr.vo.estimation), which is the right perturbation of the
inverse pose the smoother uses, so they are passed unchanged.

Before the first successful localization nothing ties the repeat to the teach frame: those vertices wait.
At the first success, that localization is moved to the first waiting vertex through repeat odometry (the
smoother's first knot needs an absolute pose; the information is counted once, only its place changes) and
the waiting vertices are fed in order. A run that never localizes is fed with the chain's assumption (it
started at the taught vertex ``start_index``) as the first knot's prior, which only fixes the gauge.

**Gravity.** The teach world is the teach run's first camera frame (KITTI and the other sources: x right,
y down, z forward). The vehicle frame is FLU (docs/frames.md), placed by ``T_vehicle_sensor``; when that is
the identity (KITTI), the camera is taken as a level, forward-looking vehicle: vehicle frame = camera
centre with x = camera z, y = -camera x, z = -camera y (``perception_model.frames.T_VEHICLE_LEVEL_CAMERA``). The
vehicle at the teach run's first camera is assumed level, so the gravity-aligned frame g (z up) is the vehicle frame
there: ``C_g_world = C_vehicle_sensor``; for a level first camera, up is ``-y`` of that camera. Each trunk's
``T_o_t`` then comes from :func:`vtr.state.controller.gravity_aligned_T_o_t` on ``C_g_trunk``. (A source whose
``T_vehicle_sensor`` is not FLU, e.g. EuRoC's IMU body frame, breaks that assumption: its o is tilted.)

**Output.** ``state.csv`` is written after the run from the smoother's knots (each as final when it left
the ``lag_s`` window, the newest ones jointly): a fixed-lag *smoothed* state at ``rate_hz`` from the first
to the last frame, the WNOA posterior mean between knots, extrapolated after the last one. A controller at
run time calls :meth:`RepeatStateEstimator.controller_state_at` instead, which extrapolates from the newest knot.

**Trunk.** The state at time t is expressed at the chain's trunk of the latest vertex at or before t (the
trunk a controller would hold at t), so p jumps when the trunk moves on; lateral/vertical errors do not.
The reference path is the polyline through the privileged vertices' vehicle origins in a window around the
trunk (the chain's trunk-search window), expressed in o; ``along_track_m`` is the arc length from the start
of the whole taught path.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from perception_model.frames import LEVEL_CAMERA_UP, T_g_map_from_up, T_vehicle_camera_from_up

from ..config import Config, SmoothingConfig, check_setting
from ..conventions import NS_PER_S
from ..errors import DataError, EstimationError, NotLocalizedError
from ..geometry import inv_T, usable_covariance
from ..map import TaughtPath
from ..state.controller import (
    ControllerState,
    PathError,
    ReferencePath,
    StateStatus,
    controller_state,
    gravity_aligned_T_o_t,
    output_jacobian,
)
from ..state.smoothing import KnotTrajectory, TrajectorySmoother, adjoint
from .localization import LocalizationStatus
from .trunk import BACKWARD

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
    localized: np.ndarray | None = None   # (N,) bool: the chain held a localization at that time
    direction: np.ndarray | None = None   # (N,) int: +1 taught order, -1 backward, 0 not decided
    status: np.ndarray | None = None      # (N,) str: StateStatus values
    position_sigma: np.ndarray | None = None   # (N, 3) m: standard deviations of position in o
    velocity_sigma: np.ndarray | None = None   # (N, 3) m/s: likewise of velocity

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

    def state_at(self, t_ns: int, *, with_covariance: bool = True):
        return self._segment(t_ns).state_at(t_ns, with_covariance=with_covariance)

    def fitted_acceleration(self, t_ns: int, window_s: float, T_sensor_point: np.ndarray | None = None):
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
        constant velocity, and the command in force at ``t1`` (zero before the first command)."""
        t = np.asarray(self.t_ns, np.int64)
        a = np.asarray(self.acceleration_g, float).reshape(-1, 3)
        dp, dv = np.zeros(3), np.zeros(3)
        if not len(t):
            return dp, dv, np.zeros(3)
        edges = np.r_[t, np.iinfo(np.int64).max]
        for j in range(len(t)):
            lo, hi = max(int(edges[j]), t0_ns), min(int(edges[j + 1]), t1_ns)
            if hi <= lo:
                continue
            d_s = (hi - lo) / NS_PER_S
            rest_s = (t1_ns - hi) / NS_PER_S
            dv += a[j] * d_s
            dp += a[j] * (0.5 * d_s**2 + d_s * rest_s)
        j = int(np.searchsorted(t, t1_ns, side="right")) - 1
        return dp, dv, a[j].copy() if j >= 0 else np.zeros(3)


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


@dataclass
class _Vertex:
    t_ns: int
    T_world_leaf: np.ndarray          # repeat world
    relative_covariance: np.ndarray | None
    T_teach_leaf: np.ndarray | None   # localization, teach world
    localization_covariance: np.ndarray | None
    T_teach_chain: np.ndarray         # the chain's estimate (used only if the run never localizes)


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

    def __init__(self, path: TaughtPath, smoothing: SmoothingConfig, T_vehicle_sensor: np.ndarray, *,
                 trunk_window: tuple[int, int], off_route_distance_m: float,
                 gravity_up: np.ndarray | None = None):
        self.path = path
        self.smoothing = smoothing
        self.smoother = TrajectorySmoother(smoothing)
        self.trunk_window = (int(trunk_window[0]), int(trunk_window[1]))
        self.off_route_distance_m = float(off_route_distance_m)
        self.gravity_up = None if gravity_up is None else np.asarray(gravity_up, float)
        self.T_vehicle_sensor = vehicle_from_sensor(T_vehicle_sensor, self.gravity_up)
        self.T_sensor_vehicle = inv_T(self.T_vehicle_sensor)
        # the gravity-aligned frame g of the teach world: from the map's up, else the vehicle at the first camera
        self.C_g_world = (self.T_vehicle_sensor[:3, :3] if self.gravity_up is None
                          else T_g_map_from_up(self.gravity_up)[:3, :3])
        self.route = RouteFrames(path, self.T_sensor_vehicle, self.C_g_world, self.trunk_window,
                                 self.off_route_distance_m, smoothing.max_extrapolation_s,
                                 smoothing.acceleration_window_s)
        self._full_view: RepeatStateView | None = None
        self._pending: list[_Vertex] = []
        self._anchored = False
        self._last: _Vertex | None = None
        self._past_segments: list[TrajectorySmoother] = []   # closed by pauses, oldest first
        self.pauses_s: list[float] = []                      # the length of each pause (s)
        self.vertex_t_ns: list[int] = []
        self.vertex_trunk: list[int] = []     # index along the privileged path
        self.vertex_localized: list[bool] = []   # the chain's verdict after the vertex's attempt
        self.vertex_direction: list[int] = []    # the chain's direction of travel after it
        self.vertex_off_route: list[bool] = []   # the attempt found the vertex beyond an end of the route
        self.frame_t_ns: list[int] = []          # every frame fed (a state long after the last one is unknown)
        self._ever = False
        self.unknown: str | None = None           # why the state of a never-localized run is unknown
        self.first_t_ns: int | None = None
        self.last_t_ns: int | None = None
        self.seconds = 0.0                    # time spent feeding the smoother and answering queries

    @classmethod
    def for_route(cls, path: TaughtPath, config: Config, T_vehicle_sensor: np.ndarray,
                  gravity_up: np.ndarray | None = None) -> RepeatStateEstimator:
        """The estimator of a repeat along ``path`` with the settings of ``config`` (``smoothing``, the
        localization's trunk window and off-route distance) and the map's ``gravity_up``."""
        loc = config.localization
        return cls(path, config.smoothing, T_vehicle_sensor,
                   trunk_window=(loc.trunk_window_back, loc.trunk_window_forward),
                   off_route_distance_m=loc.off_route_distance_m, gravity_up=gravity_up)

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
            if loc is not None and loc.success:
                loc_cov = usable_covariance(loc.covariance)
                if loc_cov is not None:
                    T_teach_leaf = self.path.T_world_localized(loc.trunk_id, loc.T_leaf_trunk)
            v = _Vertex(int(r.t_ns), np.asarray(kf.T_world_kf, float), rel_cov, T_teach_leaf, loc_cov,
                        np.asarray(step.T_teach_frame, float))
            self.vertex_t_ns.append(v.t_ns)
            self._ever = self._ever or (loc is not None and loc.success)
            self.vertex_localized.append(bool(step.localized))
            self.vertex_direction.append(int(step.direction))
            self.vertex_off_route.append(loc is not None and loc.status == LocalizationStatus.OFF_ROUTE)
            trunk = loc.trunk_id if loc is not None else None
            self.vertex_trunk.append(self.path.index(trunk) if trunk is not None else
                                     (self.vertex_trunk[-1] if self.vertex_trunk else 0))
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

    def _drift_covariance(self, T_world_a: np.ndarray, T_world_b: np.ndarray) -> np.ndarray:
        """Odometry drift between two vertices, growing with the distance travelled ([rot, trans])."""
        c = self.smoothing
        d = float(np.linalg.norm(T_world_b[:3, 3] - T_world_a[:3, 3]))
        return np.diag(np.r_[[(c.odometry_rotation_sigma_per_m * d) ** 2] * 3,
                             [(c.odometry_translation_sigma_per_m * d) ** 2] * 3])

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
            return      # a repeated timestamp: one knot per time (the next vertex's odometry spans both)
        kw = {}
        if self._last is not None and v.relative_covariance is not None:
            kw["T_prev_cur"] = inv_T(self._last.T_world_leaf) @ v.T_world_leaf
            kw["relative_covariance"] = v.relative_covariance
        if v.T_teach_leaf is not None:
            kw["T_world_sensor"], kw["covariance"] = v.T_teach_leaf, v.localization_covariance
        self.smoother.add_knot(v.t_ns, **kw)
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
            trajectory = SegmentedTrajectory([sm._view() for sm in (*self._past_segments, self.smoother)
                                              if sm.num_keyframes])
        else:
            trajectory = self.smoother._view()
        return RepeatStateView(
            route=self.route, trajectory=trajectory, vertex_t_ns=t_v[lo_v:],
            vertex_trunk=np.asarray(self.vertex_trunk, np.int64)[lo_v:], vertex_localized=localized[lo_v:],
            vertex_ever=ever[lo_v:], vertex_direction=np.asarray(self.vertex_direction, np.int64)[lo_v:],
            vertex_off_route=np.asarray(self.vertex_off_route, bool)[lo_v:], frame_t_ns=frames[lo_f:],
            unknown=self.unknown)

    def trunk_frame(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """``(T_world_trunk, T_o_t)`` of the taught vertex at path index k (vehicle frame, teach world)."""
        return self.route.trunk_frame(k)

    def trunk_index_at(self, t_ns: np.ndarray) -> np.ndarray:
        """Path index of the chain's trunk at the latest vertex at or before each time."""
        return self.view().trunk_index_at(t_ns)

    def direction_at(self, t_ns: np.ndarray) -> np.ndarray:
        """The chain's direction of travel (+1, -1; 0 undecided) at the latest vertex at or before each time."""
        return self.view().direction_at(t_ns)

    def controller_state_at(self, t_ns: int, trunk_index: int | None = None, *,
                            with_covariance: bool = False) -> ControllerState:
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


class RouteFrames:
    """The taught route as the controller state sees it (immutable once built; the memo of each trunk's frame and
    reference path fills on first use, from any thread: entries are pure functions of the route)."""

    def __init__(self, path: TaughtPath, T_sensor_vehicle: np.ndarray, C_g_world: np.ndarray,
                 trunk_window: tuple[int, int], off_route_distance_m: float, max_gap_s: float,
                 acceleration_window_s: float = 0.0) -> None:
        self.path = path
        self.T_sensor_vehicle = T_sensor_vehicle
        self.C_g_world = C_g_world
        self.trunk_window = trunk_window
        self.off_route_distance_m = off_route_distance_m
        self.max_gap_s = max_gap_s
        self.acceleration_window_s = float(acceleration_window_s)
        self.T_world_trunk = path.T_world_vertex @ T_sensor_vehicle      # taught vehicle poses, teach world
        self.arc = path.arc_length_m(T_sensor_vehicle)
        self._memo: dict[tuple[int, int], tuple[np.ndarray, ReferencePath | None, float]] = {}

    def trunk_frame(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """``(T_world_trunk, T_o_t)`` of the taught vertex at path index k (vehicle frame, teach world)."""
        T_wt = self.T_world_trunk[k]
        return T_wt, gravity_aligned_T_o_t(self.C_g_world @ T_wt[:3, :3])

    def T_g_o(self, k: int) -> np.ndarray:
        """The frame o of trunk k in the map's gravity-aligned frame g (4x4): ``T_g_world T_world_t inv(T_o_t)``."""
        T_wt, T_o_t = self.trunk_frame(k)
        T_g_world = np.eye(4)
        T_g_world[:3, :3] = self.C_g_world
        return T_g_world @ T_wt @ inv_T(T_o_t)

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
            except EstimationError:       # fewer than two distinct taught vertices
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
    vertex_ever: np.ndarray           # a localization at or before the vertex (the whole run's, not the view's)
    vertex_direction: np.ndarray
    vertex_off_route: np.ndarray
    frame_t_ns: np.ndarray
    unknown: str | None = None

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
            loc, ever, off = (self.vertex_localized[ii] & has, self.vertex_ever[ii] & has,
                              self.vertex_off_route[ii] & has)
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

    def _state(self, t_ns: int, k: int, with_covariance: bool) -> ControllerState:
        """The smoother's state at ``t_ns`` in trunk k's frame o, without validity."""
        self._check_state_at(t_ns)
        T_o_t, _, _ = self.route.trunk(k)
        s = self.trajectory.state_at(int(t_ns), with_covariance=with_covariance)
        cs = controller_state(s, self.route.T_world_trunk[k], T_o_t, self.route.T_sensor_vehicle)
        window = self.route.acceleration_window_s
        if window <= 0.0:
            return cs
        # the acceleration of the vehicle origin from a fit of the knots' velocities (smoothing.acceleration_window_s)
        a_world, cov_world = self.trajectory.fitted_acceleration(int(t_ns), window, self.route.T_sensor_vehicle)
        C_o_world = T_o_t[:3, :3] @ self.route.T_world_trunk[k][:3, :3].T
        return dataclasses.replace(cs, acceleration=C_o_world @ a_world,
                                   acceleration_covariance=C_o_world @ cov_world @ C_o_world.T)

    def controller_state_at(self, t_ns: int, trunk_index: int | None = None, *,
                            with_covariance: bool = False, commands: CommandLog | None = None) -> ControllerState:
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

    def _with_commands(self, cs: ControllerState, k: int, t_knot_ns: int, t_ns: int,
                       commands: CommandLog) -> ControllerState:
        """``cs`` (extrapolated at constant velocity from the knot at ``t_knot_ns``) moved by the commanded
        accelerations since that knot: ``dv = int a``, ``dp = int (t - tau) a`` (zero-order hold)."""
        dp_g, dv_g, a_g = commands.integrate(t_knot_ns, t_ns)
        C_o_g = self.route.T_g_o(k)[:3, :3].T
        return dataclasses.replace(cs, position=cs.position + C_o_g @ dp_g, velocity=cs.velocity + C_o_g @ dv_g,
                                   acceleration=C_o_g @ a_g, acceleration_covariance=None)

    def window(self, t_end_ns: int, n: int, dt_s: float) -> OutputWindow:
        """The outputs ``y = (p, psi)`` of ``n`` samples ``dt_s`` apart ending at ``t_end_ns``, all in the frame o of
        the trunk at ``t_end_ns`` (one fixed frame: no jump where the trunk moves on), with their joint covariance
        (:meth:`~vtr.state.smoothing.KnotTrajectory.joint_covariance` mapped through each output's Jacobian)."""
        if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 1:
            raise EstimationError(f"window: n must be a whole number >= 1, got {n!r}")
        if not (isinstance(dt_s, int | float) and math.isfinite(dt_s) and dt_s > 0):
            raise EstimationError(f"window: dt_s must be a finite time > 0 s, got {dt_s!r}")
        step_ns = int(round(dt_s * NS_PER_S))
        t = int(t_end_ns) - step_ns * np.arange(n - 1, -1, -1, dtype=np.int64)
        self._check_state_at(int(t[0]))
        k = int(self.trunk_index_at(np.array([t_end_ns]))[0])
        P, yaw, H = np.zeros((n, 3)), np.zeros(n), np.zeros((4 * n, 12 * n))
        status = []
        for j, tj in enumerate(t):
            cs = self.controller_state_at(int(tj), k)
            P[j], yaw[j] = cs.position, cs.yaw
            status.append(cs.status.value)
            H[4 * j:4 * j + 4, 12 * j:12 * j + 12] = output_jacobian(cs.T_o_a, self.route.T_sensor_vehicle)
        cov = H @ self.trajectory.joint_covariance(t) @ H.T
        yaw = np.unwrap(yaw)
        return OutputWindow(t_ns=t, position=P, yaw=yaw, covariance=0.5 * (cov + cov.T),
                            trunk_id=int(self.route.path.ids[k]), T_g_o=self.route.T_g_o(k), status=np.array(status))

    def states(self, t_ns: np.ndarray, *, with_covariance: bool = True) -> StateTable:
        """Controller states and path errors at the given times (int64 ns, not before the first vertex); with
        ``with_covariance`` the standard deviations of position and velocity in o too."""
        t_ns = np.asarray(t_ns, np.int64)
        n = len(t_ns)
        if self.unknown is not None:
            nan3, nan = np.full((n, 3), np.nan), np.full(n, np.nan)
            trunks = self.trunk_index_at(t_ns)
            return StateTable(t_ns=t_ns, position=nan3, velocity=nan3.copy(), acceleration=nan3.copy(), yaw=nan,
                              trunk_id=self.route.path.ids[trunks], lateral=nan.copy(), vertical=nan.copy(),
                              along_track=nan.copy(), localized=np.zeros(n, bool), direction=self.direction_at(t_ns),
                              status=np.full(n, StateStatus.UNKNOWN.value),
                              position_sigma=nan3.copy() if with_covariance else None,
                              velocity_sigma=nan3.copy() if with_covariance else None)
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
            except EstimationError:         # a pause: no segment reaches this time (the row is unknown)
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
        lat[~localized] = ver[~localized] = np.nan        # no path error where the repeat is not localized
        return StateTable(t_ns=t_ns, position=P, velocity=Vel, acceleration=A, yaw=yaw,
                          trunk_id=self.route.path.ids[trunks], lateral=lat, vertical=ver, along_track=along,
                          localized=localized, direction=direction, status=status,
                          position_sigma=sig_p if with_covariance else None,
                          velocity_sigma=sig_v if with_covariance else None)


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
