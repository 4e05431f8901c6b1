"""Where the controllers of the §8.4.1 simulation read their outputs (docs/discrete_flatness.md).

:class:`MeasuredOutputs` holds the noisy positions at the control rate and their first-order finite differences (the
thesis' PD and flatness MPC); :class:`SmootherOutputs` is vtr's continuous-time smoother fed at a camera's rate,
queried as the online estimator (:class:`~vtr.control.online.OnlineRepeat`) is: ``window(t_end_ns, n, dt_s)``,
``state(t_ns)`` and ``command(t_ns, acceleration)`` (the commands sent, for the extrapolation with them, eq. 8.15);
:class:`SmootherBatch` stacks one per trial. :class:`ReceivedPositions` gives PD and the flatness MPC the
first-order differences of the positions a source answered at their ticks (the thesis' definition of both).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Protocol

import numpy as np

from ..config import SmoothingConfig
from ..conventions import NS_PER_S
from ..errors import EstimationError
from ..navigation.state_view import CommandLog
from ..state.smoothing import TrajectorySmoother
from ..state.trajectory import KnotTrajectory, TrajectoryState

#: The 1-D motion has no rotation; the smoother is told its (identity) attitude with this standard deviation
#: (rad) so that the 6x6 pose covariance is definite. Rotation and x are uncoupled about the identity.
ROTATION_SIGMA_RAD = 1e-3
#: Seconds of knots each published view keeps (as ``OnlineRepeat``'s default ``history_s``).
HISTORY_S = 2.0


class OutputSource(Protocol):
    """Outputs of a batch of vehicles as a controller reads them (times in int ns, positions in m).

    ``window`` returns positions (batch, n) at ``t_end_ns - (n - 1 - i) dt_s``; ``state`` the flat state
    ``(p, v, a)`` (batch, 3) at ``t_ns``; ``window_end_ns`` the latest time at or before ``t_ns`` its window answers
    for (the newest measurement of raw outputs; ``t_ns`` itself for an estimator that carries its outputs to now
    with the commands sent); ``command`` takes the acceleration (batch,) the
    controllers expect from ``t_ns`` on (the commands sent).
    """

    measurement_period_ns: int

    def measure(self, t_ns: int, positions_m: np.ndarray) -> None: ...
    def command(self, t_ns: int, acceleration_mps2: np.ndarray) -> None: ...
    def window(self, t_end_ns: int, n: int, dt_s: float) -> np.ndarray: ...
    def state(self, t_ns: int) -> np.ndarray: ...
    def window_end_ns(self, t_ns: int) -> int: ...


def sample_times(t_end_ns: int, n: int, dt_s: float) -> list[int]:
    dt_ns = round(dt_s * NS_PER_S)
    return [t_end_ns - (n - 1 - i) * dt_ns for i in range(n)]


class MeasuredOutputs:
    """Noisy positions at every control tick, as measured; the state is their first-order finite
    differences ``v = (y_k - y_{k-1}) / dt``, ``a = (v_k - v_{k-1}) / dt`` (the thesis' flatness MPC and PD).
    The commands sent are not used (a raw measurement has no extrapolation)."""

    def __init__(self, period_ns: int) -> None:
        self.measurement_period_ns = period_ns
        self._y: dict[int, np.ndarray] = {}

    def measure(self, t_ns: int, positions_m: np.ndarray) -> None:
        self._y[t_ns] = np.asarray(positions_m, float).copy()

    def command(self, t_ns: int, acceleration_mps2: np.ndarray) -> None:
        return None

    def _at(self, t_ns: int) -> np.ndarray:
        if t_ns not in self._y:
            raise EstimationError(f"t_ns={t_ns}: no measurement at that time")
        return self._y[t_ns]

    def window(self, t_end_ns: int, n: int, dt_s: float) -> np.ndarray:
        return np.stack([self._at(t) for t in sample_times(t_end_ns, n, dt_s)], axis=1)

    def state(self, t_ns: int) -> np.ndarray:
        dt = self.measurement_period_ns / NS_PER_S
        y2, y1, y0 = self.window(t_ns, 3, dt).T
        return np.stack([y0, (y0 - y1) / dt, (y0 - 2 * y1 + y2) / dt**2], axis=1)

    def window_end_ns(self, t_ns: int) -> int:
        return max(t for t in self._y if t <= t_ns)


class SmootherOutputs:
    """One vehicle's outputs from vtr's :class:`~vtr.state.smoothing.TrajectorySmoother`: the 1-D position is
    the translation along x of an SE(3) pose (identity attitude), fed as an absolute pose measurement with
    the position noise's variance on each axis.

    The queries answer as :class:`~vtr.control.online.OnlineRepeat`'s do, on the knots published after each
    measurement: ``window`` the WNOA mean's positions; ``state`` the mean's position and velocity with the
    acceleration fitted to the knots' velocities (``smoothing.acceleration_window_s``; the WNOA mean's when 0),
    and, past the newest knot, the constant-velocity extrapolation moved by the commands sent
    (:class:`~vtr.navigation.state_view.CommandLog`, zero-order hold) with the command in force as acceleration.

    With ``command_anchor_ns`` > 0 and commands given, that extrapolation starts ``command_anchor_ns`` before the
    newest knot instead (inside the smoothed trajectory, not at its natural-spline end): any ``t_ns`` after the
    anchor is the mean's position and velocity at the anchor carried to ``t_ns`` with the commands sent (eq. 8.15
    carries a past window forward with the inputs sent the same way). ``OnlineRepeat.state`` extrapolates from
    the newest knot (``command_anchor_ns`` = 0).

    With ``inputs_in_prior`` the smoother knows the commands sent inside its window too, not only past it: it
    smooths the measured positions minus the commanded motion alone (:meth:`CommandLog.motion`, from rest) and the
    queries add that motion back. For a 1-D translation this is exactly the WNOA prior about the commanded
    acceleration (``p'' = a_cmd + w`` instead of ``p'' = w``); past the anchor the answers take the same form as
    without it (the mean at the anchor carried with the commands sent), only the mean there differs.
    ``OnlineRepeat``'s SE(3) smoother uses the commands past its newest knot only.
    """

    def __init__(
        self, smoothing: SmoothingConfig, sigma_m: float, command_anchor_ns: int = 0, inputs_in_prior: bool = False
    ) -> None:
        if not (sigma_m > 0 and math.isfinite(sigma_m)):
            raise EstimationError(f"sigma_m: expected a positive finite noise level, got {sigma_m}")
        if isinstance(command_anchor_ns, bool) or not isinstance(command_anchor_ns, int) or command_anchor_ns < 0:
            raise EstimationError(f"command_anchor_ns: expected a whole number of ns >= 0, got {command_anchor_ns!r}")
        self.command_anchor_ns = command_anchor_ns
        self.inputs_in_prior = bool(inputs_in_prior)
        self.smoother = TrajectorySmoother(smoothing)
        self.acceleration_window_s = smoothing.acceleration_window_s
        self._cov = np.diag([ROTATION_SIGMA_RAD**2] * 3 + [sigma_m**2] * 3)
        self._view: KnotTrajectory | None = None
        self._command_t: list[int] = []
        self._command_a: list[float] = []
        self._commands: CommandLog | None = None

    def add(self, t_ns: int, x_m: float) -> None:
        """A measured position ``x_m`` (m) at ``t_ns``; publishes the knots the queries read."""
        T = np.eye(4)
        T[0, 3] = x_m - self._commanded(int(t_ns))[0]
        self.smoother.add_pose(t_ns, T, self._cov)
        self._view = self.smoother.snapshot(int(t_ns) - round(HISTORY_S * NS_PER_S))

    def command(self, t_ns: int, acceleration_mps2: float) -> None:
        """The acceleration the controller expects from ``t_ns`` on (times increase)."""
        if self._command_t and t_ns <= self._command_t[-1]:
            raise EstimationError(f"command: t_ns={t_ns} is not after the previous command's")
        self._command_t.append(int(t_ns))
        self._command_a.append(float(acceleration_mps2))
        a = np.zeros((len(self._command_a), 3))
        a[:, 0] = self._command_a
        self._commands = CommandLog(np.array(self._command_t, np.int64), a)

    @property
    def view(self) -> KnotTrajectory:
        if self._view is None:
            raise EstimationError("smoother outputs: no measurement yet")
        return self._view

    def window(self, t_end_ns: int, n: int, dt_s: float) -> np.ndarray:
        """Positions (n,) at ``t_end_ns - (n - 1 - i) dt_s``: the mean's, and after the anchor (the newest knot
        when ``command_anchor_ns`` = 0) the ones :meth:`state` answers, carried there with the commands sent
        (``OnlineRepeat.window`` extrapolates so too)."""
        return np.array([self._carried(t)[0][0] for t in sample_times(t_end_ns, n, dt_s)])

    def state(self, t_ns: int) -> np.ndarray:
        """``(p m, v m/s, a m/s^2)`` at ``t_ns``."""
        (p, vel, a), mean = self._carried(t_ns)
        if a is None:
            a = mean.linear_acceleration_world[0]
            if self.acceleration_window_s > 0:
                a = self.view.fitted_acceleration(t_ns, self.acceleration_window_s)[0][0]
            a += self._commanded(t_ns)[2]
        return np.array([p, vel, a])

    def _commanded(self, t_ns: int) -> tuple[float, float, float]:
        """Position, velocity and acceleration of the commanded motion alone at ``t_ns`` where the smoother's prior
        holds it (``inputs_in_prior``); zeros otherwise."""
        if not self.inputs_in_prior or self._commands is None:
            return 0.0, 0.0, 0.0
        p, v, a = self._commands.motion(t_ns)
        return float(p[0]), float(v[0]), float(a[0])

    def _carried(self, t_ns: int) -> tuple[tuple[float, float, float | None], TrajectoryState]:
        """Position and velocity at ``t_ns``: the mean's up to the anchor (the newest knot without commands or with
        ``command_anchor_ns`` = 0), carried from it at its velocity after, plus the commanded motion (all of it where
        the prior holds it, else what the commands add after the anchor); and the command in force there (None where
        the mean answers). Also the mean's state it started from (at ``t_ns`` where the mean answers)."""
        v = self.view
        t_anchor = last = v.last_time_ns
        if self._commands is not None and self.command_anchor_ns > 0 and last is not None:
            first = v.first_time_ns
            t_anchor = max(last - self.command_anchor_ns, last if first is None else first)
        t_mean = t_ns if t_anchor is None else min(t_ns, t_anchor)
        s = v.state_at(t_mean, with_covariance=False)
        ahead_s = (t_ns - t_mean) / NS_PER_S
        p, vel = s.position[0] + s.linear_velocity_world[0] * ahead_s, s.linear_velocity_world[0]
        if self._commands is None:
            return (float(p), float(vel), None), s
        c, c_v, c_a = (x[0] for x in self._commands.motion(t_ns))
        if not self.inputs_in_prior:  # only what the commands add after t_mean
            c0, c0_v, _ = (x[0] for x in self._commands.motion(t_mean))
            c, c_v = c - c0 - c0_v * ahead_s, c_v - c0_v
        return (float(p + c), float(vel + c_v), (float(c_a) if t_ns > t_mean else None)), s

    def newest_ns(self) -> int:
        t = self.view.last_time_ns
        if t is None:
            raise EstimationError("smoother outputs: no measurement yet")
        return t


