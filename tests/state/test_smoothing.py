"""Tests of the WNOA trajectory smoother: formulas against GTSAM, Jacobians against numerical
differences, accuracy on a known helix, covariances against batch marginals, and bad input."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import V, X
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from vtr.config import SmoothingConfig
from vtr.conventions import NS_PER_S as NS
from vtr.errors import EstimationError
from vtr.geometry import exp_se3, log_se3
from vtr.state.smoothing import (
    Segment,
    TrajectorySmoother,
    TrajectoryState,
    d_jr_inv_times,
    d_jr_times,
    expmap,
    extrapolation_jacobian,
    interpolation_jacobian,
    jr,
    jr_inv,
)
from vtr.state.wnoa import (
    hermite_matrix,
    local_variable,
    wnoa_conditional_Q,
    wnoa_interpolation_matrices,
    wnoa_Phi,
    wnoa_Q,
)

FD_STEP = 1e-6
JACOBIAN_ATOL = 1e-6

# Helix: radius, yaw rate, climb rate, roll wobble amplitude and frequency.
HELIX_RADIUS_M = 5.0
HELIX_RATE = 0.5  # rad/s  (speed 2.5 m/s, centripetal 1.25 m/s²)
HELIX_CLIMB = 0.5  # m/s
HELIX_WOBBLE = 0.1  # rad
HELIX_WOBBLE_RATE = 2.0  # rad/s
HELIX_KEYFRAME_NS = 100_000_000  # 10 Hz
HELIX_QUERY_NS = 20_000_000  # 50 Hz
HELIX_KEYFRAMES = 150
HELIX_WARMUP = 10  # keyframes before extrapolation is scored
NOISE_ROT, NOISE_TRANS = 0.002, 0.01  # rad, m (per axis)


def helix(t: float) -> np.ndarray:
    """T_world_sensor of the helix at t seconds (x along the tangent, wobbling in roll)."""
    T = np.eye(4)
    T[:3, 3] = [HELIX_RADIUS_M * np.cos(HELIX_RATE * t), HELIX_RADIUS_M * np.sin(HELIX_RATE * t), HELIX_CLIMB * t]
    T[:3, :3] = Rotation.from_euler(
        "zx", [HELIX_RATE * t + np.pi / 2, HELIX_WOBBLE * np.sin(HELIX_WOBBLE_RATE * t)]
    ).as_matrix()
    return T


def helix_twist(t: float, h: float = 1e-5) -> np.ndarray:
    return log_se3(np.linalg.inv(helix(t - h)) @ helix(t + h)) / (2 * h)


def rms(a) -> float:
    return float(np.sqrt(np.mean(np.square(a))))


@pytest.fixture(scope="module")
def helix_run():
    """Smoother fed with the noisy helix at 10 Hz; extrapolation errors scored as it runs."""
    rng = np.random.default_rng(1)
    cov = np.diag([NOISE_ROT**2] * 3 + [NOISE_TRANS**2] * 3)
    sm = TrajectorySmoother(SmoothingConfig())
    ext = {0.1: [], 0.5: []}
    raw = []
    for k in range(HELIX_KEYFRAMES):
        t_ns = k * HELIX_KEYFRAME_NS
        noise = np.r_[rng.normal(0, NOISE_ROT, 3), rng.normal(0, NOISE_TRANS, 3)]
        M = helix(t_ns / NS) @ exp_se3(noise)
        raw.append(np.linalg.norm(M[:3, 3] - helix(t_ns / NS)[:3, 3]))
        sm.add_pose(t_ns, M, cov)
        if k >= HELIX_WARMUP:
            for ahead in ext:
                s = sm.state_at(t_ns + int(ahead * NS), with_covariance=False)
                ext[ahead].append(np.linalg.norm(s.position - helix(t_ns / NS + ahead)[:3, 3]))
    return sm, ext, raw


# ---- formulas -------------------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(st.floats(0.0, 1.0), st.floats(0.01, 2.0))
def test_hermite_equals_wnoa_interpolation_matrices(frac, dt):
    tau = frac * dt
    Lam, Psi = wnoa_interpolation_matrices(tau, dt)
    H = hermite_matrix(tau, dt)
    # weights of (dt v1, xi21, dt g21) -> (Lam01 v1 + Psi00 xi21 + Psi01 g21, Lam11 v1 + Psi10 xi21 + Psi11 g21)
    np.testing.assert_allclose(H[0] * [dt, 1, dt], [Lam[0, 1], Psi[0, 0], Psi[0, 1]], atol=1e-9)
    np.testing.assert_allclose(H[1] * [dt, 1, dt], [Lam[1, 1], Psi[1, 0], Psi[1, 1]], atol=1e-9)
    cond = wnoa_Q(tau) - Psi @ wnoa_Phi(dt - tau) @ wnoa_Q(tau)
    np.testing.assert_allclose(wnoa_conditional_Q(tau, dt), cond, atol=1e-12)


def _random_segment(rng, dt=0.2):
    T1 = exp_se3(rng.normal(size=6))
    v1 = rng.normal(size=6)
    T2 = T1 @ exp_se3(dt * v1 + 0.1 * rng.normal(size=6))
    v2 = v1 + 0.5 * rng.normal(size=6)
    return T1, v1, T2, v2, dt


@pytest.mark.parametrize("frac", [0.0, 0.13, 0.5, 0.91, 1.0])
def test_interpolation_matches_gtsam(frac):
    """Our numpy interpolation equals gtsam's updateInterpValuesPose3 on the same knots."""
    rng = np.random.default_rng(3)
    T1, v1, T2, v2, dt = _random_segment(rng)
    q = np.array([0.1, 0.2, 0.3, 1.0, 2.0, 3.0])
    tau = frac * dt
    seg = Segment(T1, v1, T2, v2, dt)
    xi, dxi, _ = local_variable(tau, seg.dt, seg.M)
    E_xi, Jr = expmap(xi)
    vals = gtsam.Values()
    vals.insert(X(0), gtsam.Pose3(T1))
    vals.insert(V(0), v1)
    vals.insert(X(2), gtsam.Pose3(T2))
    vals.insert(V(2), v2)
    est = {gtsam.StateData(X(0), V(0), 0.0), gtsam.StateData(X(2), V(2), dt)}
    itp = {gtsam.StateData(X(1), V(1), tau)}
    out = gtsam.updateInterpValuesPose3(gtsam.NonlinearFactorGraph(), vals, est, itp, q)
    np.testing.assert_allclose(T1 @ E_xi, out.atPose3(X(1)).matrix(), atol=1e-12)
    np.testing.assert_allclose(Jr @ dxi, out.atVector6(V(1)), atol=1e-12)


