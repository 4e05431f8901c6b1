"""One route followed online: a camera thread feeds frames, a control thread asks for the state, a window of outputs
and the perception constraint (docs/online.md).

:class:`OnlineRepeat` owns the repeat (odometry, the localization chain), the state estimator (the smoother) and, with a
perception model, the taught-path field, for one route. The locking rule, the one there is:

* :meth:`OnlineRepeat.feed` runs on the camera thread (one feeder at a time; a second feeder waits). After each frame it
  *publishes* an immutable view of the state (:class:`~vtr.navigation.repeat_state.RepeatStateView`, the last
  ``history_s`` seconds of smoother knots copied, the chain's verdicts) by replacing one reference.
* Every query (:meth:`state`, :meth:`window`, :meth:`constraint`, :attr:`localized`) reads the latest published view and
  never takes a lock: a reader sees a frame wholly or not at all, never blocks the feeder, and is never blocked by it
  beyond the copy of that reference.

The map is never written: the repeat's own vertices go to a private copy in temporary space, removed on
:meth:`close` (as ``vtr repeat --read-only-map``). Before the first localization every query raises
:class:`~vtr.errors.NotLocalizedError` (an ``EstimationError``), never ``IndexError``.
"""

from __future__ import annotations

import tempfile
import threading
from pathlib import Path

import numpy as np

from perception_model.model import PerceptionModel

from ..config import Config
from ..errors import EstimationError, NotLocalizedError
from ..map import Map, copy_map_file
from ..navigation.repeat import Repeat, RepeatStep
from ..navigation.repeat_state import RepeatStateEstimator
from ..navigation.state_view import CommandLog, OutputWindow, RepeatStateView
from ..state.controller import ControllerState
from ..types import StereoImages
from .field import CameraMount, FieldEvaluation, TaughtPathField

#: seconds of smoother knots each published view keeps (a window of chapter 8's length and the MPC's last second)
DEFAULT_HISTORY_S = 2.0


