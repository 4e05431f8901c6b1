"""The thesis' §8.4.1 simulation (vtr.control.discrete_flatness, tools/discrete_flatness.py): the plant, the
three controllers' maps and gains, tracking without noise, and Fig. 8.2's ordering at one low and one high noise
level with perfect measurements and with the smoother in the loop (10 trials each, as the thesis and the tool;
the figures in docs/discrete_flatness.md)."""

from __future__ import annotations

import csv
import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vtr.config import SmoothingConfig
from vtr.control.discrete_flatness import DiscreteFlatnessController, fit_window
from vtr.control.discrete_flatness import _discrete_flatness_gains as df_gains
from vtr.control.discrete_flatness import _mpc_gains as mpc_gains
from vtr.control.flatness_sweep import RESULT_COLUMNS, make_source, noiseless_error_m, simulate, sweep
from vtr.control.output_sources import MeasuredOutputs, ReceivedPositions, SmootherBatch, SmootherOutputs
from vtr.control.pitch_model import (
    CONTROLLERS,
    DiscreteFlatnessSettings,
    InnerLoopModel,
    PitchPlant,
    SpiralReference,
    reference_qc,
)
from vtr.errors import ConfigError, EstimationError
from vtr.navigation.state_view import CommandLog

ROOT = Path(__file__).resolve().parents[2]
S = DiscreteFlatnessSettings()
G = 9.81
LOW_SIGMA, HIGH_SIGMA, TRIALS = 0.0005, 0.005, 10  # the thesis' 10 trials


# -- settings -----------------------------------------------------------------------------------


def test_settings_refuse_values_outside_their_domain_naming_the_field():
    with pytest.raises(ConfigError, match="discrete_flatness.horizon"):
        DiscreteFlatnessSettings(horizon=2)
    with pytest.raises(ConfigError, match="discrete_flatness.time_constant_s"):
        DiscreteFlatnessSettings(time_constant_s=-0.1)
    with pytest.raises(ConfigError, match="plant_rate_hz/control_rate_hz"):
        DiscreteFlatnessSettings(plant_rate_hz=130.0)
    with pytest.raises(ConfigError, match="warmup_s"):
        DiscreteFlatnessSettings(warmup_s=0.1, window_knots_back=2)
    with pytest.raises(ConfigError, match="window_length"):
        DiscreteFlatnessSettings(window_length=60)  # 1.18 s of history before a 1 s warm-up
    with pytest.raises(ConfigError, match="discrete_flatness.window_length"):
        DiscreteFlatnessSettings(window_length=2)  # fewer outputs than the window r = 3 of (8.12)
    with pytest.raises(ConfigError, match="discrete_flatness.estimator_derivatives"):
        DiscreteFlatnessSettings(estimator_derivatives="smoothed")
    with pytest.raises(ConfigError, match="discrete_flatness.estimator_inputs"):
        DiscreteFlatnessSettings(estimator_inputs="both")


def test_smoother_density_is_the_references_acceleration_over_one_camera_period():
    assert reference_qc(S) == pytest.approx(S.qc_translation, rel=0.01)


# -- plant --------------------------------------------------------------------------------------


def test_plant_integrates_the_euler_model_of_8_11():
    dt, tau, k = 1 / S.plant_rate_hz, S.time_constant_s, S.attitude_gain
    plant = PitchPlant(S, 2)
    u = np.array([0.1, -0.2])
    n = 80
    for _ in range(n):
        plant.step(u)
    alpha = 1 - dt / tau
    theta = k * u * (1 - alpha ** np.arange(n)[:, None])  # pitch before each step (n, 2)
    v = np.concatenate([[0 * u], np.cumsum(dt * G * np.tan(theta), axis=0)])
    x = np.sum(dt * v[:n], axis=0)
    np.testing.assert_allclose(plant.state[:, 2], k * u * (1 - alpha**n), rtol=1e-12)
    np.testing.assert_allclose(plant.state[:, 1], v[n], rtol=1e-12)
    np.testing.assert_allclose(plant.state[:, 0], x, rtol=1e-12)
    # and it is the continuous first-order response to within the Euler step's error
    t = n * dt
    assert abs(plant.state[0, 2] - k * u[0] * (1 - math.exp(-t / tau))) < 0.02 * k * abs(u[0])


