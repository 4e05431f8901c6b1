"""The world of the thesis' §8.4.1 simulation (ch. 8, Fig. 8.2): its settings, the reference and the 1-D plant.

A multirotor moves in 1-D (x) with first-order pitch dynamics (thesis eq. 8.11, Euler at ``plant_rate_hz``):
``x+ = x + dt v``, ``v+ = v + dt g tan(theta)``, ``theta+ = theta + dt (k theta_cmd - theta) / tau``, and tracks
``y_ref = A t sin(omega t)`` from rest. :class:`InnerLoopModel` is the same pitch loop as a controller predicts it
from the commands it sent (the acceleration it hands an estimator). The controllers are in
:mod:`vtr.control.discrete_flatness`, the outputs they read in :mod:`vtr.control.output_sources`, the closed loop
and the sweep in :mod:`vtr.control.flatness_sweep`; docs/discrete_flatness.md.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np

from ..config import Choice, Range, Section, setting
from ..conventions import NS_PER_S
from ..errors import ConfigError, EstimationError
from .flat_model import GRAVITY_MPS2

#: Window of the 1-D model: the input at step k is fixed by outputs k..k+3 (8.12), the state by k..k+2.
WINDOW = 3

Loop = Literal["perfect", "estimator"]
ControllerName = Literal["pd", "flatness_mpc", "discrete_flatness"]
LOOPS: tuple[Loop, ...] = ("perfect", "estimator")
CONTROLLERS: tuple[ControllerName, ...] = ("pd", "flatness_mpc", "discrete_flatness")


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
    warmup_s: float = setting(1.0, Range(0.0, 60.0))
    horizon: int = setting(200, Range(4, 5000, integer=True))  # N of (8.16) and of the flatness MPC (4 s)
    q_position: float = setting(1.0, Range(0.0, 1e9, lo_open=True))  # tracking weight (1/m^2)
    # outputs the discrete-time flatness controller fits its window to (M >= r = 3; M = r is eq. 8.15 itself):
    # 25 ticks = 0.5 s = two time constants of the pitch loop (docs/discrete_flatness.md, "The window")
    window_length: int = setting(25, Range(WINDOW, 10_000, integer=True))
    # Tuning (calibrate()): as in the thesis, the three are tuned to track alike without noise (perfect loop):
    # PD critically damped at the bandwidth of its smallest noiseless error; then the flatness MPC's weight on the
    # pitch command (thesis eq. 3.8, 1/rad^2) and discrete flatness' weight on the third difference (8.16, as a
    # jerk: (s^3/m)^2) each set so that its noiseless error equals PD's
    pd_kp: float = setting(20.25, Range(0.0, 1e6))  # PD position gain (1/s^2)
    pd_kd: float = setting(9.0, Range(0.0, 1e6))  # PD velocity gain (1/s)
    r_command_flatness_mpc: float = setting(0.385, Range(0.0, 1e9, lo_open=True))
    r_jerk_discrete_flatness: float = setting(1.51e-3, Range(0.0, 1e9, lo_open=True))
    # white-noise-on-acceleration density of the estimator loop's smoother (m^2/s^3): the reference's mean
    # squared acceleration times the measurement period (reference_qc), so that the prior's velocity change
    # over one camera period has the reference's size
    qc_translation: float = setting(1.83, Range(0.0, 1e6, lo_open=True))
    smoother_lag_s: float = setting(1.0, Range(0.0, 3600.0, lo_open=True))  # fixed-lag window
    # the estimator loop's outputs are the smoother's mean up to this many measurement periods before its newest
    # knot, carried from there to now with the commands sent (state(now) and the discrete-time flatness window
    # alike): at the newest knot the WNOA mean is a natural spline's end (zero acceleration); a knot or two inside
    # it is not
    window_knots_back: int = setting(2, Range(0, 100, integer=True))
    # where PD and the flatness MPC take velocity and acceleration in the estimator loop: first-order differences of
    # the positions state(now) answered at their ticks, as §8.4.1 defines both controllers ("finite_difference"),
    # or state(now)'s own velocity and acceleration ("estimator"; measured, docs/discrete_flatness.md)
    estimator_derivatives: str = setting("finite_difference", Choice("finite_difference", "estimator"))
    # where the estimator loop's smoother uses the commands sent: in its prior as well ("prior": it smooths the
    # positions minus the commanded motion, the WNOA prior about the commanded acceleration, exact in 1-D), or only
    # to carry the outputs past the anchor ("extrapolation", as OnlineRepeat's SE(3) smoother does past its newest
    # knot); measured both ways in docs/discrete_flatness.md
    estimator_inputs: str = setting("prior", Choice("prior", "extrapolation"))

    def __post_init__(self) -> None:
        super().__post_init__()
        for name, fast, slow in (
            ("plant_rate_hz/control_rate_hz", self.plant_rate_hz, self.control_rate_hz),
            ("control_rate_hz/measurement_rate_hz", self.control_rate_hz, self.measurement_rate_hz),
        ):
            ratio = fast / slow
            if ratio < 1 or abs(ratio - round(ratio)) > 1e-9:
                raise ConfigError(f"discrete_flatness: {name} must be a whole number >= 1, got {ratio:g}")
        history_s = self.window_knots_back / self.measurement_rate_hz + (self.window_length - 1) / self.control_rate_hz
        if self.warmup_s < history_s - 1e-9:
            raise ConfigError(
                f"discrete_flatness: warmup_s={self.warmup_s:g} is shorter than the first window's "
                f"history ({history_s:g} s: window_knots_back camera periods and window_length - 1 "
                f"= {self.window_length - 1} ticks)"
            )
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
        return (
            A * t * s,
            A * (s + w * t * c),
            on * A * (2 * w * c - w * w * t * s),
            on * A * w * w * (-3 * s - w * t * c),
        )

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
        self.state = np.stack(
            [x + dt * v, v + dt * GRAVITY_MPS2 * np.tan(th), th + dt * (s.attitude_gain * u - th) / s.time_constant_s],
            axis=1,
        )


class InnerLoopModel:
    """The pitch loop of (8.11) as a controller predicts it from the commands it sent, from rest: the acceleration
    ``g tan(theta)`` it expects of the vehicle (the flat model's map from attitude to acceleration); the mean of it
    over each held command is what it hands to an estimator that extrapolates with the commands sent (eq. 8.15;
    ``OnlineRepeat.command``)."""

    def __init__(self, settings: DiscreteFlatnessSettings, batch: int) -> None:
        self.s = settings
        self.pitch_rad = np.zeros(batch)
        self.held_acceleration_mps2 = np.zeros(batch)

    @property
    def acceleration_mps2(self) -> np.ndarray:
        return GRAVITY_MPS2 * np.tan(self.pitch_rad)

    def hold(self, command: np.ndarray) -> None:
        """The pitch after one control period with ``command`` held (plant steps of ``1 / plant_rate_hz``), and
        ``held_acceleration_mps2``, the mean acceleration over that period: the one constant that, held from the
        command's time to the next (``CommandLog``'s zero-order hold), gives the period's velocity change."""
        s, dt = self.s, 1.0 / self.s.plant_rate_hz
        total = np.zeros_like(self.pitch_rad)
        for _ in range(s.substeps):
            total = total + self.acceleration_mps2
            self.pitch_rad = self.pitch_rad + dt * (s.attitude_gain * command - self.pitch_rad) / s.time_constant_s
        self.held_acceleration_mps2 = total / s.substeps
