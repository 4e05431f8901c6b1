"""The thesis' §8.4.1 simulation (vtr.control.discrete_flatness, tools/discrete_flatness.py): the plant, the
three controllers' maps and gains, tracking without noise, and Fig. 8.2's ordering at one low and one high noise
level with perfect measurements and with the smoother in the loop (3 trials here; the tool runs 10). Where the
ordering does not hold the test is a strict xfail carrying the measured figures (docs/discrete_flatness.md)."""

from __future__ import annotations

import csv
import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest

from vtr.config import SmoothingConfig
from vtr.control.discrete_flatness import (
    CONTROLLERS,
    RESULT_COLUMNS,
    DiscreteFlatnessController,
    DiscreteFlatnessSettings,
    MeasuredOutputs,
    PitchPlant,
    SmootherBatch,
    SmootherOutputs,
    SpiralReference,
    make_source,
    noiseless_error_m,
    reference_qc,
    simulate,
    sweep,
)
from vtr.control.discrete_flatness import _discrete_flatness_gains as df_gains
from vtr.control.discrete_flatness import _mpc_gains as mpc_gains
from vtr.errors import ConfigError, EstimationError

ROOT = Path(__file__).resolve().parents[2]
S = DiscreteFlatnessSettings()
G = 9.81
LOW_SIGMA, HIGH_SIGMA, TRIALS = 0.0005, 0.005, 3


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
    theta = k * u * (1 - alpha ** np.arange(n)[:, None])           # pitch before each step (n, 2)
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
    N, dt, q, r = 10, 0.02, 1.0, 1e-3
    g_r, g_z = mpc_gains(N, dt, q, r)
    rng = np.random.default_rng(3)
    ref, z0 = rng.normal(size=N), rng.normal(size=3)
    A = np.array([[1, dt, dt * dt / 2], [0, 1, dt], [0, 0, 1]])
    B = np.array([dt**3 / 6, dt * dt / 2, dt])
    Theta, Gamma, Ak = np.zeros((N, N)), np.zeros((N, 3)), np.eye(3)
    for i in range(N):
        Ak = A @ Ak
        Gamma[i] = Ak[0]
        for m in range(i + 1):
            Theta[i, m] = (np.linalg.matrix_power(A, i - m) @ B)[0]
    jerk = np.linalg.solve(q * Theta.T @ Theta + r * np.eye(N), q * Theta.T @ (ref - Gamma @ z0))
    assert g_r @ ref - g_z @ z0 == pytest.approx(jerk[0], rel=1e-8)


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


@pytest.mark.xfail(strict=True, reason="measured (10 trials): pd 0.0285, flatness_mpc 0.0534, discrete_flatness "
                   "0.0552 m at sigma 0.0005 (spread 94 %; 22 % at 0.0002, 6 % at 0.0001): both predictive "
                   "controllers read second differences of 50 Hz positions")
def test_perfect_low_noise_the_three_agree_within_20_percent(ordering):
    assert spread(ordering["perfect", LOW_SIGMA]) <= 0.20


def test_perfect_high_noise_flatness_mpc_is_worse_than_pd(ordering):
    e = ordering["perfect", HIGH_SIGMA]
    assert e["flatness_mpc"] > e["pd"]


def test_perfect_high_noise_discrete_flatness_is_better_than_flatness_mpc(ordering):
    e = ordering["perfect", HIGH_SIGMA]
    assert e["discrete_flatness"] < e["flatness_mpc"]


@pytest.mark.xfail(strict=True, reason="measured (10 trials, sigma 0.005): pd 0.0319, discrete_flatness 0.170, "
                   "flatness_mpc 1.63 m; PD with the feasible reference's feedforward commands 56 rad of pitch "
                   "noise per m of position noise, discrete flatness 281 (a 50 Hz second difference)")
def test_perfect_high_noise_discrete_flatness_is_better_than_pd(ordering):
    e = ordering["perfect", HIGH_SIGMA]
    assert e["discrete_flatness"] < e["pd"]


@pytest.mark.xfail(strict=True, reason="measured (10 trials, sigma 0.0005): pd 0.514, flatness_mpc 0.293, "
                   "discrete_flatness 0.0508 m: the smoother's state at its newest knot is a natural spline's "
                   "end (zero acceleration, lagging velocity), which PD and the MPC read and discrete flatness avoids")
def test_estimator_low_noise_the_three_agree_within_20_percent(ordering):
    assert spread(ordering["estimator", LOW_SIGMA]) <= 0.20


@pytest.mark.xfail(strict=True, reason="measured (10 trials, sigma 0.005): flatness_mpc 0.270, pd 0.640 m (0.28 "
                   "vs 0.80 at 0.01, 1.16 vs 2.30 at 0.05): the smoother filters the noise that ruins the MPC's "
                   "finite differences; its lag costs PD's stiffer feedback more")
def test_estimator_high_noise_flatness_mpc_is_worse_than_pd(ordering):
    e = ordering["estimator", HIGH_SIGMA]
    assert e["flatness_mpc"] > e["pd"]


def test_estimator_high_noise_discrete_flatness_is_better_than_both(ordering):
    e = ordering["estimator", HIGH_SIGMA]
    assert e["discrete_flatness"] < min(e["pd"], e["flatness_mpc"])


# -- the smoother adapter -----------------------------------------------------------------------


def test_smoother_outputs_follow_the_motion_and_stop_the_window_inside_the_knots():
    ref = SpiralReference(1.4, 1.0)
    period_ns = 100_000_000
    batch = SmootherBatch([SmootherOutputs(SmoothingConfig(qc_translation=S.qc_translation), 1e-4)], period_ns,
                          knots_back=2)
    for i in range(20):
        batch.measure(i * period_ns, ref.position(np.array([i * 0.1])))
    newest = 19 * period_ns
    assert batch.measured_until_ns(newest + 40_000_000) == newest - 2 * period_ns
    t_end = 1.5
    w = batch.window(int(t_end * 1e9), 3, 0.02)[0]
    np.testing.assert_allclose(w, ref.position(t_end - np.array([0.04, 0.02, 0.0])), atol=1e-3)
    p, v, _ = batch.state(int(t_end * 1e9))[0]
    _, v_true, _, _ = ref.derivatives(np.array(t_end))
    assert abs(p - ref.position(np.array(t_end))) < 1e-3 and abs(v - v_true) < 0.05


def test_bad_inputs_are_one_line_errors():
    with pytest.raises(EstimationError, match="sigma_m"):
        SmootherOutputs(SmoothingConfig(), 0.0)
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
        ("perfect", c, s) for c in CONTROLLERS for s in (0.001, 0.01)}
    assert all(float(r["mean_error_m"]) > 0 for r in rows)
    assert (tmp_path / "error_vs_sigma.png").stat().st_size > 0
    out = capsys.readouterr()
    assert "Fig. 8.2 ordering" in out.out and "[6/6] perfect sigma=0.01" in out.err
