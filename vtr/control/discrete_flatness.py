"""Discrete-time flatness control against position noise: the thesis' §8.4.1 simulation (ch. 8, Fig. 8.2).

A multirotor moves in 1-D (x) with first-order pitch dynamics (thesis eq. 8.11, Euler at ``plant_rate_hz``):
``x+ = x + dt v``, ``v+ = v + dt g tan(theta)``, ``theta+ = theta + dt (k theta_cmd - theta) / tau``. Three
controllers at ``control_rate_hz`` track ``y_ref = A t sin(omega t)`` from rest:

* :class:`PDController` - position and velocity error with the reference's acceleration fed forward;
* :class:`FlatnessMPC` - the flatness-based MPC of ch. 3 (triple integrator in the flat state ``(p, v, a)``,
  jerk input, feedforward linearization through the pitch dynamics), fed a state estimate;
* :class:`DiscreteFlatnessController` - ch. 8: a window of ``r = 3`` outputs and the inputs sent since,
  pushed forward through the input-to-output map (8.15), the output trajectory optimized with cost (8.16),
  and the input read off the first four optimized outputs with the output-to-input map (8.12).

Both predictive controllers minimize the same cost (position error and jerk) over the same horizon, so they
differ only in what they are fed. The unconstrained quadratic programs are solved in closed form: each
reduces to one precomputed gain row (no solver per tick), vectorized over trials. Where the outputs come
from is an :class:`OutputSource`: :class:`MeasuredOutputs` (noisy positions at the control rate and their
finite differences) or :class:`SmootherOutputs` (vtr's continuous-time smoother fed at a camera's rate).
See docs/discrete_flatness.md for the derivation, the settings and the measured figures.
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Literal, Protocol

import numpy as np

from ..config import Range, Section, SmoothingConfig, setting
from ..conventions import NS_PER_S
from ..errors import ConfigError, EstimationError
from ..state.smoothing import TrajectorySmoother
from .flat_model import GRAVITY_MPS2

#: Window of the 1-D model: the input at step k is fixed by outputs k..k+3 (8.12), the state by k..k+2.
WINDOW = 3
#: The 1-D motion has no rotation; the smoother is told its (identity) attitude with this standard deviation
#: (rad) so that the 6x6 pose covariance is definite. Rotation and x are uncoupled about the identity.
ROTATION_SIGMA_RAD = 1e-3

Loop = Literal["perfect", "estimator"]
ControllerName = Literal["pd", "flatness_mpc", "discrete_flatness"]
LOOPS: tuple[Loop, ...] = ("perfect", "estimator")
CONTROLLERS: tuple[ControllerName, ...] = ("pd", "flatness_mpc", "discrete_flatness")
RESULT_COLUMNS = ("loop", "controller", "sigma_m", "mean_error_m", "std_error_m", "max_error_m", "trials")


@dataclass(frozen=True)
class DiscreteFlatnessSettings(Section):
    """Every number of the simulation, with its domain (checked when built)."""

    SECTION: ClassVar[str] = "discrete_flatness"

    plant_rate_hz: float = setting(200.0, Range(0.0, 100_000.0, lo_open=True))  # Euler step of (8.11)
    control_rate_hz: float = setting(50.0, Range(0.0, 10_000.0, lo_open=True))  # all three controllers
    # camera rate of the estimator loop (positions fed to the smoother)
    measurement_rate_hz: float = setting(10.0, Range(0.0, 10_000.0, lo_open=True))
    time_constant_s: float = setting(0.25, Range(0.0, 100.0, lo_open=True))  # tau of the pitch loop (ch. 3)
    attitude_gain: float = setting(1.4, Range(0.0, 100.0, lo_open=True))  # k of the pitch loop (ch. 3)
    # bound on the pitch the inner loop is commanded to reach (k theta_cmd); the reference needs 0.67 rad
    pitch_max_rad: float = setting(math.pi / 4, Range(0.0, math.pi / 2, lo_open=True, hi_open=True))
    amplitude_m: float = setting(1.4, Range(0.0, 1e3))  # A of y_ref = A t sin(omega t)
    omega_rps: float = setting(1.0, Range(0.0, 1e3, lo_open=True))
    duration_s: float = setting(2 * math.pi, Range(0.0, 3600.0, lo_open=True))  # one period of omega
    # at rest before the reference starts: the measurement history and the smoother's first knots
    warmup_s: float = setting(0.5, Range(0.0, 60.0))
    horizon: int = setting(200, Range(4, 5000, integer=True))  # N of (8.16) and of the flatness MPC (4 s)
    q_position: float = setting(1.0, Range(0.0, 1e9, lo_open=True))  # tracking weight (1/m^2)
    # Tuning (calibrate()): as in the thesis, the three are tuned to track alike without noise (perfect loop):
    # PD critically damped at the bandwidth of its smallest noiseless error; each predictive controller's jerk
    # weight ((s^3/m)^2) then set so that its noiseless error equals PD's
    pd_kp: float = setting(20.25, Range(0.0, 1e6))  # PD position gain (1/s^2)
    pd_kd: float = setting(9.0, Range(0.0, 1e6))  # PD velocity gain (1/s)
    r_jerk_flatness_mpc: float = setting(4.4e-4, Range(0.0, 1e9, lo_open=True))
    r_jerk_discrete_flatness: float = setting(1.6e-3, Range(0.0, 1e9, lo_open=True))
    # white-noise-on-acceleration density of the estimator loop's smoother (m^2/s^3): the reference's mean
    # squared acceleration times the measurement period (reference_qc), so that the prior's velocity change
    # over one camera period has the reference's size
    qc_translation: float = setting(1.83, Range(0.0, 1e6, lo_open=True))
    smoother_lag_s: float = setting(1.0, Range(0.0, 3600.0, lo_open=True))  # fixed-lag window
    # the discrete-time flatness window ends this many measurement periods before the smoother's newest knot:
    # there the WNOA mean is a natural spline's end (zero acceleration); a knot or two inside it is not
    window_knots_back: int = setting(2, Range(0, 100, integer=True))

    def __post_init__(self) -> None:
        super().__post_init__()
        for name, fast, slow in (("plant_rate_hz/control_rate_hz", self.plant_rate_hz, self.control_rate_hz),
                                 ("control_rate_hz/measurement_rate_hz", self.control_rate_hz,
                                  self.measurement_rate_hz)):
            ratio = fast / slow
            if ratio < 1 or abs(ratio - round(ratio)) > 1e-9:
                raise ConfigError(f"discrete_flatness: {name} must be a whole number >= 1, got {ratio:g}")
        history_s = self.window_knots_back / self.measurement_rate_hz + (WINDOW - 1) / self.control_rate_hz
        if self.warmup_s < history_s - 1e-9:
            raise ConfigError(f"discrete_flatness: warmup_s={self.warmup_s:g} is shorter than the first window's "
                              f"history ({history_s:g} s: window_knots_back camera periods and {WINDOW - 1} ticks)")
        if abs(NS_PER_S / self.control_rate_hz - round(NS_PER_S / self.control_rate_hz)) > 1e-6:
            raise ConfigError(f"discrete_flatness: control_rate_hz={self.control_rate_hz:g} has no whole-ns period")

    def replace(self, **changes: Any) -> DiscreteFlatnessSettings:
        """A copy with ``changes`` (checked like any other)."""
        return dataclasses.replace(self, **changes)

    @property
    def control_dt_s(self) -> float:
        return 1.0 / self.control_rate_hz

    @property
    def control_dt_ns(self) -> int:
        return round(NS_PER_S / self.control_rate_hz)

    @property
    def substeps(self) -> int:
        """Plant steps per control tick (the input is held over them)."""
        return round(self.plant_rate_hz / self.control_rate_hz)

    @property
    def measurement_every(self) -> int:
        """Control ticks per camera measurement in the estimator loop."""
        return round(self.control_rate_hz / self.measurement_rate_hz)

    @property
    def warmup_ticks(self) -> int:
        return math.ceil(self.warmup_s * self.control_rate_hz - 1e-9)

    @property
    def ticks(self) -> int:
        """Control ticks from the reference's start to ``duration_s``."""
        return math.ceil(self.duration_s * self.control_rate_hz - 1e-9)

    @property
    def command_max(self) -> float:
        """Largest pitch command (rad): the inner loop settles at ``attitude_gain`` times it."""
        return self.pitch_max_rad / self.attitude_gain