# ---- Jacobians against numerical differences --------------------------------------------------


def _interp_state(T1, v1, T2, v2, dt, tau):
    seg = Segment(T1, v1, T2, v2, dt)
    xi, dxi, _ = local_variable(tau, seg.dt, seg.M)
    E_xi, Jr = expmap(xi)
    return T1 @ E_xi, Jr @ dxi


def _central_difference(perturbed, n_cols: int) -> np.ndarray:
    """12 x n_cols Jacobian by central differences; ``perturbed(j, d)`` is the 12-vector state change
    when block ``j // 6`` is perturbed by the 6-vector ``d`` (non-zero in component ``j % 6``)."""
    num = np.zeros((12, n_cols))
    for j in range(n_cols):
        d = np.zeros(6)
        d[j % 6] = FD_STEP
        num[:, j] = (perturbed(j, d) - perturbed(j, -d)) / (2 * FD_STEP)
    return num


def _state_diff(Ta, va, Tb, vb):
    """(Tb, vb) minus (Ta, va) in right-perturbation coordinates."""
    return np.r_[log_se3(np.linalg.inv(Ta) @ Tb), vb - va]


@pytest.mark.parametrize("frac", [0.0, 0.3, 0.77, 1.0])
def test_interpolation_jacobian_numerical(frac):
    rng = np.random.default_rng(11)
    T1, v1, T2, v2, dt = _random_segment(rng, dt=0.3)
    tau = frac * dt
    seg = Segment(T1, v1, T2, v2, dt)
    xi, dxi, _ = local_variable(tau, seg.dt, seg.M)
    E_xi, Jr = expmap(xi)
    A = interpolation_jacobian(seg, tau, xi, dxi, E_xi, Jr)
    T0, w0 = _interp_state(T1, v1, T2, v2, dt, tau)

    def perturbed(j, d):
        a = [T1, v1, T2, v2]
        a[j // 6] = a[j // 6] @ exp_se3(d) if j // 6 in (0, 2) else a[j // 6] + d
        return _state_diff(T0, w0, *_interp_state(*a, dt, tau))

    np.testing.assert_allclose(A, _central_difference(perturbed, 24), atol=JACOBIAN_ATOL)


@pytest.mark.parametrize("dt", [0.05, 0.5, 2.0])
def test_extrapolation_jacobian_numerical(dt):
    rng = np.random.default_rng(5)
    T, v = exp_se3(rng.normal(size=6)), rng.normal(size=6)
    F = extrapolation_jacobian(dt, v)
    T0 = T @ exp_se3(dt * v)

    def perturbed(j, d):
        Tp, vp = (T @ exp_se3(d), v) if j < 6 else (T, v + d)
        return _state_diff(T0, v, Tp @ exp_se3(dt * vp), vp)

    np.testing.assert_allclose(F, _central_difference(perturbed, 12), atol=JACOBIAN_ATOL)


def test_jr_derivatives_numerical():
    """The derivative helpers of Jr(xi) w and Jr^-1(xi) w against a coarser independent difference."""
    rng = np.random.default_rng(2)
    xi, w = rng.normal(size=6), rng.normal(size=6)
    h = 1e-4
    for fn, jac in ((jr, d_jr_times), (jr_inv, d_jr_inv_times)):
        num = np.stack([(fn(xi + h * e) @ w - fn(xi - h * e) @ w) / (2 * h) for e in np.eye(6)], axis=1)
        np.testing.assert_allclose(jac(xi, w), num, atol=1e-7)


# ---- smoother on a known trajectory ----------------------------------------------------------


def test_helix_interpolation_accuracy(helix_run):
    sm, _, raw = helix_run
    pos, rot, vel, angvel = [], [], [], []
    t_end = (HELIX_KEYFRAMES - 1) * HELIX_KEYFRAME_NS
    for t_ns in range(HELIX_WARMUP * HELIX_KEYFRAME_NS, t_end, HELIX_QUERY_NS):
        s = sm.state_at(t_ns, with_covariance=False)
        T = helix(t_ns / NS)
        pos.append(np.linalg.norm(s.position - T[:3, 3]))
        rot.append(np.linalg.norm(log_se3(np.linalg.inv(T) @ s.pose)[:3]))
        tw = helix_twist(t_ns / NS)
        vel.append(np.linalg.norm(s.velocity[3:] - tw[3:]))
        angvel.append(np.linalg.norm(s.velocity[:3] - tw[:3]))
    print(
        f"\nhelix interpolation at 50 Hz: position rms {rms(pos):.4f} max {max(pos):.4f} m "
        f"(raw measurements rms {rms(raw):.4f} m); rotation rms {rms(rot):.4f} max {max(rot):.4f} rad; "
        f"velocity rms {rms(vel):.3f} m/s; angular velocity rms {rms(angvel):.3f} rad/s"
    )
    # measured: position 0.012 rms / 0.029 max; rotation 0.0026 / 0.007; velocity 0.12; angular 0.032
    assert rms(pos) < 0.02 and max(pos) < 0.05
    assert rms(pos) < rms(raw)
    assert rms(rot) < 0.005 and max(rot) < 0.015
    assert rms(vel) < 0.2
    assert rms(angvel) < 0.06


def test_helix_extrapolation_accuracy(helix_run):
    _, ext, _ = helix_run
    e1, e5 = ext[0.1], ext[0.5]
    print(
        f"\nhelix extrapolation: +0.1 s rms {rms(e1):.4f} max {max(e1):.4f} m; "
        f"+0.5 s rms {rms(e5):.4f} max {max(e5):.4f} m"
    )
    # measured: +0.1 s 0.033 rms / 0.07 max; +0.5 s 0.12 rms / 0.29 max. Physically: a constant-twist
    # prediction misses half the centripetal acceleration (1.25 m/s²) times t², 0.16 m at 0.5 s.
    assert rms(e1) < 0.05 and max(e1) < 0.12
    assert rms(e5) < 0.2 and max(e5) < 0.45
    assert rms(e1) < rms(e5)


def test_acceleration_is_derivative_of_velocity(helix_run):
    sm, _, _ = helix_run
    h = 1_000_000  # 1 ms
    for t_ns in (2_030_000_000, 5_555_000_000, 9_010_000_000):
        s = sm.state_at(t_ns, with_covariance=False)
        vp = sm.state_at(t_ns + h, with_covariance=False).velocity
        vm = sm.state_at(t_ns - h, with_covariance=False).velocity
        np.testing.assert_allclose(s.acceleration, (vp - vm) / (2 * h / NS), atol=1e-4)
        # with covariance the same mean comes out
        np.testing.assert_allclose(sm.state_at(t_ns).acceleration, s.acceleration, atol=1e-8)


def _world_acceleration_errors(sm):
    errs = []
    for t_ns in range(2 * NS, 14 * NS, 50_000_000):
        s = sm.state_at(t_ns, with_covariance=False)
        t = t_ns / NS
        p = lambda u: helix(u)[:3, 3]  # noqa: E731
        a_true = (p(t + 1e-3) - 2 * p(t) + p(t - 1e-3)) / 1e-6
        errs.append(np.linalg.norm(s.linear_acceleration_world - a_true))
    return errs


def test_helix_acceleration_world(helix_run):
    """Acceleration of the sensor origin in world: exact on noiseless data, noisy on noisy data."""
    sm_clean = TrajectorySmoother(SmoothingConfig())
    cov = np.diag([1e-10] * 3 + [1e-8] * 3)
    for k in range(HELIX_KEYFRAMES):
        sm_clean.add_pose(k * HELIX_KEYFRAME_NS, helix(k * HELIX_KEYFRAME_NS / NS), cov)
    clean = _world_acceleration_errors(sm_clean)
    noisy = _world_acceleration_errors(helix_run[0])
    print(
        f"\nhelix world acceleration error rms: noiseless {rms(clean):.4f} m/s², with 1 cm noise "
        f"{rms(noisy):.2f} m/s² (true magnitude 1.25 m/s²)"
    )
    # measured: noiseless 0.0097, noisy 2.25 (the second derivative of the GP mean amplifies noise)
    assert rms(clean) < 0.03
    assert rms(noisy) < 3.5


def test_continuity_at_knots(helix_run):
    sm, _, _ = helix_run
    for k in (12, 60, 140):
        t = k * HELIX_KEYFRAME_NS
        a, b, c = (sm.state_at(t + d, with_covariance=False) for d in (-1, 0, 1))
        assert b.kind == "knot"
        np.testing.assert_allclose(a.pose, b.pose, atol=1e-6)
        np.testing.assert_allclose(c.pose, b.pose, atol=1e-6)
        np.testing.assert_allclose(a.velocity, b.velocity, atol=1e-5)


# ---- covariances against batch marginals of the same model --------------------------------------


def _batch_marginal(times, meas, cov, qc, vel_sig, t_query):
    """Marginal covariance at t_query from a batch graph with an extra knot at t_query (exact GP model)."""
    all_t = sorted(set(times) | {t_query})
    g = gtsam.NonlinearFactorGraph()
    v = gtsam.Values()
    mi = {t: i for i, t in enumerate(times)}
    for i, t in enumerate(all_t):
        if t in mi:
            g.add(gtsam.PriorFactorPose3(X(i), gtsam.Pose3(meas[mi[t]]), gtsam.noiseModel.Gaussian.Covariance(cov)))
        if i == 0:
            g.add(gtsam.PriorFactorVector6(V(0), np.zeros(6), gtsam.noiseModel.Diagonal.Sigmas(vel_sig)))
        else:
            g.add(
                gtsam.WnoaMotionFactorPose3(
                    gtsam.StateData(X(i - 1), V(i - 1), all_t[i - 1] / NS), gtsam.StateData(X(i), V(i), t / NS), qc
                )
            )
        near = meas[min(mi.get(t, len(times) - 1), len(times) - 1)]
        v.insert(X(i), gtsam.Pose3(near))
        v.insert(V(i), np.zeros(6))
    res = gtsam.LevenbergMarquardtOptimizer(g, v).optimize()
    m = gtsam.Marginals(g, res)
    iq = all_t.index(t_query)
    J = m.jointMarginalCovariance([X(iq), V(iq)]).fullMatrix()
    return J, res.atPose3(X(iq)).matrix(), res.atVector(V(iq))


def test_covariance_matches_batch_marginals():
    rng = np.random.default_rng(8)
    cfg = SmoothingConfig(qc_rotation=0.1, qc_translation=1.0, lag_s=100.0)
    sm = TrajectorySmoother(cfg)
    cov = np.diag([1e-4] * 3 + [1e-2] * 3)
    times = [k * HELIX_KEYFRAME_NS for k in range(12)]
    meas = [helix(t / NS) @ exp_se3(np.r_[rng.normal(0, 0.01, 3), rng.normal(0, 0.1, 3)]) for t in times]
    for t, M in zip(times, meas, strict=True):
        sm.add_pose(t, M, cov)
    sm.refine(5)
    vel_sig = sm.velocity_prior_sigmas
    worst = {}
    for t_q, kind in (
        (times[-2] + 37_000_000, "interpolated"),
        (times[-1], "knot"),
        (times[-1] + 300_000_000, "extrapolated"),
    ):
        s = sm.state_at(t_q)
        assert s.kind == kind
        J, T_b, v_b = _batch_marginal(times, meas, cov, sm.q_psd, vel_sig, t_q)
        np.testing.assert_allclose(s.pose, T_b, atol=1e-5)
        np.testing.assert_allclose(s.velocity, v_b, atol=1e-4)
        sd = np.sqrt(np.diag(J))
        rel = np.abs(s.covariance - J) / np.outer(sd, sd)  # correlation-scale difference
        worst[kind] = rel.max()
        assert rel.max() < 0.02, (kind, rel.max())
    print(
        "\ncovariance vs batch marginals, max |diff| / (sigma_i sigma_j): "
        + ", ".join(f"{k} {v:.1e}" for k, v in worst.items())
    )


# ---- measurements of both kinds, fixed lag ---------------------------------------------------


def test_relative_measurements_and_fixed_lag():
    rng = np.random.default_rng(4)
    cfg = SmoothingConfig(lag_s=1.0)
    sm = TrajectorySmoother(cfg)
    cov = np.diag([1e-6] * 3 + [1e-4] * 3)
    n = 40
    truth = [helix(k * 0.1) for k in range(n)]
    sm.add_pose(0, truth[0], cov)
    for k in range(1, n):
        rel = np.linalg.inv(truth[k - 1]) @ truth[k] @ exp_se3(rng.normal(0, 1e-3, 6))
        if k % 10 == 0:  # a localization every second, odometry in between
            sm.add_knot(
                k * HELIX_KEYFRAME_NS, T_world_sensor=truth[k], covariance=cov, T_prev_cur=rel, relative_covariance=cov
            )
        else:
            sm.add_relative_pose(k * HELIX_KEYFRAME_NS, rel, cov)
    knots = sm.knots()
    assert len(knots.times_ns) == n
    err = max(np.linalg.norm(P[:3, 3] - T[:3, 3]) for P, T in zip(knots.poses, truth, strict=True))
    assert err < 0.05
    # the window slid: old knots are final and still answer queries
    assert sm.window_start_ns > 0
    old = sm.state_at(5 * HELIX_KEYFRAME_NS + 50_000_000)
    assert old.kind == "interpolated" and old.covariance is not None
    assert np.all(np.linalg.eigvalsh(old.covariance) > 0)


def test_state_is_frozen(helix_run):
    sm, _, _ = helix_run
    s = sm.state_at(3 * NS + 1)
    assert isinstance(s, TrajectoryState)
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.t_ns = 0  # type: ignore[misc]
    with pytest.raises(ValueError):
        s.pose[0, 0] = 2.0
    assert s.covariance.shape == (12, 12)
    assert np.all(np.linalg.eigvalsh(s.covariance) > 0)


# ---- bad input --------------------------------------------------------------------------------


def _snapshot(sm: TrajectorySmoother):
    k = sm.knots()
    probes = [sm.state_at(t) for t in (0, 150_000_000, 250_000_000, 900_000_000)]
    return k, probes, sm.num_keyframes


def _assert_same(a, b):
    (ka, pa, na), (kb, pb, nb) = a, b
    assert na == nb
    np.testing.assert_array_equal(ka.times_ns, kb.times_ns)
    np.testing.assert_array_equal(ka.poses, kb.poses)
    np.testing.assert_array_equal(ka.velocities, kb.velocities)
    for x, y in zip(pa, pb, strict=True):
        np.testing.assert_array_equal(x.pose, y.pose)
        np.testing.assert_array_equal(x.velocity, y.velocity)
        np.testing.assert_array_equal(x.covariance, y.covariance)


def _good_smoother():
    sm = TrajectorySmoother(SmoothingConfig())
    cov = np.diag([1e-4] * 3 + [1e-2] * 3)
    for k in range(3):
        sm.add_pose(k * HELIX_KEYFRAME_NS, helix(k * 0.1), cov)
    return sm, cov


def _bad_cases(cov):
    T = helix(0.3)
    nan_T = T.copy()
    nan_T[0, 3] = np.nan
    skew_T = T.copy()
    skew_T[:3, :3] *= 1.1
    neg_cov = cov.copy()
    neg_cov[0, 0] = -1e-4
    asym = cov.copy()
    asym[0, 1] = 1e-3
    nan_cov = cov.copy()
    nan_cov[2, 2] = np.nan
    t = 3 * HELIX_KEYFRAME_NS
    return {
        "out of order": lambda s: s.add_pose(150_000_000, T, cov),
        "duplicate time": lambda s: s.add_pose(200_000_000, T, cov),
        "float time": lambda s: s.add_pose(float(t), T, cov),
        "non-SE(3)": lambda s: s.add_pose(t, skew_T, cov),
        "wrong shape": lambda s: s.add_pose(t, T[:3], cov),
        "NaN pose": lambda s: s.add_pose(t, nan_T, cov),
        "non-PSD covariance": lambda s: s.add_pose(t, T, neg_cov),
        "asymmetric covariance": lambda s: s.add_pose(t, T, asym),
        "NaN covariance": lambda s: s.add_pose(t, T, nan_cov),
        "singular covariance": lambda s: s.add_pose(t, T, np.zeros((6, 6))),
        "no measurement": lambda s: s.add_knot(t),
        "pose without covariance": lambda s: s.add_knot(t, T_world_sensor=T),
        "query before first": lambda s: s.state_at(-1),
        "query with float time": lambda s: s.state_at(0.5),
    }


@pytest.mark.parametrize("case", list(_bad_cases(np.eye(6)).keys()))
def test_bad_input_raises_and_leaves_state_unchanged(case):
    sm, cov = _good_smoother()
    before = _snapshot(sm)
    with pytest.raises(EstimationError):
        _bad_cases(cov)[case](sm)
    _assert_same(before, _snapshot(sm))
    # and the smoother still works
    sm.add_pose(3 * HELIX_KEYFRAME_NS, helix(0.3), cov)
    assert sm.num_keyframes == 4


def test_empty_smoother_rejects_queries_and_relative_first():
    sm = TrajectorySmoother(SmoothingConfig())
    with pytest.raises(EstimationError, match="no measurement"):
        sm.state_at(0)
    with pytest.raises(EstimationError, match="first keyframe"):
        sm.add_relative_pose(0, np.eye(4), np.eye(6))
    assert sm.num_keyframes == 0
    sm.add_pose(5, np.eye(4), np.eye(6) * 1e-4)
    s = sm.state_at(5 + NS)
    assert s.kind == "extrapolated"
    np.testing.assert_allclose(s.pose, np.eye(4), atol=1e-9)
