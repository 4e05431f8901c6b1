"""The streamed binned fit (chunk by chunk, memory per bin) equals ``fit_binned`` on all data at once."""

from __future__ import annotations

import math

import numpy as np
import pytest

from perception_model.errors import FitError
from perception_model.fit import (
    BinAccumulator,
    BinSpec,
    Samples,
    bin_observations,
    fit_binned,
    fit_binned_stream,
    simulate_labels,
)
from perception_model.model import THESIS_CONSTANTS_DEG, PerceptionModel


@pytest.fixture(scope="module")
def data():
    rng = np.random.default_rng(3)
    n = 60_000
    alpha = rng.uniform(0, math.radians(12), n)
    theta = rng.uniform(0, math.radians(40), n)
    y = simulate_labels(PerceptionModel(*THESIS_CONSTANTS_DEG, "deg"), alpha, theta, rng)
    return alpha, theta, y


def test_streamed_fit_equals_the_fit_of_everything(data):
    alpha, theta, y = data
    cuts = [0, 7_000, 31_000, len(alpha)]

    def chunks():
        return (Samples(alpha[a:b], theta[a:b], y[a:b]) for a, b in zip(cuts[:-1], cuts[1:], strict=True))

    whole = fit_binned(Samples(alpha, theta, y))
    streamed = fit_binned_stream(chunks, source="3 chunks")
    assert np.allclose(streamed.model.constants, whole.model.constants, rtol=1e-7, atol=1e-10)
    assert np.allclose(streamed.covariance, whole.covariance, rtol=1e-5, atol=1e-14)
    assert streamed.n == whole.n and streamed.n_inliers == whole.n_inliers and streamed.n_bins == whole.n_bins
    assert streamed.r2 == pytest.approx(whole.r2, rel=1e-9)
    assert streamed.log_loss == pytest.approx(whole.log_loss, rel=1e-9)
    assert (streamed.model.alpha_max, streamed.model.theta_max) == (whole.model.alpha_max, whole.model.theta_max)


def test_accumulator_bins_like_bin_observations(data):
    alpha, theta, y = data
    acc = BinAccumulator(BinSpec())
    acc.add(Samples(alpha[:100], theta[:100], y[:100]))  # a small first chunk: the grid grows afterwards
    acc.add(Samples(alpha[100:], theta[100:], y[100:]))
    got, want = acc.binned(), bin_observations(Samples(alpha, theta, y), BinSpec())
    assert np.array_equal(got.count_grid, want.count_grid) and np.array_equal(got.inlier_grid, want.inlier_grid)
    assert np.allclose(got.alpha, want.alpha) and np.allclose(got.theta, want.theta)


def test_streamed_fit_rejects_empty_or_one_label(data):
    with pytest.raises(FitError, match="no observations"):
        fit_binned_stream(lambda: [], source="none")
    alpha, theta, _ = data
    with pytest.raises(FitError, match="same inlier label"):
        fit_binned_stream(lambda: [Samples(alpha, theta, np.ones(len(alpha), bool))], source="ones")
