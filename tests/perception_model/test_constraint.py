"""Chance constraint: values, analytic gradients vs finite differences, exact and MC tails, properties."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from perception_model.angles import optical_axis, parallax_angle, view_angle
from perception_model.constraint import (
    PerceptionConstraint,
    c_bar_from_delta,
    compare_tails,
    delta_from_c_bar,
    inlier_moments,
    monte_carlo_tail,
    normal_tail,
    poisson_binomial_pmf,
    poisson_binomial_tail,
)
from perception_model.errors import GeometryError, PerceptionModelError
from perception_model.model import PerceptionModel
from perception_model.synthetic import ground_scene

THESIS = PerceptionModel.thesis()
GRAD_RTOL = 1e-6
FD_STEP_M = 1e-4  # central differences: truncation ~h^2 f''' and rounding ~eps f / h both << 1e-6 relative
FD_STEP_RAD = 1e-5
BOUNDARY_MARGIN = 1e-3  # FD points keep every landmark this far (rad / probability) from cut and clip


@pytest.fixture(scope="module")
def scene():
    return ground_scene(800, np.random.default_rng(11))


def _horizon(rng, n):
    k = np.arange(n)
    pos = np.column_stack([0.3 * k, rng.uniform(-3, 3, n), rng.uniform(-1, 1, n)])
    return pos, rng.uniform(-0.3, 0.3, n)


def _away_from_boundaries(model, lm, pos, yaw):
    """True if no landmark is near the view cut, the clip at 1, or alpha = 0 for any horizon step."""
    alpha = parallax_angle(lm[None], pos[:, None])
    theta = view_angle(lm[None], pos[:, None], optical_axis(yaw)[:, None])
    raw = model.raw(alpha, theta)
    return (
        np.abs(theta - model.theta_cutoff).min() > BOUNDARY_MARGIN
        and np.abs(raw - 1.0).min() > BOUNDARY_MARGIN
        and alpha.min() > BOUNDARY_MARGIN
    )


def _fd(con, pos, yaw, attr, axes=None):
    """Central differences of ``attr`` w.r.t. each position coordinate and yaw."""

    def f(p, y):
        return getattr(con.evaluate(p, None if axes is not None else y, axes=axes, gradient=False), attr)

    d_pos = np.empty(pos.shape)
    for j in range(3):
        e = np.zeros(3)
        e[j] = FD_STEP_M
        d_pos[:, j] = (f(pos + e, yaw) - f(pos - e, yaw)) / (2 * FD_STEP_M)
    d_yaw = (f(pos, yaw + FD_STEP_RAD) - f(pos, yaw - FD_STEP_RAD)) / (2 * FD_STEP_RAD)
    return d_pos, d_yaw


def _rel_err(analytic, fd):
    return float(
        np.max(np.linalg.norm(np.atleast_2d(fd - analytic), axis=-1) / np.linalg.norm(np.atleast_2d(analytic), axis=-1))
    )


def test_c_bar_from_delta():
    assert c_bar_from_delta(delta_from_c_bar(3.0)) == pytest.approx(3.0, rel=1e-12)
    assert c_bar_from_delta(0.05) == pytest.approx(stats.norm.ppf(0.95), rel=1e-12)
    with pytest.raises(PerceptionModelError):
        c_bar_from_delta(0.7)


def test_probabilities_match_the_model_and_angle_functions(scene):
    rng = np.random.default_rng(1)
    pos, yaw = _horizon(rng, 6)
    con = PerceptionConstraint(THESIS, scene.landmarks)
    ev = con.evaluate(pos, yaw)
    alpha = parallax_angle(scene.landmarks[None], pos[:, None])
    theta = view_angle(scene.landmarks[None], pos[:, None], optical_axis(yaw)[:, None])
    ref = THESIS.probability(alpha, theta)
    assert np.allclose(ev.p, ref, atol=1e-13)
    mu, var = inlier_moments(ref)
    assert np.allclose(ev.mu, mu) and np.allclose(ev.sigma, np.sqrt(var))
    assert np.allclose(ev.g, mu - 3.0 * np.sqrt(var) - 30.0)
    assert np.allclose(ev.g_conservative, mu - 3.0 * np.sqrt(mu) - 30.0)


@pytest.mark.parametrize(
    "model",
    [THESIS, PerceptionModel(1.6, 0.028, -0.145), PerceptionModel(0.5, 0.012, -0.1)],
    ids=["thesis", "clipped-at-1", "wide-view(no-cut-polynomial-fallback)"],
)
def test_analytic_gradients_match_central_differences(scene, model):
    rng = np.random.default_rng(2)
    con = PerceptionConstraint(model, scene.landmarks, l_min=30.0, c_bar=3.0)
    pos, yaw = _horizon(rng, 15)
    keep = [i for i in range(15) if _away_from_boundaries(model, scene.landmarks, pos[i : i + 1], yaw[i : i + 1])]
    assert len(keep) >= 10
    pos, yaw = pos[keep], yaw[keep]
    ev = con.evaluate(pos, yaw)
    errors = {}
    for attr, gp, gy in (
        ("mu", "dmu_dpos", "dmu_dyaw"),
        ("sigma", "dsigma_dpos", "dsigma_dyaw"),
        ("g", "dg_dpos", "dg_dyaw"),
        ("g_conservative", "dgc_dpos", "dgc_dyaw"),
    ):
        fd_pos, fd_yaw = _fd(con, pos, yaw, attr)
        errors[attr] = (
            _rel_err(getattr(ev, gp), fd_pos),
            _rel_err(getattr(ev, gy)[:, None], fd_yaw[:, None]),
        )
    print(f"\nmax relative gradient error (position, yaw) for {model.constants}: {errors}")
    for e_pos, e_yaw in errors.values():
        assert e_pos <= GRAD_RTOL and e_yaw <= GRAD_RTOL


def test_gradients_with_explicit_axes(scene):
    rng = np.random.default_rng(4)
    con = PerceptionConstraint(THESIS, scene.landmarks)
    pos, yaw = _horizon(rng, 5)
    axes = optical_axis(yaw) * 3.0  # length does not matter
    ev = con.evaluate(pos, axes=axes)
    assert ev.dmu_dyaw is None
    ref = con.evaluate(pos, yaw)
    assert np.allclose(ev.g, ref.g) and np.allclose(ev.dg_dpos, ref.dg_dpos)
    fd_pos, _ = _fd(con, pos, yaw, "g", axes=axes)
    assert _rel_err(ev.dg_dpos, fd_pos) <= GRAD_RTOL


def test_linearization_for_one_sqp_step(scene):
    con = PerceptionConstraint(THESIS, scene.landmarks)
    pos, yaw = _horizon(np.random.default_rng(6), 15)
    for kind in ("normal", "conservative"):
        lin = con.linearize(pos, yaw, kind=kind)
        ev = con.evaluate(pos, yaw)
        assert np.allclose(lin.value, ev.g if kind == "normal" else ev.g_conservative)
        step = np.full((15, 3), 1e-3)
        new = con.evaluate(pos + step, yaw + 1e-4, gradient=False)
        target = new.g if kind == "normal" else new.g_conservative
        assert np.allclose(lin.predict(pos + step, yaw + 1e-4), target, atol=1e-4)
        a, b = lin.as_inequality()
        y0 = np.column_stack([pos, yaw])
        assert a.shape == (15, 4) and np.allclose(np.einsum("ij,ij->i", a, y0) - b, lin.value)
    with pytest.raises(PerceptionModelError):
        con.linearize(pos, yaw, kind="bogus")


def test_geometry_errors(scene):
    with pytest.raises(GeometryError, match="taught camera"):
        PerceptionConstraint(THESIS, np.zeros((2, 3)))
    con = PerceptionConstraint(THESIS, scene.landmarks)
    with pytest.raises(GeometryError, match="coincides"):
        con.evaluate(scene.landmarks[:1], [0.0])
    with pytest.raises(GeometryError, match="NaN"):
        con.evaluate([[np.nan, 0, 0]], [0.0])
    with pytest.raises(PerceptionModelError, match="exactly one"):
        con.evaluate([[0.0, 0, 0]])
    # camera exactly on the taught camera: alpha = 0 for every landmark, gradient finite (zero subgradient)
    ev = con.evaluate([[0.0, 0.0, 0.0]], [scene.yaw])
    assert np.all(np.isfinite(ev.dg_dpos)) and np.isfinite(ev.dg_dyaw).all()


def test_poisson_binomial_exact_distribution():
    rng = np.random.default_rng(8)
    p = rng.uniform(0, 0.6, 300)
    pmf = poisson_binomial_pmf(p)
    assert pmf.sum() == pytest.approx(1.0, abs=1e-12)
    k = np.arange(pmf.size)
    mu, var = inlier_moments(p)
    assert (k * pmf).sum() == pytest.approx(mu, rel=1e-12)
    assert ((k - mu) ** 2 * pmf).sum() == pytest.approx(var, rel=1e-10)
    assert np.allclose(poisson_binomial_pmf(p, "dft"), pmf, atol=1e-13)
    same = np.full(50, 0.3)
    assert np.allclose(poisson_binomial_pmf(same), stats.binom.pmf(np.arange(51), 50, 0.3), atol=1e-14)
    assert poisson_binomial_tail(p, 40) + poisson_binomial_tail(p, 40, lower=True) == pytest.approx(1.0)
    assert poisson_binomial_tail([], 0) == 1.0
    with pytest.raises(PerceptionModelError):
        poisson_binomial_pmf([0.5, 1.2])


def test_normal_vs_exact_vs_monte_carlo_on_800_landmarks(scene):
    """P(L < L_min) for the thesis scene at growing lateral offsets from the taught camera."""
    con = PerceptionConstraint(THESIS, scene.landmarks)
    rng = np.random.default_rng(9)
    head = ("offset m", "mu", "sigma", "normal", "exact", "MC", "MC se")
    print("\n" + " ".join(f"{h:>10s}" for h in head))
    for off in (3.5, 4.0, 4.5, 5.0):
        p = con.probabilities([[0.0, off, 0.0]], [scene.yaw])[0]
        t = compare_tails(p, 30.0, n_samples=40_000, rng=rng)
        cells = (
            f"{off:.1f}",
            f"{t.mu:.1f}",
            f"{t.sigma:.2f}",
            f"{t.normal:.3e}",
            f"{t.exact:.3e}",
            f"{t.monte_carlo:.3e}",
            f"{t.monte_carlo_se:.1e}",
        )
        print(" ".join(f"{c:>10s}" for c in cells))
        assert t.n_landmarks == 800
        assert abs(t.monte_carlo - t.exact) <= 4.0 * t.monte_carlo_se + 1e-6
        assert t.exact_dft == pytest.approx(t.exact, abs=1e-12)
        assert abs(t.normal - t.exact) < 0.05
        # p_i are small, so L is right-skewed: its left tail is lighter than the normal one and the
        # normal approximation overestimates the failure probability (conservative) near the bound
        if t.exact < 0.05:
            assert t.normal >= t.exact


def test_monte_carlo_and_normal_tail_helpers():
    p = np.full(100, 0.5)
    est, se = monte_carlo_tail(p, 50, 20_000, rng=np.random.default_rng(0))
    exact = poisson_binomial_tail(p, 50)
    assert abs(est - exact) < 4 * se
    assert normal_tail(50.0, 5.0, 50.0) == pytest.approx(0.5)
    assert normal_tail(50.0, 5.0, 50.0, lower=True) == pytest.approx(0.5)
    assert normal_tail(50.0, 0.0, 40.0) == 1.0


prob_lists = st.lists(st.floats(0.0, 1.0, allow_nan=False), min_size=1, max_size=200)


@settings(max_examples=200, deadline=None)
@given(p=prob_lists, c_bar=st.floats(0.0, 6.0), l_min=st.floats(0.0, 100.0))
def test_conservative_never_exceeds_normal_approximation(p, c_bar, l_min):
    mu, var = inlier_moments(np.array(p))
    g = mu - c_bar * math.sqrt(var) - l_min
    g_c = mu - c_bar * math.sqrt(mu) - l_min
    assert g_c <= g + 1e-9


@settings(max_examples=60, deadline=None)
@given(
    x=st.floats(-8.0, 8.0),
    y=st.floats(-8.0, 8.0),
    z=st.floats(-3.0, 3.0),
    yaw=st.floats(-math.pi, math.pi),
    c_bar=st.floats(0.0, 5.0),
)
def test_conservative_le_normal_along_any_pose(scene, x, y, z, yaw, c_bar):
    con = PerceptionConstraint(THESIS, scene.landmarks[:200], c_bar=c_bar)
    ev = con.evaluate([[x, y, z]], [yaw], gradient=False)
    assert ev.g_conservative[0] <= ev.g[0] + 1e-9


@pytest.mark.parametrize("force_exact", [False, True], ids=["polynomial+fallback", "exact-only"])
def test_view_factor_paths_behind_the_camera(monkeypatch, force_exact):
    """Landmarks all around the camera (view angles up to 180 deg) with a wide-view model (cut at 131 deg)."""
    import perception_model.constraint as constraint_mod

    if force_exact:
        monkeypatch.setattr(constraint_mod, "_build_view_factor", lambda *args: None)
    model = PerceptionModel(0.5, 0.012, -0.1)
    rng = np.random.default_rng(12)
    lm = rng.normal(size=(400, 3)) * 15.0
    con = PerceptionConstraint(model, lm)
    assert (con._view is None) == force_exact
    pos = rng.uniform(-2, 2, (6, 3))
    yaw = rng.uniform(-3, 3, 6)
    ev = con.evaluate(pos, yaw)
    theta = view_angle(lm[None], pos[:, None], optical_axis(yaw)[:, None])
    assert (theta > math.radians(95)).any() and (theta > model.theta_cutoff).any()
    ref = model.probability(parallax_angle(lm[None], pos[:, None]), theta)
    assert np.allclose(ev.p, ref, atol=1e-13)
    keep = [i for i in range(6) if _away_from_boundaries(model, lm, pos[i : i + 1], yaw[i : i + 1])]
    assert len(keep) >= 2
    fd_pos, fd_yaw = _fd(con, pos[keep], yaw[keep], "g")
    sub = con.evaluate(pos[keep], yaw[keep])
    assert _rel_err(sub.dg_dpos, fd_pos) <= GRAD_RTOL
    assert _rel_err(sub.dg_dyaw[:, None], fd_yaw[:, None]) <= GRAD_RTOL
