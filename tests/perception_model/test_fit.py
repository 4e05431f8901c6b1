"""Fitting: recovery of the thesis constants from synthetic labels, intervals, evaluation, bad data."""

from __future__ import annotations

import math

import numpy as np
import pytest

from perception_model.errors import FitError, PerceptionModelWarning
from perception_model.fit import (
    PROB_EPS,
    FitSettings,
    Samples,
    calibration_table,
    evaluate,
    fit_binned,
    fit_mle,
    fit_observations,
    holdout_split,
    neg_log_likelihood,
    simulate_labels,
)
from perception_model.model import PerceptionModel
from perception_model.synthetic import sample_angles, simulate_observations

TRUE = PerceptionModel.thesis()
N_OBS = 200_000  # >= 50 000 required; 200 000 keeps the 5 % recovery far from the noise (~2 s.e. at 50k)
REL_TOL = 0.05


@pytest.fixture(scope="module")
def synthetic():
    """Thesis-model labels at uniform angles: parallax 0-20 deg, view 0-50 deg (thesis data range)."""
    rng = np.random.default_rng(20240607)
    a, t = sample_angles(N_OBS, rng)
    y = simulate_labels(TRUE, a, t, rng)
    return a, t, y


@pytest.fixture(scope="module")
def binned_fit(synthetic):
    return fit_binned(Samples(*synthetic))


@pytest.fixture(scope="module")
def mle_fit(synthetic):
    return fit_mle(Samples(*synthetic))


def _report(result):
    cis = ", ".join(f"{c.name}={c.estimate:.5f} [{c.low:.5f}, {c.high:.5f}]" for c in result.intervals)
    print(f"\n{result.method}: n={result.n} R2={result.r2:.4f} log-loss={result.log_loss:.4f} {cis}")


def test_binned_recovers_thesis_constants_within_5_percent(binned_fit):
    _report(binned_fit)
    assert binned_fit.converged
    assert binned_fit.model.angle_unit == "deg"
    for est, true in zip(binned_fit.model.constants, TRUE.constants, strict=True):
        assert abs(est / true - 1.0) < REL_TOL
    assert binned_fit.r2 > 0.9
    for c in binned_fit.intervals:
        assert c.low < c.estimate < c.high


def test_mle_interval_contains_true_constants(mle_fit):
    _report(mle_fit)
    assert mle_fit.converged
    assert mle_fit.ci_method == "fisher"
    for c, true in zip(mle_fit.intervals, TRUE.constants, strict=True):
        assert c.contains(true), c
        assert abs(c.estimate / true - 1.0) < REL_TOL


def test_mle_and_binned_agree_and_are_as_good_as_truth(synthetic, binned_fit, mle_fit):
    a, t, y = synthetic
    truth = evaluate(TRUE, Samples(a, t, y))
    for r in (binned_fit, mle_fit):
        assert r.log_loss == pytest.approx(truth.log_loss, abs=2e-3)
    # the MLE maximizes the likelihood, so its training log-loss is the lowest
    assert mle_fit.log_loss <= binned_fit.log_loss + 1e-12
    assert mle_fit.log_loss <= truth.log_loss + 1e-12


def test_log_likelihood_gradient_matches_finite_differences(synthetic):
    a, t, y = (v[:5000] for v in synthetic)
    k = 180.0 / math.pi
    c = np.array([0.4, 0.03, -0.14])
    _, g = neg_log_likelihood(c, a * k, t * k, y.astype(float))
    for j in range(3):
        h = 1e-7 * max(1.0, abs(c[j]))
        e = np.zeros(3)
        e[j] = h
        fd = (
            neg_log_likelihood(c + e, a * k, t * k, y.astype(float))[0]
            - neg_log_likelihood(c - e, a * k, t * k, y.astype(float))[0]
        ) / (2 * h)
        assert g[j] == pytest.approx(fd, rel=1e-6, abs=1e-9)