class OnlineRepeat:
    """The repeat of one taught route, online: :meth:`feed` on the camera thread, queries from any other.

    Args:
        map_path: the taught map (only read: a private copy takes the repeat's vertices).
        config: the configuration (default ``Config()``).
        model: a perception model: :meth:`constraint` needs one.
        gravity_up: overrides the map's stored up direction (first teach camera's frame).
        start_index: optional hint of the taught vertex the repeat starts near (never needed).
        mount: the camera on the vehicle for the field (lever arm, axis yaw).
        history_s: seconds of state each published view keeps (queries further back raise ``EstimationError``).
        allow_partial: follow a route whose teach run did not finish.
    """

    def __init__(
        self,
        map_path: str | Path,
        config: Config | None = None,
        *,
        model: PerceptionModel | None = None,
        gravity_up: np.ndarray | None = None,
        start_index: int | None = None,
        mount: CameraMount | None = None,
        history_s: float = DEFAULT_HISTORY_S,
        allow_partial: bool = False,
    ) -> None:
        if not (isinstance(history_s, int | float) and 0 < history_s < float("inf")):
            raise EstimationError(f"history_s: expected a finite time > 0 s, got {history_s!r}")
        config = config or Config()
        map_path = Path(map_path)
        with Map.open(map_path) as m:  # a readable map with a route, not being written by another process
            m.check_taught_route(allow_partial)
        self._tmp = tempfile.TemporaryDirectory(prefix="vtr-online-")
        try:
            copy = Path(self._tmp.name) / map_path.name
            copy_map_file(map_path, copy)
            self.map = Map.open(copy, "a")
            up = self.map.gravity_up if gravity_up is None else np.asarray(gravity_up, float)
            self.repeat = Repeat(
                self.map, config, source=f"online:{map_path}", start_index=start_index, allow_partial=allow_partial
            )
            self.estimator = RepeatStateEstimator.for_route(
                self.repeat.chain.path, config.smoothing, config.localization, self.map.camera.T_vehicle_sensor, up
            )
            self.field = (
                None
                if model is None
                else TaughtPathField.from_map(
                    self.map, model, up_map=up, mount=mount, config=config.localization, control=config.control
                )
            )
        except BaseException:
            self._tmp.cleanup()
            raise
        self.history_s = float(history_s)
        self._feeding = threading.Lock()
        self._commanding = threading.Lock()  # the command log's writers (readers take the published log)
        self._command_t: list[int] = []
        self._command_a: list[np.ndarray] = []
        self._commands: CommandLog | None = None
        self._view: RepeatStateView = self.estimator.view(self.history_s)
        self._latest: RepeatStep | None = None
        self._closed = False

    # -- the camera thread ---------------------------------------------------------------------------------------

    def feed(self, images: StereoImages) -> RepeatStep:
        """Process one rectified stereo pair (odometry; localization when it becomes a keyframe; the smoother), then
        publish the new view. One feeder at a time."""
        with self._feeding:
            if self._closed:
                raise EstimationError("feed: this OnlineRepeat is closed")
            step = self.repeat.process(images)
            self.estimator.add(step)
            view = self.estimator.view(self.history_s)
            self._latest = step
            self._view = view  # the publication: one reference, replaced whole
        return step

    # -- any thread ----------------------------------------------------------------------------------------------

    @property
    def view(self) -> RepeatStateView:
        """The latest published view (immutable): query it several times for answers about one same frame."""
        return self._view

    @property
    def latest(self) -> RepeatStep | None:
        """The last frame's step (None before the first)."""
        return self._latest

    @property
    def localized(self) -> bool:
        """The chain's verdict after the last frame fed (False before the first)."""
        step = self._latest
        return bool(step is not None and step.localized)

    def command(self, t_ns: int, acceleration_g: np.ndarray) -> None:
        """Tell the estimator the acceleration the controller commanded from ``t_ns`` on (vehicle origin, map gravity
        frame g, m/s²; e.g. the flat model's input): after the newest keyframe :meth:`state` extrapolates with the
        commands instead of at constant velocity (thesis eq. 8.15). Times must increase."""
        a = np.asarray(acceleration_g, float)
        if a.shape != (3,) or not np.all(np.isfinite(a)):
            raise EstimationError(f"command: acceleration_g must be 3 finite numbers, got {acceleration_g!r}")
        with self._commanding:
            t_ns = _time(t_ns)
            if self._command_t and t_ns <= self._command_t[-1]:
                raise EstimationError(f"command: t_ns={int(t_ns)} is not after the previous command's")
            self._command_t.append(t_ns)
            self._command_a.append(a)
            keep = self._view.trajectory.first_time_ns
            if keep is not None and len(self._command_t) > 1 and self._command_t[1] < keep:
                drop = int(np.searchsorted(self._command_t, keep, side="right")) - 1
                del self._command_t[:drop], self._command_a[:drop]
            self._commands = CommandLog(np.array(self._command_t, np.int64), np.array(self._command_a))

    def state(self, t_ns: int, *, with_covariance: bool = True) -> ControllerState:
        """The controller state at ``t_ns`` (its status, direction, covariances in o; see
        :meth:`RepeatStateView.controller_state_at`), extrapolated with the commands sent (:meth:`command`), if any.
        ``NotLocalizedError`` before the first localization; an ``EstimationError`` more than
        ``smoothing.max_extrapolation_s`` after the last keyframe."""
        return self._view.controller_state_at(_time(t_ns), with_covariance=with_covariance, commands=self._commands)

    def window(self, t_end_ns: int, n: int, dt_s: float) -> OutputWindow:
        """``n`` outputs ``(p, psi)`` ``dt_s`` apart ending at ``t_end_ns`` in one frame, with their joint covariance
        (:meth:`RepeatStateView.window`); samples after the newest keyframe extrapolated with the commands sent, as
        :meth:`state` is."""
        return self._view.window(_time(t_end_ns), n, dt_s, commands=self._commands)

    def constraint(
        self, positions_g: np.ndarray, yaw_g: np.ndarray, *, axes: np.ndarray | None = None, gradient: bool = True
    ) -> FieldEvaluation:
        """The perception chance constraint along a horizon of vehicle outputs in the map's gravity frame g (an MPC's
        prediction), each step's trunk chosen from the latest trunk in the chain's direction of travel."""
        if self.field is None:
            raise EstimationError("constraint: this OnlineRepeat was made without a perception model")
        v = self._view
        if not len(v.vertex_t_ns) or not v.vertex_ever[-1]:
            raise NotLocalizedError("constraint: the repeat has not been localized yet (no trunk to start from)")
        previous = int(v.vertex_trunk[-1])
        direction = int(v.vertex_direction[-1])
        pos = np.asarray(positions_g, float)
        return self.field.evaluate(
            pos, yaw_g, previous=previous, axes=axes, direction=direction or 1, gradient=gradient
        )

    # -- lifetime ------------------------------------------------------------------------------------------------

    def close(self) -> None:
        """End the repeat (its private map copy is removed). Idempotent."""
        with self._feeding:
            if self._closed:
                return
            self._closed = True
            try:
                self.map.close()
            finally:
                self._tmp.cleanup()

    def __enter__(self) -> OnlineRepeat:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _time(t_ns: object) -> int:
    """A query time as int ns; ``NotLocalizedError`` for None (no frame yet: the view's ``last_frame_t_ns``),
    ``EstimationError`` for anything else that is not a whole number."""
    if t_ns is None:
        raise NotLocalizedError("no time: no frame has been fed yet")
    if isinstance(t_ns, bool) or not isinstance(t_ns, int | np.integer):
        raise EstimationError(f"t_ns: expected a whole number of nanoseconds, got {type(t_ns).__name__}")
    return int(t_ns)


__all__ = ["DEFAULT_HISTORY_S", "OnlineRepeat"]