def test_plant_refuses_a_command_of_the_wrong_shape():
    with pytest.raises(EstimationError, match="command"):
        PitchPlant(S, 2).step(np.zeros(3))


# -- maps and gains -----------------------------------------------------------------------------


def test_output_to_input_map_inverts_the_input_to_output_map():
    ctrl = DiscreteFlatnessController(S, 0)
    rng = np.random.default_rng(1)
    # outputs of the Euler model at the control step under random inputs
    dt, tau, k = S.control_dt_s, S.time_constant_s, S.attitude_gain
    u = rng.uniform(-0.3, 0.3, 40)
    x = v = th = 0.0
    ys = []
    for uk in u:
        ys.append(x)
        x, v, th = x + dt * v, v + dt * G * math.tan(th), th + dt * (k * uk - th) / tau
    ys.append(x)
    for _ in range(3):
        x, v, th = x + dt * v, v + dt * G * math.tan(th), th
        ys.append(x)
    y = np.array(ys)
    recovered = ctrl.inverse(y[:40], y[1:41], y[2:42], y[3:43])
    np.testing.assert_allclose(recovered, u, atol=1e-9)
    np.testing.assert_allclose(ctrl.forward(y[:40], y[1:41], y[2:42], u), y[3:43], atol=1e-12)


def test_discrete_flatness_gain_row_solves_the_equality_constrained_qp_8_16():
    N, dt, q, r = 12, 0.02, 2.0, 1e-3
    g_r, g_f = df_gains(N, dt, q, r)
    rng = np.random.default_rng(2)
    ref, fixed = rng.normal(size=N + 1), rng.normal(size=3)
    D = np.zeros((N - 2, N + 1))
    for i in range(N - 2):
        D[i, i : i + 4] = (-1, 3, -3, 1)
    H = 2 * (q * np.eye(N + 1) + r / dt**6 * D.T @ D)
    E = np.eye(N + 1)[:3]
    kkt = np.block([[H, E.T], [E, np.zeros((3, 3))]])
    y = np.linalg.solve(kkt, np.concatenate([2 * q * ref, fixed]))[: N + 1]
    assert g_r @ ref[3:] + g_f @ fixed == pytest.approx(y[3], rel=1e-8, abs=1e-10)


def test_flatness_mpc_gain_row_is_the_unconstrained_optimum():
    """Cost (3.8): tracking plus the linearized pitch command u_i = (a_i + tau j_i) / (g k) over i = 0..N-1."""
    N, dt, q, r, tau, k = 10, 0.02, 1.0, 0.3, 0.25, 1.4
    g_r, g_z = mpc_gains(N, dt, q, r, tau, k)
    rng = np.random.default_rng(3)
    ref, z0 = rng.normal(size=N), rng.normal(size=3)
    A = np.array([[1, dt, dt * dt / 2], [0, 1, dt], [0, 0, 1]])
    B = np.array([dt**3 / 6, dt * dt / 2, dt])

    def cost(j):
        z, total = z0.copy(), 0.0
        for i in range(N):
            total += r * ((z[2] + tau * j[i]) / (G * k)) ** 2
            z = A @ z + B * j[i]
            total += q * (z[0] - ref[i]) ** 2
        return total

    # the cost is quadratic in j: its minimizer from the gradient and Hessian by exact finite differences
    e = np.eye(N)
    c0 = cost(np.zeros(N))
    grad = np.array([(cost(e[i]) - cost(-e[i])) / 2 for i in range(N)])
    H = np.array([[(cost(e[i] + e[m]) - cost(e[i]) - cost(e[m]) + c0) for m in range(N)] for i in range(N)])
    jerk = np.linalg.solve(H, -grad)
    assert g_r @ ref - g_z @ z0 == pytest.approx(jerk[0], rel=1e-6)