# ----------------------------------------------------------------------------------------------
# Reference and plant


@dataclass(frozen=True)
class SpiralReference:
    """``y_ref(t) = A t sin(omega t)`` for ``t >= 0`` (m), at rest at 0 before; derivatives in closed form."""

    amplitude_m: float
    omega_rps: float

    def derivatives(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity, acceleration and jerk at times ``t_s`` (any shape)."""
        t = np.asarray(t_s, float)
        on = t >= 0.0
        t = np.maximum(t, 0.0)
        A, w = self.amplitude_m, self.omega_rps
        s, c = np.sin(w * t), np.cos(w * t)
        return (A * t * s, A * (s + w * t * c), on * A * (2 * w * c - w * w * t * s),
                on * A * w * w * (-3 * s - w * t * c))

    def position(self, t_s: np.ndarray) -> np.ndarray:
        return self.derivatives(t_s)[0]


def reference_qc(settings: DiscreteFlatnessSettings, samples: int = 100_001) -> float:
    """White-noise-on-acceleration density (m^2/s^3) whose velocity change over one measurement period has
    the reference's mean squared size: ``mean(y_ref''^2) / measurement_rate_hz``."""
    ref = SpiralReference(settings.amplitude_m, settings.omega_rps)
    a = ref.derivatives(np.linspace(0.0, settings.duration_s, samples))[2]
    return float(np.mean(a**2) / settings.measurement_rate_hz)


class PitchPlant:
    """The 1-D dynamics (8.11) for a batch of vehicles: state ``(x m, v m/s, theta rad)`` each, from rest."""

    def __init__(self, settings: DiscreteFlatnessSettings, batch: int) -> None:
        self.s = settings
        self.state = np.zeros((batch, 3))

    @property
    def position(self) -> np.ndarray:
        return self.state[:, 0].copy()

    def step(self, command: np.ndarray) -> None:
        """One Euler step of ``1 / plant_rate_hz`` with the pitch commands ``command`` (batch,)."""
        u = np.asarray(command, float)
        if u.shape != self.state[:, 0].shape or not np.all(np.isfinite(u)):
            raise EstimationError(f"command: expected {self.state.shape[0]} finite pitch commands, got {u.shape}")
        s, dt = self.s, 1.0 / self.s.plant_rate_hz
        x, v, th = self.state.T
        self.state = np.stack([x + dt * v, v + dt * GRAVITY_MPS2 * np.tan(th),
                               th + dt * (s.attitude_gain * u - th) / s.time_constant_s], axis=1)


# ----------------------------------------------------------------------------------------------
# Where the controllers' outputs come from


class OutputSource(Protocol):
    """Outputs of a batch of vehicles as a controller reads them (times in int ns, positions in m).

    ``window`` returns positions (batch, n) at ``t_end_ns - (n - 1 - i) dt_s``; ``state`` the flat state
    ``(p, v, a)`` (batch, 3) at ``t_ns``; ``measured_until_ns`` the latest time at or before ``t_ns`` whose
    window rests on measurements alone (no extrapolation).
    """

    measurement_period_ns: int

    def measure(self, t_ns: int, positions_m: np.ndarray) -> None: ...
    def window(self, t_end_ns: int, n: int, dt_s: float) -> np.ndarray: ...
    def state(self, t_ns: int) -> np.ndarray: ...
    def measured_until_ns(self, t_ns: int) -> int: ...


def _times(t_end_ns: int, n: int, dt_s: float) -> list[int]:
    dt_ns = round(dt_s * NS_PER_S)
    return [t_end_ns - (n - 1 - i) * dt_ns for i in range(n)]


class MeasuredOutputs:
    """Noisy positions at every control tick, as measured; the state is their first-order finite
    differences ``v = (y_k - y_{k-1}) / dt``, ``a = (v_k - v_{k-1}) / dt`` (the thesis' flatness MPC and PD)."""

    def __init__(self, period_ns: int) -> None:
        self.measurement_period_ns = period_ns
        self._y: dict[int, np.ndarray] = {}

    def measure(self, t_ns: int, positions_m: np.ndarray) -> None:
        self._y[t_ns] = np.asarray(positions_m, float).copy()

    def _at(self, t_ns: int) -> np.ndarray:
        if t_ns not in self._y:
            raise EstimationError(f"t_ns={t_ns}: no measurement at that time")
        return self._y[t_ns]

    def window(self, t_end_ns: int, n: int, dt_s: float) -> np.ndarray:
        return np.stack([self._at(t) for t in _times(t_end_ns, n, dt_s)], axis=1)

    def state(self, t_ns: int) -> np.ndarray:
        dt = self.measurement_period_ns / NS_PER_S
        y2, y1, y0 = self.window(t_ns, 3, dt).T
        return np.stack([y0, (y0 - y1) / dt, (y0 - 2 * y1 + y2) / dt**2], axis=1)

    def measured_until_ns(self, t_ns: int) -> int:
        return max(t for t in self._y if t <= t_ns)


class SmootherOutputs:
    """One vehicle's outputs from vtr's :class:`~vtr.state.smoothing.TrajectorySmoother`: the 1-D position is
    the translation along x of an SE(3) pose (identity attitude), fed as an absolute pose measurement with
    the position noise's variance on each axis.

    ``window(t_end_ns, n, dt_s)`` (positions (n,)) and ``state(t_ns)`` (``(p, v, a)``) are the calls of the
    online estimator that will replace it. After the newest knot the smoother extrapolates at constant velocity
    and at that knot its WNOA mean has zero acceleration (a natural spline's end), so :class:`SmootherBatch`
    ends the discrete-time flatness window ``knots_back`` knots earlier and the controller carries it to now
    with the inputs it sent (8.15).
    """

    def __init__(self, smoothing: SmoothingConfig, sigma_m: float) -> None:
        if not (sigma_m > 0 and math.isfinite(sigma_m)):
            raise EstimationError(f"sigma_m: expected a positive finite noise level, got {sigma_m}")
        self.smoother = TrajectorySmoother(smoothing)
        self._cov = np.diag([ROTATION_SIGMA_RAD**2] * 3 + [sigma_m**2] * 3)

    def add(self, t_ns: int, x_m: float) -> None:
        """A measured position ``x_m`` (m) at ``t_ns``."""
        T = np.eye(4)
        T[0, 3] = x_m
        self.smoother.add_pose(t_ns, T, self._cov)

    def window(self, t_end_ns: int, n: int, dt_s: float) -> np.ndarray:
        """Positions (n,) at ``t_end_ns - (n - 1 - i) dt_s``."""
        return np.array([self.smoother.state_at(t, with_covariance=False).position[0]
                         for t in _times(t_end_ns, n, dt_s)])

    def state(self, t_ns: int) -> np.ndarray:
        """``(p m, v m/s, a m/s^2)`` at ``t_ns``."""
        s = self.smoother.state_at(t_ns, with_covariance=False)
        return np.array([s.position[0], s.linear_velocity_world[0], s.linear_acceleration_world[0]])

    def newest_ns(self) -> int:
        t = self.smoother.last_time_ns
        if t is None:
            raise EstimationError("smoother outputs: no measurement yet")
        return t


class SmootherBatch:
    """:class:`OutputSource` over one :class:`SmootherOutputs` per vehicle, fed every ``period_ns``; windows
    end ``knots_back`` measurement periods before the newest knot."""

    def __init__(self, sources: Sequence[SmootherOutputs], period_ns: int, knots_back: int = 0) -> None:
        self.sources = list(sources)
        self.measurement_period_ns = period_ns
        self.knots_back = knots_back

    def measure(self, t_ns: int, positions_m: np.ndarray) -> None:
        for src, x in zip(self.sources, np.asarray(positions_m, float), strict=True):
            src.add(t_ns, float(x))

    def window(self, t_end_ns: int, n: int, dt_s: float) -> np.ndarray:
        return np.stack([src.window(t_end_ns, n, dt_s) for src in self.sources])

    def state(self, t_ns: int) -> np.ndarray:
        return np.stack([src.state(t_ns) for src in self.sources])

    def measured_until_ns(self, t_ns: int) -> int:
        newest = min(src.newest_ns() for src in self.sources)
        return min(t_ns, newest - self.knots_back * self.measurement_period_ns)


# ----------------------------------------------------------------------------------------------
# Controllers


class _Controller:
    """Shared clock and reference: tick k is at ``t_start_ns + k control_dt_ns`` and the reference starts there."""

    name: ControllerName

    def __init__(self, settings: DiscreteFlatnessSettings, t_start_ns: int) -> None:
        self.s = settings
        self.t_start_ns = int(t_start_ns)
        self.dt = settings.control_dt_s
        self.dt_ns = settings.control_dt_ns
        self.reference = SpiralReference(settings.amplitude_m, settings.omega_rps)

    def tick(self, t_ns: int) -> int:
        k, rest = divmod(int(t_ns) - self.t_start_ns, self.dt_ns)
        if rest:
            raise EstimationError(f"t_ns={t_ns}: not on the control grid ({self.dt_ns} ns from {self.t_start_ns})")
        return k

    def t_s(self, k: int) -> float:
        return k * self.dt

    def clip(self, u: np.ndarray) -> np.ndarray:
        m = self.s.command_max
        return np.clip(np.nan_to_num(u, nan=0.0, posinf=m, neginf=-m), -m, m)

    def command(self, t_ns: int, source: OutputSource) -> np.ndarray:
        raise NotImplementedError


class PDController(_Controller):
    """PD on position and velocity with the reference's flat feedforward (it is feasible):
    ``a = y_ref'' + kp (y_ref - p) + kd (y_ref' - v)``, ``theta_cmd = (atan(a / g) + tau theta_ref') / k``
    where ``theta_ref = atan(y_ref'' / g)`` (the pitch lag compensated along the reference only)."""

    name: ControllerName = "pd"

    def command(self, t_ns: int, source: OutputSource) -> np.ndarray:
        p, v, _ = source.state(t_ns).T
        r, dr, ddr, dddr = self.reference.derivatives(np.array(self.t_s(self.tick(t_ns))))
        a = ddr + self.s.pd_kp * (r - p) + self.s.pd_kd * (dr - v)
        dtheta_ref = (dddr / GRAVITY_MPS2) / (1.0 + (ddr / GRAVITY_MPS2) ** 2)
        return self.clip((np.arctan(a / GRAVITY_MPS2) + self.s.time_constant_s * dtheta_ref)
                         / self.s.attitude_gain)


def _triple_integrator(dt: float) -> tuple[np.ndarray, np.ndarray]:
    A = np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
    B = np.array([dt**3 / 6.0, 0.5 * dt * dt, dt])
    return A, B


@functools.lru_cache(maxsize=16)
def _mpc_gains(horizon: int, dt: float, q: float, r: float) -> tuple[np.ndarray, np.ndarray]:
    """``(g_r (N,), g_z (3,))``: the flatness MPC's first jerk is ``g_r . r_{1..N} - g_z . z0``."""
    N = horizon
    A, B = _triple_integrator(dt)
    Gamma = np.zeros((N, 3))   # y_i = Gamma_i z0 + Theta_i j  (i = 1..N)
    Theta = np.zeros((N, N))
    Ak = np.eye(3)
    col = np.zeros((N, 3))     # A^i B
    for i in range(N):
        col[i] = Ak @ B
        Ak = A @ Ak
        Gamma[i] = Ak[0]
    for i in range(N):
        Theta[i, : i + 1] = col[i::-1, 0]
    sq, sr = math.sqrt(q), math.sqrt(r)
    stacked = np.vstack([sq * Theta, sr * np.eye(N)])
    rhs = np.vstack([sq * np.eye(N), np.zeros((N, N))])
    first = np.linalg.lstsq(stacked, rhs, rcond=None)[0][0]
    return first, first @ Gamma


@functools.lru_cache(maxsize=16)
def _discrete_flatness_gains(horizon: int, dt: float, q: float, r: float) -> tuple[np.ndarray, np.ndarray]:
    """``(g_r (N - 2,), g_f (3,))``: the optimal ``y*_{k+3} = g_r . r_{k+3..k+N} + g_f . (y_k, y_{k+1}, y_{k+2})``."""
    N = horizon
    D = np.zeros((N - 2, N + 1))
    for i in range(N - 2):
        D[i, i : i + 4] = (-1.0, 3.0, -3.0, 1.0)
    sq, sr = math.sqrt(q), math.sqrt(r) / dt**3
    free = N + 1 - WINDOW
    stacked = np.vstack([sq * np.eye(free), sr * D[:, WINDOW:]])
    pinv_first = np.linalg.lstsq(stacked, np.eye(stacked.shape[0]), rcond=None)[0][0]
    return sq * pinv_first[:free], -sr * pinv_first[free:] @ D[:, :WINDOW]


class FlatnessMPC(_Controller):
    """Ch. 3's flatness-based MPC in 1-D: flat state ``z = (p, v, a)``, flat input jerk ``j`` (exact
    discretization of the triple integrator), cost ``sum_{i=1..N} q (y_i - r_i)^2 + sum_{i<N} r j_i^2``;
    the first jerk and the desired flat state (the plan's start, the estimate) go through the inverse of
    the pitch dynamics: ``theta = atan(a / g)``, ``theta_cmd = (tau j cos^2(theta) / g + theta) / k``."""

    name: ControllerName = "flatness_mpc"

    def __init__(self, settings: DiscreteFlatnessSettings, t_start_ns: int) -> None:
        super().__init__(settings, t_start_ns)
        self.gain_reference, self.gain_state = _mpc_gains(settings.horizon, self.dt, settings.q_position,
                                                          settings.r_jerk_flatness_mpc)
        self.offsets = np.arange(1, settings.horizon + 1)

    def command(self, t_ns: int, source: OutputSource) -> np.ndarray:
        z = source.state(t_ns)
        r = self.reference.position(self.t_s(self.tick(t_ns)) + self.offsets * self.dt)
        jerk = self.gain_reference @ r - z @ self.gain_state
        theta = np.arctan(z[:, 2] / GRAVITY_MPS2)
        tau, k = self.s.time_constant_s, self.s.attitude_gain
        return self.clip((tau * jerk * np.cos(theta) ** 2 / GRAVITY_MPS2 + theta) / k)


class DiscreteFlatnessController(_Controller):
    """Ch. 8's predictive controller on a window of ``r = 3`` outputs and the inputs it sent.

    Euler model at the control step ``dt``: ``y_{k+2} - 2 y_{k+1} + y_k = g dt^2 tan(theta_k)`` and
    ``theta_{k+1} = theta_k + dt (k u_k - theta_k) / tau``, so
    output-to-input (8.12): ``u_k = (tau (theta_{k+1} - theta_k) / dt + theta_k) / k`` with ``theta_k`` from
    outputs ``k..k+2`` and ``theta_{k+1}`` from ``k+1..k+3``; input-to-output (8.13):
    ``y_{k+3} = 2 y_{k+2} - y_{k+1} + g dt^2 tan(theta_{k+1})``. Each tick the window ends at the newest tick
    the source has measured; (8.13) with the inputs sent carries it to ``y_k, y_{k+1}, y_{k+2}`` (8.15), which
    fix the first ``r`` outputs of (8.16): ``min sum_{i=0..N} q (y_i - r_i)^2 + r' (y_{i+3} - 3 y_{i+2} +
    3 y_{i+1} - y_i)^2`` with ``r' = r_jerk_discrete_flatness / dt^6`` (the cost of :class:`FlatnessMPC` in
    outputs: the third difference is ``dt^3`` times the jerk). Only ``y*_{k+3}`` enters ``u_k``, so the QP
    is one gain row.
    """

    name: ControllerName = "discrete_flatness"

    def __init__(self, settings: DiscreteFlatnessSettings, t_start_ns: int) -> None:
        super().__init__(settings, t_start_ns)
        self.gain_reference, self.gain_fixed = _discrete_flatness_gains(
            settings.horizon, self.dt, settings.q_position, settings.r_jerk_discrete_flatness)
        self.offsets = np.arange(WINDOW, settings.horizon + 1)
        self.inputs: dict[int, np.ndarray] = {}

    def _theta(self, y0: np.ndarray, y1: np.ndarray, y2: np.ndarray) -> np.ndarray:
        return np.arctan((y2 - 2 * y1 + y0) / (GRAVITY_MPS2 * self.dt**2))

    def _sent(self, k: int, like: np.ndarray) -> np.ndarray:
        return self.inputs.get(k, np.zeros_like(like))

    def forward(self, y0: np.ndarray, y1: np.ndarray, y2: np.ndarray, u0: np.ndarray) -> np.ndarray:
        """Input-to-output map (8.13): ``y_{k+3}`` from ``y_k, y_{k+1}, y_{k+2}`` and ``u_k``."""
        th0 = self._theta(y0, y1, y2)
        th1 = th0 + self.dt * (self.s.attitude_gain * u0 - th0) / self.s.time_constant_s
        return 2 * y2 - y1 + GRAVITY_MPS2 * self.dt**2 * np.tan(th1)

    def inverse(self, y0: np.ndarray, y1: np.ndarray, y2: np.ndarray, y3: np.ndarray) -> np.ndarray:
        """Output-to-input map (8.12): ``u_k`` from ``y_k .. y_{k+3}``."""
        th0, th1 = self._theta(y0, y1, y2), self._theta(y1, y2, y3)
        return (self.s.time_constant_s * (th1 - th0) / self.dt + th0) / self.s.attitude_gain

    def command(self, t_ns: int, source: OutputSource) -> np.ndarray:
        k = self.tick(t_ns)
        j = (source.measured_until_ns(t_ns) - self.t_start_ns) // self.dt_ns   # newest measured tick
        ys = list(source.window(self.t_start_ns + j * self.dt_ns, WINDOW, self.dt).T)
        for i in range(j - WINDOW + 1, k):        # (8.15): y_{j+1} .. y_{k+2} with the inputs sent
            ys.append(self.forward(ys[-3], ys[-2], ys[-1], self._sent(i, ys[-1])))
        fixed = np.stack(ys[-WINDOW:], axis=1)    # y_k, y_{k+1}, y_{k+2}
        r = self.reference.position(self.t_s(k) + self.offsets * self.dt)
        y3 = fixed @ self.gain_fixed + self.gain_reference @ r
        u = self.clip(self.inverse(fixed[:, 0], fixed[:, 1], fixed[:, 2], y3))
        self.inputs[k] = u
        return u


CONTROLLER_TYPES: dict[ControllerName, type[_Controller]] = {
    "pd": PDController, "flatness_mpc": FlatnessMPC, "discrete_flatness": DiscreteFlatnessController}


# ----------------------------------------------------------------------------------------------
# Closed loop and sweep


@dataclass(frozen=True)
class ClosedLoopRun:
    """One closed-loop batch: true and reference positions (batch, steps) at the plant rate from the
    reference's start, the commands (batch, ticks), and each run's mean absolute tracking error (m)."""

    t_s: np.ndarray
    position_m: np.ndarray
    reference_m: np.ndarray
    commands: np.ndarray
    mean_error_m: np.ndarray


def simulate(settings: DiscreteFlatnessSettings, controller: ControllerName, source: OutputSource,
             noise_m: np.ndarray) -> ClosedLoopRun:
    """Fly ``controller`` with outputs from ``source``; ``noise_m`` (batch, warmup_ticks + ticks) is added to
    the true position at each tick the source measures. Tick ``-warmup_ticks`` is at time 0 (ns)."""
    noise = np.asarray(noise_m, float)
    W, K, n = settings.warmup_ticks, settings.ticks, settings.substeps
    if noise.ndim != 2 or noise.shape[1] != W + K or not np.all(np.isfinite(noise)):
        raise EstimationError(f"noise_m: expected finite values of shape (batch, {W + K}), got {noise.shape}")
    dt_ns = settings.control_dt_ns
    t_start_ns = W * dt_ns
    ctrl = CONTROLLER_TYPES[controller](settings, t_start_ns)
    plant = PitchPlant(settings, noise.shape[0])
    xs, cmds = [], []
    for k in range(-W, K):
        t_ns = t_start_ns + k * dt_ns
        if t_ns % source.measurement_period_ns == 0:
            source.measure(t_ns, plant.position + noise[:, k + W])
        u = ctrl.command(t_ns, source) if k >= 0 else np.zeros(noise.shape[0])
        if k >= 0:
            cmds.append(u)
        for _ in range(n):
            if k >= 0:
                xs.append(plant.position)
            plant.step(u)
    t = np.arange(K * n) / settings.plant_rate_hz
    x = np.stack(xs, axis=1)
    ref = np.broadcast_to(SpiralReference(settings.amplitude_m, settings.omega_rps).position(t), x.shape)
    return ClosedLoopRun(t, x, np.array(ref), np.stack(cmds, axis=1), np.mean(np.abs(x - ref), axis=1))


def make_source(settings: DiscreteFlatnessSettings, loop: Loop, batch: int, sigma_m: float) -> OutputSource:
    """The outputs a loop's controllers read: raw measurements at the control rate (``perfect``) or one
    smoother per vehicle fed at ``measurement_rate_hz`` (``estimator``)."""
    if loop == "perfect":
        return MeasuredOutputs(settings.control_dt_ns)
    if loop == "estimator":
        smoothing = SmoothingConfig(qc_translation=settings.qc_translation, lag_s=settings.smoother_lag_s,
                                    max_extrapolation_s=max(1.0, 2.0 / settings.measurement_rate_hz))
        return SmootherBatch([SmootherOutputs(smoothing, sigma_m) for _ in range(batch)],
                             settings.measurement_every * settings.control_dt_ns, settings.window_knots_back)
    raise EstimationError(f"loop: expected one of {LOOPS}, got {loop!r}")


#: PD bandwidths (rad/s) searched by :func:`calibrate` (critically damped: kp = w^2, kd = 2 w).
PD_BANDWIDTHS_RPS = tuple(float(w) for w in np.arange(1.0, 8.01, 0.25))
#: Bracket of log10 of the jerk weights searched by :func:`calibrate`, and its bisection steps.
LOG10_R_JERK_BRACKET = (-7.0, 0.0)
CALIBRATION_STEPS = 24


def noiseless_error_m(settings: DiscreteFlatnessSettings, controller: ControllerName) -> float:
    """Mean tracking error (m) of ``controller`` with exact measurements at the control rate."""
    noise = np.zeros((1, settings.warmup_ticks + settings.ticks))
    return float(simulate(settings, controller, MeasuredOutputs(settings.control_dt_ns), noise).mean_error_m[0])


def calibrate(settings: DiscreteFlatnessSettings) -> DiscreteFlatnessSettings:
    """The tuning rule of the settings' defaults (thesis: "all controllers are tuned to have similar performance"
    at low noise), applied without noise: PD critically damped at the bandwidth of ``PD_BANDWIDTHS_RPS`` with
    the smallest noiseless error; then each predictive controller's jerk weight bisected (in log10, the error
    grows with the weight) until its noiseless error equals PD's. No noisy run enters the tuning."""
    pd = {w: settings.replace(pd_kp=w * w, pd_kd=2 * w) for w in PD_BANDWIDTHS_RPS}
    s = min(pd.values(), key=lambda c: noiseless_error_m(c, "pd"))
    target = noiseless_error_m(s, "pd")
    weights: tuple[tuple[ControllerName, str], ...] = (("flatness_mpc", "r_jerk_flatness_mpc"),
                                                       ("discrete_flatness", "r_jerk_discrete_flatness"))
    for name, key in weights:
        lo, hi = LOG10_R_JERK_BRACKET
        for _ in range(CALIBRATION_STEPS):
            mid = 0.5 * (lo + hi)
            if noiseless_error_m(s.replace(**{key: 10.0**mid}), name) < target:
                lo = mid
            else:
                hi = mid
        s = s.replace(**{key: 10.0 ** (0.5 * (lo + hi))})
    return s


@dataclass(frozen=True)
class SweepRow:
    """Tracking error of one controller in one loop at one noise level, over ``trials`` runs (m)."""

    loop: Loop
    controller: ControllerName
    sigma_m: float
    mean_error_m: float
    std_error_m: float
    max_error_m: float
    trials: int


def trial_noise(settings: DiscreteFlatnessSettings, sigma_m: float, trials: int, seed: int) -> np.ndarray:
    """Position noise (trials, warmup_ticks + ticks), the same for every controller and loop at one sigma."""
    rng = np.random.default_rng(seed)       # the same draws scaled at every sigma: the curves compare
    return sigma_m * rng.standard_normal((trials, settings.warmup_ticks + settings.ticks))


def sweep(settings: DiscreteFlatnessSettings, sigmas_m: Sequence[float], trials: int, seed: int = 0,
          loops: Sequence[Loop] = LOOPS, controllers: Sequence[ControllerName] = CONTROLLERS,
          progress: Callable[[SweepRow], None] | None = None) -> list[SweepRow]:
    """Every loop x noise level x controller, ``trials`` runs each (one batch), in that order."""
    if trials < 1:
        raise EstimationError(f"trials: expected at least 1, got {trials}")
    bad = [s for s in sigmas_m if not (s > 0 and math.isfinite(s))]
    if bad or not sigmas_m:
        raise EstimationError(f"sigmas_m: expected positive finite noise levels, got {list(sigmas_m)}")
    rows = []
    for loop in loops:
        for sigma in sigmas_m:
            noise = trial_noise(settings, sigma, trials, seed)
            for name in controllers:
                err = simulate(settings, name, make_source(settings, loop, trials, sigma), noise).mean_error_m
                row = SweepRow(loop, name, float(sigma), float(err.mean()), float(err.std()), float(err.max()),
                               trials)
                rows.append(row)
                if progress is not None:
                    progress(row)
    return rows


def write_results_csv(path: Path, rows: Sequence[SweepRow]) -> None:
    """``RESULT_COLUMNS``, one row per loop, controller and sigma."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(RESULT_COLUMNS)
        for r in rows:
            w.writerow([r.loop, r.controller, f"{r.sigma_m:g}", f"{r.mean_error_m:.6g}", f"{r.std_error_m:.6g}",
                        f"{r.max_error_m:.6g}", r.trials])


__all__ = [
    "CONTROLLERS", "LOOPS", "RESULT_COLUMNS", "WINDOW", "ClosedLoopRun", "DiscreteFlatnessController",
    "DiscreteFlatnessSettings", "FlatnessMPC", "MeasuredOutputs", "OutputSource", "PDController", "PitchPlant",
    "SmootherBatch", "SmootherOutputs", "SpiralReference", "SweepRow", "calibrate", "make_source",
    "noiseless_error_m", "reference_qc", "simulate", "sweep", "trial_noise", "write_results_csv",
]
