"""The closed loop of the thesis' §8.4.1 simulation and its noise sweep (Fig. 8.2): fly a controller on a batch of
vehicles, tune the three alike without noise, sweep the position noise, write the table (docs/discrete_flatness.md).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import SmoothingConfig
from ..errors import EstimationError
from .discrete_flatness import CONTROLLER_TYPES
from .output_sources import MeasuredOutputs, OutputSource, ReceivedPositions, SmootherBatch, SmootherOutputs
from .pitch_model import (
    CONTROLLERS,
    LOOPS,
    ControllerName,
    DiscreteFlatnessSettings,
    InnerLoopModel,
    Loop,
    PitchPlant,
    SpiralReference,
)

RESULT_COLUMNS = ("loop", "controller", "sigma_m", "mean_error_m", "std_error_m", "max_error_m", "trials")


@dataclass(frozen=True)
class ClosedLoopRun:
    """One closed-loop batch: true and reference positions (batch, steps) at the plant rate from the
    reference's start, the commands (batch, ticks), and each run's mean absolute tracking error (m)."""

    t_s: np.ndarray
    position_m: np.ndarray
    reference_m: np.ndarray
    commands: np.ndarray
    mean_error_m: np.ndarray


def simulate(
    settings: DiscreteFlatnessSettings, controller: ControllerName, source: OutputSource, noise_m: np.ndarray
) -> ClosedLoopRun:
    """Fly ``controller`` with outputs from ``source``; ``noise_m`` (batch, warmup_ticks + ticks) is added to
    the true position at each tick the source measures. Tick ``-warmup_ticks`` is at time 0 (ns). Each tick the
    source is told the mean acceleration over the coming control period that the commands sent so far produce by
    the controller's model of the pitch loop (:class:`~vtr.control.pitch_model.InnerLoopModel`): the commands in,
    for an estimator's extrapolation."""
    noise = np.asarray(noise_m, float)
    W, K, n = settings.warmup_ticks, settings.ticks, settings.substeps
    if noise.ndim != 2 or noise.shape[1] != W + K or not np.all(np.isfinite(noise)):
        raise EstimationError(f"noise_m: expected finite values of shape (batch, {W + K}), got {noise.shape}")
    dt_ns = settings.control_dt_ns
    t_start_ns = W * dt_ns
    ctrl = CONTROLLER_TYPES[controller](settings, t_start_ns)
    plant = PitchPlant(settings, noise.shape[0])
    inner = InnerLoopModel(settings, noise.shape[0])
    xs, cmds = [], []
    for k in range(-W, K):
        t_ns = t_start_ns + k * dt_ns
        if t_ns % source.measurement_period_ns == 0:
            source.measure(t_ns, plant.position + noise[:, k + W])
        u = ctrl.command(t_ns, source) if k >= 0 else np.zeros(noise.shape[0])
        inner.hold(u)
        source.command(t_ns, inner.held_acceleration_mps2)
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
    smoother per vehicle fed at ``measurement_rate_hz`` (``estimator``): its state and windows are the smoother's mean
    up to ``window_knots_back`` camera periods before the newest knot, carried from there to the time asked with the
    commands sent (with ``estimator_inputs`` = ``prior`` the smoother's prior holds the commands too), and with
    ``estimator_derivatives`` = ``finite_difference`` the state is the first-order differences of the positions
    answered at the control ticks (:class:`~vtr.control.output_sources.ReceivedPositions`)."""
    if loop == "perfect":
        return MeasuredOutputs(settings.control_dt_ns)
    if loop == "estimator":
        smoothing = SmoothingConfig(
            qc_translation=settings.qc_translation,
            lag_s=settings.smoother_lag_s,
            max_extrapolation_s=max(1.0, 2.0 / settings.measurement_rate_hz),
        )
        period_ns = settings.measurement_every * settings.control_dt_ns
        anchor_ns = settings.window_knots_back * period_ns
        prior = settings.estimator_inputs == "prior"
        vehicles = [SmootherOutputs(smoothing, sigma_m, anchor_ns, inputs_in_prior=prior) for _ in range(batch)]
        smoothers = SmootherBatch(vehicles, period_ns)
        if settings.estimator_derivatives == "finite_difference":
            return ReceivedPositions(smoothers, settings.control_dt_ns)
        return smoothers
    raise EstimationError(f"loop: expected one of {LOOPS}, got {loop!r}")


#: PD bandwidths (rad/s) searched by :func:`calibrate` (critically damped: kp = w^2, kd = 2 w).
PD_BANDWIDTHS_RPS = tuple(float(w) for w in np.arange(1.0, 8.01, 0.25))
#: Brackets of log10 of the predictive controllers' weights searched by :func:`calibrate` (the noiseless error
#: grows with each), and the bisection steps.
LOG10_WEIGHT_BRACKETS = {"r_command_flatness_mpc": (-4.0, 3.0), "r_jerk_discrete_flatness": (-7.0, 0.0)}
CALIBRATION_STEPS = 24


def noiseless_error_m(settings: DiscreteFlatnessSettings, controller: ControllerName) -> float:
    """Mean tracking error (m) of ``controller`` with exact measurements at the control rate."""
    noise = np.zeros((1, settings.warmup_ticks + settings.ticks))
    return float(simulate(settings, controller, MeasuredOutputs(settings.control_dt_ns), noise).mean_error_m[0])


def calibrate(settings: DiscreteFlatnessSettings) -> DiscreteFlatnessSettings:
    """The tuning rule of the settings' defaults (thesis: "all controllers are tuned to have similar performance"
    at low noise), applied without noise: PD critically damped at the bandwidth of ``PD_BANDWIDTHS_RPS`` with
    the smallest noiseless error; then each predictive controller's weight bisected (in log10, the error
    grows with the weight) until its noiseless error equals PD's. No noisy run enters the tuning."""
    pd = {w: settings.replace(pd_kp=w * w, pd_kd=2 * w) for w in PD_BANDWIDTHS_RPS}
    s = min(pd.values(), key=lambda c: noiseless_error_m(c, "pd"))
    target = noiseless_error_m(s, "pd")
    weights: tuple[tuple[ControllerName, str], ...] = (
        ("flatness_mpc", "r_command_flatness_mpc"),
        ("discrete_flatness", "r_jerk_discrete_flatness"),
    )
    for name, key in weights:
        lo, hi = LOG10_WEIGHT_BRACKETS[key]
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
    rng = np.random.default_rng(seed)  # the same draws scaled at every sigma: the curves compare
    return sigma_m * rng.standard_normal((trials, settings.warmup_ticks + settings.ticks))


def sweep(
    settings: DiscreteFlatnessSettings,
    sigmas_m: Sequence[float],
    trials: int,
    seed: int = 0,
    loops: Sequence[Loop] = LOOPS,
    controllers: Sequence[ControllerName] = CONTROLLERS,
    progress: Callable[[SweepRow], None] | None = None,
) -> list[SweepRow]:
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
                row = SweepRow(loop, name, float(sigma), float(err.mean()), float(err.std()), float(err.max()), trials)
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
            w.writerow(
                [
                    r.loop,
                    r.controller,
                    f"{r.sigma_m:g}",
                    f"{r.mean_error_m:.6g}",
                    f"{r.std_error_m:.6g}",
                    f"{r.max_error_m:.6g}",
                    r.trials,
                ]
            )