# -- the window fit -----------------------------------------------------------------------------


def _model_outputs(u, dt=S.control_dt_s, tau=S.time_constant_s, k=S.attitude_gain, y0=0.3, v0=-0.4, th0=0.1):
    """Outputs of the Euler model at the control step under inputs u (len L): ticks 0..L+2."""
    x, v, th, ys = y0, v0, th0, []
    for uk in list(u) + [0.0] * 3:
        ys.append(x)
        x, v, th = x + dt * v, v + dt * G * math.tan(th), th + dt * (k * uk - th) / tau
    return np.array(ys[: len(u) + 3])


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), M=st.integers(3, 40), extra=st.integers(0, 5))
def test_the_window_fit_recovers_the_models_outputs(seed, M, extra):
    """Noiseless outputs of the model under the inputs sent: the fit of any window length reproduces them and
    carries them past the window with the inputs (8.15), as the one-input-at-a-time map does with M = 3."""
    rng = np.random.default_rng(seed)
    L = M - 1 + extra
    u = rng.uniform(-0.3, 0.3, L)
    y = _model_outputs(u, th0=rng.uniform(-0.5, 0.5))
    got = fit_window(y[None, :M], u[None], S.control_dt_s, S.time_constant_s, S.attitude_gain)[0]
    np.testing.assert_allclose(got, y, atol=1e-9)


def test_a_window_of_three_is_8_15_and_a_longer_one_averages_the_noise():
    ctrl = DiscreteFlatnessController(S.replace(window_length=3), 0)
    rng = np.random.default_rng(4)
    u = rng.uniform(-0.2, 0.2, 30)
    y = _model_outputs(u)
    sigma, trials = 0.002, 400
    noisy = y[None] + sigma * rng.standard_normal((trials, len(y)))
    # M = 3: the input-to-output map applied one input at a time from three measured outputs (8.15) ...
    ys = [noisy[:, 25], noisy[:, 26], noisy[:, 27]]
    for i in range(25, 30):
        ys.append(ctrl.forward(ys[-3], ys[-2], ys[-1], np.full(trials, u[i])))
    three = np.stack(ys[-3:], axis=1)
    # ... is what the fit of a window of three gives (checked where Gauss-Newton's tan is mild: small noise)
    small = y[None] + 1e-5 * rng.standard_normal((trials, len(y)))
    ys_small = [small[:, 25], small[:, 26], small[:, 27]]
    for i in range(25, 30):
        ys_small.append(ctrl.forward(ys_small[-3], ys_small[-2], ys_small[-1], np.full(trials, u[i])))
    fit3 = fit_window(
        small[:, 25:28], np.tile(u[25:30], (trials, 1)), S.control_dt_s, S.time_constant_s, S.attitude_gain
    )
    np.testing.assert_allclose(fit3[:, -3:], np.stack(ys_small[-3:], axis=1), atol=1e-9)
    # M = 25 ending at the same tick: the fixed outputs y_k.. carry far less noise than from three outputs
    long = fit_window(noisy[:, 3:28], np.tile(u[3:30], (trials, 1)), S.control_dt_s, S.time_constant_s, S.attitude_gain)
    err3, err25 = three - y[-3:], long[:, -3:] - y[-3:]
    assert np.sqrt(np.mean(err25**2)) < 0.1 * np.sqrt(np.mean(err3**2))
    assert np.all(np.abs(np.mean(err25, axis=0)) < 4 * np.std(err25, axis=0) / math.sqrt(trials))  # unbiased


def test_the_inner_loop_model_is_the_plants_pitch():
    plant, inner = PitchPlant(S, 1), InnerLoopModel(S, 1)
    for uk in np.random.default_rng(5).uniform(-0.4, 0.4, 20):
        for _ in range(S.substeps):
            plant.step(np.array([uk]))
        inner.hold(np.array([uk]))
    np.testing.assert_allclose(inner.pitch_rad, plant.state[:, 2], rtol=1e-12)
    np.testing.assert_allclose(inner.acceleration_mps2, G * np.tan(plant.state[:, 2]), rtol=1e-12)