def test_radian_fit_is_the_same_model(synthetic):
    a, t, y = (v[:50_000] for v in synthetic)
    deg = fit_binned(Samples(a, t, y))
    rad = fit_binned(Samples(a, t, y), FitSettings(angle_unit="rad"))
    assert rad.model.angle_unit == "rad"
    assert rad.model.in_unit("deg").constants == pytest.approx(deg.model.constants, rel=1e-5)


def test_bootstrap_intervals(synthetic):
    a, t, y = (v[:30_000] for v in synthetic)
    r = fit_binned(Samples(a, t, y), FitSettings(ci="bootstrap", n_bootstrap=20, seed=1))
    assert r.ci_method == "bootstrap"
    for c in r.intervals:
        assert c.low <= c.high and c.std_err > 0


def test_fit_observations_holds_out_whole_localizations_and_evaluates():
    obs = simulate_observations(TRUE, 60_000, np.random.default_rng(5))
    held = holdout_split(obs.frame_groups(), 0.25, seed=3)
    groups = obs.frame_groups()
    assert not set(groups[held]) & set(groups[~held])
    r = fit_observations(obs, FitSettings(method="binned", holdout_fraction=0.25, seed=3))
    assert r.holdout is not None and r.n + r.holdout.n == len(obs)
    assert r.holdout.r2 > 0.5
    for row in r.holdout.calibration:
        if row.n >= 200:
            assert abs(row.observed - row.mean_predicted) < 4 * row.std_err + 0.01
    d = r.to_dict()
    assert d["holdout"]["n"] == r.holdout.n and set(d["intervals"]) == {"c1", "c2", "c3"}


def test_calibration_table_and_log_loss_edges():
    p = np.array([0.0, 0.05, 0.15, 1.0])
    y = np.array([0, 0, 1, 1])
    rows = calibration_table(p, y, 10)
    assert [r.n for r in rows] == [2, 1, 1]  # p = 1 falls in the last bin
    ev = evaluate(TRUE, Samples([0.1, 0.2], [0.1, 0.2], [0, 1]))
    assert math.isfinite(ev.log_loss) and ev.log_loss < -math.log(PROB_EPS)


@pytest.mark.parametrize("labels, match", [(0, "all .* outliers"), (1, "all .* inliers")])
def test_single_label_data_is_refused(labels, match):
    a, t = sample_angles(1000, np.random.default_rng(0))
    y = np.full(1000, labels)
    with pytest.raises(FitError, match=match):
        fit_binned(Samples(a, t, y, source="run.csv"))
    with pytest.raises(FitError, match=match):
        fit_mle(Samples(a, t, y))


def test_bad_inputs_are_refused():
    a, t = sample_angles(1000, np.random.default_rng(0))
    y = simulate_labels(TRUE, a, t, np.random.default_rng(1))
    with pytest.raises(FitError, match="no observations"):
        Samples([], [], [])
    a_nan = a.copy()
    a_nan[17] = np.nan
    with pytest.raises(FitError, match="row 17"):
        Samples(a_nan, t, y)
    with pytest.raises(FitError, match="lengths"):
        Samples(a[:10], t, y)
    with pytest.raises(FitError, match="0/1"):
        Samples(a, t, y * 2)
    with pytest.raises(FitError, match="bins"):
        fit_binned(Samples(a[:50], t[:50], y[:50]), FitSettings(min_bin_count=10))
    with pytest.raises(FitError, match="negative"):
        Samples(-a, t, y)


def test_fit_warns_when_the_fitted_surface_is_cut_inside_the_data_range():
    narrow = PerceptionModel(0.5, 0.05, -0.1)  # cos(c2 theta) reaches 0 at 31 deg < 50 deg of data
    rng = np.random.default_rng(4)
    a, t = sample_angles(40_000, rng)
    y = simulate_labels(narrow, a, t, rng)
    for fitter in (fit_binned, fit_mle):
        with pytest.warns(PerceptionModelWarning, match=r"synthetic\.csv: fitted model: cos\(c2\*theta\) reaches 0"):
            r = fitter(Samples(a, t, y, source="synthetic.csv"))
        assert r.model.c2 == pytest.approx(0.05, rel=0.05)
