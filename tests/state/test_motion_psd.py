"""The WNOA prior's Qc estimated from the vehicle's own motion (vtr.state.wnoa.MotionPsd): on a simulated WNOA
trajectory with keyframe positions measured with noise, the two spans recover Qc, not Qc plus the noise."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vtr.geometry import make_T
from vtr.state.wnoa import MotionPsd

FALLBACK = np.ones(6)


def _steps(qc: float, noise_m: float, dt_s: float, n: int, seed: int) -> list[np.ndarray]:
    """Translation-only keyframe steps of a WNOA motion (per axis PSD qc) with position noise."""
    rng = np.random.default_rng(seed)
    fine = 20  # substeps per keyframe for the simulation
    h = dt_s / fine
    v = np.array([5.0, 0.0, 0.0])
    p = np.zeros(3)
    keyframes = [p.copy()]
    for _ in range(n):
        for _ in range(fine):
            dv = rng.normal(0.0, np.sqrt(qc * h), 3)
            p = p + v * h + dv * h / 2
            v = v + dv
        keyframes.append(p.copy())
    measured = np.array(keyframes) + rng.normal(0.0, noise_m, (n + 1, 3))
    return [np.r_[0.0, 0.0, 0.0, b - a] for a, b in zip(measured[:-1], measured[1:], strict=True)]


@settings(max_examples=10, deadline=None)
@given(qc=st.sampled_from([0.01, 0.1, 1.0]), noise_m=st.sampled_from([0.0, 0.002, 0.005]), seed=st.integers(0, 1000))
def test_the_estimate_finds_the_motion_s_psd_under_noise(qc, noise_m, seed):
    est = MotionPsd(FALLBACK, window_s=1e9, min_samples=5, floor_share=1e-6, long_steps=4)
    for xi in _steps(qc, noise_m, 0.1, 3000, seed):
        est.add(xi, 0.1)
    got = est.qc[3:]
    # the noise alone would read as 6 r / (T1 + T2) / (2 dt / 3) per axis: 0.23-1.5 m^2/s^3 here
    assert np.all(got > 0.6 * qc) and np.all(got < 1.6 * qc), (qc, noise_m, got)


def test_the_fallback_holds_until_enough_samples_and_after_a_break():
    est = MotionPsd(FALLBACK, window_s=10.0, min_samples=5, floor_share=1e-3, long_steps=4)
    step = np.r_[0.0, 0.0, 0.0, 1.0, 0.0, 0.0]
    for _ in range(8):
        est.add(step, 0.1)
    assert np.array_equal(est.qc, FALLBACK)  # one long-span sample so far
    for _ in range(10):
        est.add(step, 0.1)
    assert np.allclose(est.qc, 1e-3)  # a constant twist: no acceleration, the floor
    est.broken()
    est.add(step * 3, 0.1)  # no sample across the break
    assert np.allclose(est.qc, 1e-3)


def test_a_taught_path_gives_the_prior_and_a_disabled_estimate_the_configured_qc():
    t = np.arange(50) * 100_000_000
    T = np.array([make_T(np.eye(3), [0.0, 0.0, 0.5 * k]) for k in range(50)])
    est = MotionPsd(FALLBACK, window_s=10.0, min_samples=5, floor_share=1e-3, long_steps=4)
    assert np.allclose(est.of_poses(t, T, max_step_s=1.0), 1e-3)
    assert np.array_equal(est.of_poses(t[:5], T[:5], max_step_s=1.0), FALLBACK)  # too short to say
    off = MotionPsd(FALLBACK, window_s=0.0, min_samples=5, floor_share=1e-3, long_steps=4)
    assert np.array_equal(off.of_poses(t, T, max_step_s=1.0), FALLBACK)


def test_the_floor_is_a_share_of_the_configured_qc_even_when_the_fallback_is_an_estimate():
    """A repeat starts from its taught path's estimate; on a motion with no acceleration at all (a synthetic constant-
    velocity flight) that estimate sits at its own floor, and a floor taken as a share of *it* fell to 1e-6 of the
    configured Qc: a prior so stiff against odometry that GTSAM found the system indeterminate (the demo's aerial
    mission failed). The floor is a share of the configured Qc."""
    configured = np.r_[np.full(3, 0.1), np.full(3, 1.0)]
    taught = 1e-3 * configured  # a taught estimate at its own floor
    est = MotionPsd(taught, window_s=1e9, min_samples=5, floor_share=1e-3, long_steps=4, configured=configured)
    for _ in range(200):  # exactly constant velocity: no motion PSD at all
        est.add(np.r_[0.0, 0.0, 0.0, 0.5, 0.0, 0.0], 0.1)
    np.testing.assert_allclose(est.qc, 1e-3 * configured)


def _odometry_like_steps(qc: float, step_sd: float, scale_sd: float, scale_s: float, seed: int) -> list[np.ndarray]:
    """Along-track keyframe steps (0.2 s at 12 m/s) of a WNOA motion with PSD ``qc``, measured as odometry errs: each
    step off by an independent share ``step_sd`` of itself plus a scale error ``scale_sd`` that varies over
    ``scale_s`` seconds (a first-order Gauss-Markov process)."""
    rng = np.random.default_rng(seed)
    n, fine, dt = 3000, 20, 0.2
    h = dt / fine
    dv = rng.normal(0.0, np.sqrt(qc * h), n * fine)
    v = 12.0 + np.r_[0.0, np.cumsum(dv)[:-1]]
    true = (v * h + dv * h / 2).reshape(n, fine).sum(axis=1)
    a = np.exp(-dt / scale_s)
    kick = np.sqrt(1 - a * a) * rng.normal(0.0, scale_sd, n)
    scale = np.zeros(n)
    for i in range(1, n):
        scale[i] = a * scale[i - 1] + kick[i]
    measured = true * (1.0 + scale + rng.normal(0.0, step_sd, n))
    return [np.r_[0.0, 0.0, 0.0, 0.0, 0.0, x] for x in measured]


@pytest.mark.xfail(
    strict=True,
    reason="measured: odometry's along-track error on kitti06 is partly a scale varying over ~1 s (steps off by +60, "
    "+69, then -80, -42, -51, -32 mm); with 1.25 % independent step errors and a 0.75 % scale correlated over 1 s the "
    "estimate reads 0.022-0.028 m2/s3 for a true 0.001 (the independent part alone 0.015-0.020: the positions' noise "
    "model reads it as 0.14 s / tau^3); on kitti06 0.014 against the true motion's 0.0013 (docs/online.md)",
)
def test_the_estimate_finds_the_motion_s_psd_under_odometry_like_errors():
    for seed in range(3):
        est = MotionPsd(FALLBACK, window_s=1e9, min_samples=5, floor_share=1e-6, long_steps=4)
        for xi in _odometry_like_steps(1e-3, 0.0125, 0.0075, 1.0, seed):
            est.add(xi, 0.2)
        assert 0.5e-3 < est.qc[5] < 2e-3, (seed, est.qc[5])