def test_the_acceleration_handed_over_a_held_command_gives_the_periods_velocity_change():
    """What the loop hands the estimator (CommandLog holds it until the next command): the mean over the period,
    so that the velocity the commands add is the plant's at every tick, not lagging by the pitch's motion."""
    plant, inner = PitchPlant(S, 1), InnerLoopModel(S, 1)
    for uk in np.random.default_rng(6).uniform(-0.4, 0.4, 20):
        v0, a0 = plant.state[0, 1], inner.acceleration_mps2[0]
        for _ in range(S.substeps):
            plant.step(np.array([uk]))
        inner.hold(np.array([uk]))
        dv = plant.state[0, 1] - v0
        assert inner.held_acceleration_mps2[0] * S.control_dt_s == pytest.approx(dv, rel=1e-12, abs=1e-15)
        assert abs(a0 * S.control_dt_s - dv) > 1e-6  # the pitch moves within the period: its start is not it


# -- closed loop --------------------------------------------------------------------------------


@pytest.mark.parametrize("controller", CONTROLLERS)
def test_each_controller_tracks_the_noiseless_reference(controller):
    """y_ref reaches 6.7 m and 7.7 m/s^2 over the run; the vehicle starts at rest (y_ref'' = 2.8 m/s^2 at 0)."""
    run = simulate(S, controller, MeasuredOutputs(S.control_dt_ns), np.zeros((1, S.warmup_ticks + S.ticks)))
    err = np.abs(run.position_m - run.reference_m)[0]
    assert np.ptp(run.reference_m) > 6.0
    assert err.mean() < 0.035
    assert err[err.size // 2 :].max() < 0.06


def test_the_defaults_are_tuned_alike_without_noise():
    """The thesis' tuning rule (calibrate): the three track alike without noise; no noisy run enters it."""
    e = [noiseless_error_m(S, c) for c in CONTROLLERS]
    assert max(e) / min(e) - 1 < 0.05, e


@pytest.fixture(scope="module")
def ordering() -> dict[tuple[str, float], dict[str, float]]:
    out: dict[tuple[str, float], dict[str, float]] = {}
    for r in sweep(S, [LOW_SIGMA, HIGH_SIGMA], TRIALS, seed=0):
        out.setdefault((r.loop, r.sigma_m), {})[r.controller] = r.mean_error_m
    return out


def spread(e: dict[str, float]) -> float:
    return max(e.values()) / min(e.values()) - 1


def test_perfect_low_noise_the_three_agree_within_20_percent(ordering):
    assert spread(ordering["perfect", LOW_SIGMA]) <= 0.20


def test_perfect_high_noise_flatness_mpc_is_worse_than_pd(ordering):
    e = ordering["perfect", HIGH_SIGMA]
    assert e["flatness_mpc"] > e["pd"]


def test_perfect_high_noise_discrete_flatness_is_better_than_flatness_mpc(ordering):
    e = ordering["perfect", HIGH_SIGMA]
    assert e["discrete_flatness"] < e["flatness_mpc"]


def test_perfect_high_noise_discrete_flatness_is_better_than_pd(ordering):
    e = ordering["perfect", HIGH_SIGMA]
    assert e["discrete_flatness"] < e["pd"]


def test_estimator_low_noise_the_three_agree_within_20_percent(ordering):
    assert spread(ordering["estimator", LOW_SIGMA]) <= 0.20


def test_estimator_high_noise_flatness_mpc_is_worse_than_pd(ordering):
    e = ordering["estimator", HIGH_SIGMA]
    assert e["flatness_mpc"] > e["pd"]


def test_estimator_high_noise_discrete_flatness_is_better_than_both(ordering):
    e = ordering["estimator", HIGH_SIGMA]
    assert e["discrete_flatness"] < min(e["pd"], e["flatness_mpc"])


# -- the smoother adapter -----------------------------------------------------------------------


def test_smoother_outputs_follow_the_motion_and_carry_the_window_to_now_with_the_commands():
    ref = SpiralReference(1.4, 1.0)
    period_ns = 100_000_000
    anchor_ns = 2 * period_ns
    batch = SmootherBatch(
        [SmootherOutputs(SmoothingConfig(qc_translation=S.qc_translation), 1e-4, command_anchor_ns=anchor_ns)],
        period_ns,
    )
    with pytest.raises(EstimationError, match="no measurement"):
        batch.window_end_ns(0)
    for i in range(20):
        batch.measure(i * period_ns, ref.position(np.array([i * 0.1])))
    newest = 19 * period_ns
    assert batch.window_end_ns(newest + 40_000_000) == newest + 40_000_000
    # without commands: the mean inside the knots (an extrapolation at constant velocity after them)
    t_end = 1.5
    w = batch.window(int(t_end * 1e9), 3, 0.02)[0]
    np.testing.assert_allclose(w, ref.position(t_end - np.array([0.04, 0.02, 0.0])), atol=1e-3)
    p, v, _ = batch.state(int(t_end * 1e9))[0]
    _, v_true, _, _ = ref.derivatives(np.array(t_end))
    assert abs(p - ref.position(np.array(t_end))) < 1e-3 and abs(v - v_true) < 0.05
    # with commands: after the anchor (two knots back) the window's positions are the state's, carried with them
    batch.command(newest - anchor_ns, np.array([2.0]))
    now = newest + 60_000_000
    times = now - 20_000_000 * np.arange(19, -1, -1)
    w = batch.window(now, 20, 0.02)[0]
    np.testing.assert_allclose(w, [batch.state(int(t))[0, 0] for t in times], rtol=0, atol=1e-12)
    src = batch.sources[0]
    before = times <= newest - anchor_ns
    np.testing.assert_allclose(
        w[before], [src.view.state_at(int(t), with_covariance=False).position[0] for t in times[before]], atol=1e-12
    )
    anchor = src.view.state_at(newest - anchor_ns, with_covariance=False)
    ahead = (now - (newest - anchor_ns)) / 1e9
    assert w[-1] == pytest.approx(
        anchor.position[0] + anchor.linear_velocity_world[0] * ahead + 0.5 * 2.0 * ahead**2, abs=1e-12
    )


def test_the_commands_sent_move_the_extrapolation_past_the_newest_knot():
    """Constant acceleration from rest: past the newest knot the constant-velocity extrapolation falls behind by
    a t^2 / 2; with the acceleration commanded (eq. 8.15, OnlineRepeat.command's zero-order hold) it does not."""
    acc, period_ns = 2.0, 100_000_000
    plain, told = (SmootherOutputs(SmoothingConfig(qc_translation=S.qc_translation), 1e-4) for _ in range(2))
    for i in range(15):
        t = i * 0.1
        for src in (plain, told):
            src.add(i * period_ns, 0.5 * acc * t * t)
        told.command(i * period_ns, acc)
    t_ns = 14 * period_ns + 80_000_000
    t = t_ns / 1e9
    p_plain, v_plain, _ = plain.state(t_ns)
    p_told, v_told, a_told = told.state(t_ns)
    ahead = 0.08  # s past the newest knot
    assert a_told == acc
    assert p_told - p_plain == pytest.approx(0.5 * acc * ahead**2, rel=1e-9)
    assert v_told - v_plain == pytest.approx(acc * ahead, rel=1e-9)
    assert abs(p_told - 0.5 * acc * t * t) < 0.5 * abs(p_plain - 0.5 * acc * t * t)
    with pytest.raises(EstimationError, match="command"):
        told.command(14 * period_ns, acc)


def test_the_extrapolation_with_the_commands_sent_starts_at_the_anchor():
    """Constant acceleration from rest, commanded exactly: with the anchor two knots inside, any time after it is
    the mean there carried with the commands (p_a + v_a dt + a dt^2 / 2), closer to the motion than the same
    extrapolation from the newest knot (a natural spline's end, its velocity lagging); before the anchor the
    smoother's mean is unchanged."""
    acc, period_ns = 2.0, 100_000_000
    cfg = SmoothingConfig(qc_translation=S.qc_translation)
    newest, anchored = SmootherOutputs(cfg, 1e-4), SmootherOutputs(cfg, 1e-4, command_anchor_ns=2 * period_ns)
    for i in range(15):
        for src in (newest, anchored):
            src.add(i * period_ns, 0.5 * acc * (i * 0.1) ** 2)
            src.command(i * period_ns, acc)
    t_anchor = 12 * period_ns
    mean = anchored.view.state_at(t_anchor, with_covariance=False)
    p_a, v_a = mean.position[0], mean.linear_velocity_world[0]
    for t_ns in (t_anchor + 20_000_000, 14 * period_ns, 14 * period_ns + 80_000_000):
        dt = (t_ns - t_anchor) / 1e9
        p, v, a = anchored.state(t_ns)
        assert p == pytest.approx(p_a + v_a * dt + 0.5 * acc * dt * dt, rel=1e-12)
        assert v == pytest.approx(v_a + acc * dt, rel=1e-12) and a == acc
    t_ns, t = 14 * period_ns + 80_000_000, 1.48
    true_p, true_v = 0.5 * acc * t * t, acc * t
    p_new, v_new, _ = newest.state(t_ns)
    p_anc, v_anc, _ = anchored.state(t_ns)
    assert abs(v_anc - true_v) < 0.5 * abs(v_new - true_v) and abs(p_anc - true_p) < abs(p_new - true_p)
    np.testing.assert_array_equal(anchored.state(t_anchor), newest.state(t_anchor))


def test_received_positions_differences_what_was_answered_at_each_tick():
    """PD's and the MPC's state in the estimator loop (§8.4.1's finite differences): over raw measurements it is
    MeasuredOutputs' state itself; over the smoother, each past tick's position is the one answered then, not the
    smoother's revised one."""
    dt_ns, dt = S.control_dt_ns, S.control_dt_s
    raw, wrapped = MeasuredOutputs(dt_ns), ReceivedPositions(MeasuredOutputs(dt_ns), dt_ns)
    ys = np.random.default_rng(7).normal(size=(6, 2))
    for i, y in enumerate(ys):
        raw.measure(i * dt_ns, y)
        wrapped.measure(i * dt_ns, y)
        if i >= 4:  # the two ticks before the first query are read then (MeasuredOutputs' state needs two more)
            np.testing.assert_allclose(wrapped.state(i * dt_ns), raw.state(i * dt_ns), rtol=1e-12)
    period_ns = 5 * dt_ns
    src = ReceivedPositions(SmootherBatch([SmootherOutputs(SmoothingConfig(), 1e-3)], period_ns), dt_ns)
    ref = SpiralReference(1.4, 1.0)
    for i in range(10):
        src.measure(i * period_ns, ref.position(np.array([i * period_ns / 1e9])))
        src.command(i * period_ns, np.zeros(1))
    t1 = 9 * period_ns + 4 * dt_ns
    p1 = src.state(t1)[0, 0]
    src.measure(10 * period_ns, ref.position(np.array([1.0])) + 0.01)  # a knot that moves the past
    p2, v2, _ = src.state(t1 + dt_ns)[0]
    assert v2 == pytest.approx((p2 - p1) / dt, rel=1e-12)
    assert src.source.state(t1)[0, 0] != p1  # the smoother's answer for t1 changed; the difference kept the old


def test_a_smoother_with_the_commands_in_its_prior_follows_the_commanded_motion_to_its_newest_knot():
    """Exact positions of a motion driven by known commands (a held acceleration that changes sign): with the commands
    in its prior the smoother's state at the newest knot is the motion's (the WNOA mean's end condition, zero
    acceleration, now holds for what is left: nothing); without, it lags."""
    period_ns, dt_ns = 100_000_000, 20_000_000
    accel = [1.5 if k < 60 else -2.0 for k in range(100)]  # one command per 20 ms
    truth = CommandLog(np.arange(100, dtype=np.int64) * dt_ns, np.column_stack([accel, np.zeros(100), np.zeros(100)]))
    err = {}
    for prior in (True, False):
        src = SmootherOutputs(SmoothingConfig(qc_translation=S.qc_translation), 1e-4, inputs_in_prior=prior)
        for k in range(100):
            t = k * dt_ns
            if t % period_ns == 0:
                src.add(t, float(truth.motion(t)[0][0]))
            src.command(t, accel[k])
        newest = 95 * dt_ns
        p, v, a = src.state(newest)
        tp, tv, ta = (x[0] for x in truth.motion(newest))
        err[prior] = (abs(p - tp), abs(v - tv), abs(a - ta))
        w = src.window(newest + 3 * dt_ns, 10, 0.02)  # past the newest knot: the state's positions
        times = newest + 3 * dt_ns - dt_ns * np.arange(9, -1, -1)
        np.testing.assert_allclose(w, [src.state(int(t))[0] for t in times], atol=1e-12)
    assert err[True][0] < 1e-3 and err[True][1] < 0.01 and err[True][2] < 0.05
    assert err[False][1] > 0.03 and err[False][2] > 0.1  # measured: 0.058 m/s and 0.15 m/s^2 behind


def test_the_estimator_loop_reads_the_positions_or_the_estimators_derivatives():
    assert isinstance(make_source(S, "estimator", 2, 0.001), ReceivedPositions)
    assert isinstance(make_source(S.replace(estimator_derivatives="estimator"), "estimator", 2, 0.001), SmootherBatch)
    src = make_source(S, "estimator", 1, 0.001)
    assert isinstance(src, ReceivedPositions) and isinstance(src.source, SmootherBatch)
    period_ns = S.measurement_every * S.control_dt_ns
    assert src.source.sources[0].command_anchor_ns == S.window_knots_back * period_ns
    assert src.source.sources[0].inputs_in_prior
    plain = make_source(S.replace(estimator_inputs="extrapolation"), "estimator", 1, 0.001)
    assert isinstance(plain, ReceivedPositions) and not plain.source.sources[0].inputs_in_prior


def test_bad_inputs_are_one_line_errors():
    with pytest.raises(EstimationError, match="sigma_m"):
        SmootherOutputs(SmoothingConfig(), 0.0)
    with pytest.raises(EstimationError, match="command_anchor_ns"):
        SmootherOutputs(SmoothingConfig(), 0.001, command_anchor_ns=-1)
    with pytest.raises(EstimationError, match="noise_m"):
        simulate(S, "pd", make_source(S, "perfect", 1, 0.001), np.zeros((1, 5)))
    with pytest.raises(EstimationError, match="loop"):
        make_source(S, "online", 1, 0.001)  # type: ignore[arg-type]
    with pytest.raises(EstimationError, match="sigmas_m"):
        sweep(S, [0.0], 1)


# -- the tool -----------------------------------------------------------------------------------


def test_tool_writes_the_csv_columns_and_the_figure(tmp_path, capsys):
    spec = importlib.util.spec_from_file_location("discrete_flatness_tool", ROOT / "tools" / "discrete_flatness.py")
    assert spec is not None and spec.loader is not None
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    assert tool.main(["--out", str(tmp_path), "--trials", "1", "--sigmas", "0.001,0.01", "--loops", "perfect"]) == 0
    with open(tmp_path / "results.csv") as f:
        rows = list(csv.DictReader(f))
    assert tuple(rows[0]) == RESULT_COLUMNS
    assert {(r["loop"], r["controller"], float(r["sigma_m"])) for r in rows} == {
        ("perfect", c, s) for c in CONTROLLERS for s in (0.001, 0.01)
    }
    assert all(float(r["mean_error_m"]) > 0 for r in rows)
    assert (tmp_path / "error_vs_sigma.png").stat().st_size > 0
    out = capsys.readouterr()
    assert "Fig. 8.2 ordering" in out.out and "[6/6] perfect sigma=0.01" in out.err