class SmootherBatch:
    """:class:`OutputSource` over one :class:`SmootherOutputs` per vehicle, fed every ``period_ns``; windows end
    at the time asked (each source carries its outputs there with the commands sent)."""

    def __init__(self, sources: Sequence[SmootherOutputs], period_ns: int) -> None:
        self.sources = list(sources)
        self.measurement_period_ns = period_ns

    def measure(self, t_ns: int, positions_m: np.ndarray) -> None:
        for src, x in zip(self.sources, np.asarray(positions_m, float), strict=True):
            src.add(t_ns, float(x))

    def command(self, t_ns: int, acceleration_mps2: np.ndarray) -> None:
        for src, a in zip(self.sources, np.asarray(acceleration_mps2, float), strict=True):
            src.command(t_ns, float(a))

    def window(self, t_end_ns: int, n: int, dt_s: float) -> np.ndarray:
        return np.stack([src.window(t_end_ns, n, dt_s) for src in self.sources])

    def state(self, t_ns: int) -> np.ndarray:
        return np.stack([src.state(t_ns) for src in self.sources])

    def window_end_ns(self, t_ns: int) -> int:
        """``t_ns`` (an ``EstimationError`` before the first measurement)."""
        for src in self.sources:
            src.newest_ns()
        return t_ns


class ReceivedPositions:
    """:class:`OutputSource` over ``source`` whose ``state`` is the first-order differences of the positions
    ``source.state`` answered at the control ticks, ``v_k = (p_k - p_{k-1}) / dt``, ``a_k = (v_k - v_{k-1}) / dt``
    (``dt`` = ``period_ns``): PD and the flatness MPC of §8.4.1 as defined there ("position and first-order
    finite-difference velocity and acceleration estimates"), with an estimator's positions in place of the sensor's.
    Each tick's position is kept as it was answered then; a tick not queried before (the first ones) is the
    source's answer now. ``measure``, ``command``, ``window`` and ``window_end_ns`` pass through."""

    def __init__(self, source: OutputSource, period_ns: int) -> None:
        self.source = source
        self.period_ns = int(period_ns)
        self.measurement_period_ns = source.measurement_period_ns
        self._p: dict[int, np.ndarray] = {}

    def measure(self, t_ns: int, positions_m: np.ndarray) -> None:
        self.source.measure(t_ns, positions_m)

    def command(self, t_ns: int, acceleration_mps2: np.ndarray) -> None:
        self.source.command(t_ns, acceleration_mps2)

    def window(self, t_end_ns: int, n: int, dt_s: float) -> np.ndarray:
        return self.source.window(t_end_ns, n, dt_s)

    def window_end_ns(self, t_ns: int) -> int:
        return self.source.window_end_ns(t_ns)

    def _position(self, t_ns: int) -> np.ndarray:
        if t_ns not in self._p:
            self._p[t_ns] = np.asarray(self.source.state(t_ns), float)[:, 0].copy()
        return self._p[t_ns]

    def state(self, t_ns: int) -> np.ndarray:
        self._p[t_ns] = np.asarray(self.source.state(t_ns), float)[:, 0].copy()  # this tick's answer, kept
        dt = self.period_ns / NS_PER_S
        y0, y1, y2 = (self._position(t_ns - i * self.period_ns) for i in range(3))
        return np.stack([y0, (y0 - y1) / dt, (y0 - 2 * y1 + y2) / dt**2], axis=1)


__all__ = [
    "HISTORY_S",
    "ROTATION_SIGMA_RAD",
    "MeasuredOutputs",
    "OutputSource",
    "ReceivedPositions",
    "SmootherBatch",
    "SmootherOutputs",
    "sample_times",
]
