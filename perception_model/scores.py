"""How well a model explains labelled angles: log-loss, Brier score, binned R^2 and a calibration table.

:func:`evaluate` judges a model on :class:`~perception_model.samples.Samples` (the held-out part of a fit, or
``perception-model evaluate``) with the bins and calibration of a
:class:`~perception_model.settings.FitSettings`; the scores are also the fits' own. See
``docs/perception_model.md`` ("Model and fit").
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .binning import bin_observations
from .fit_result import BinnedFrequencies, CalibrationBin, Evaluation
from .model import PerceptionModel
from .samples import Samples
from .settings import DEFAULT_SETTINGS, FitSettings

#: Probabilities are clipped to [PROB_EPS, 1 - PROB_EPS] in log-likelihoods and log-loss.
PROB_EPS = 1e-6


def weighted_r2(freq: NDArray[np.float64], pred: NDArray[np.float64], weight: NDArray[Any]) -> float:
    """``1 - sum w (f - p)^2 / sum w (f - mean_w f)^2`` (NaN if the frequencies are constant)."""
    mean = np.sum(weight * freq) / np.sum(weight)
    ss_tot = float(np.sum(weight * (freq - mean) ** 2))
    ss_res = float(np.sum(weight * (freq - pred) ** 2))
    return 1.0 - ss_res / ss_tot if ss_tot > 0 else math.nan


def log_loss(p: ArrayLike, y: ArrayLike) -> float:
    """Mean negative Bernoulli log-likelihood, probabilities clipped to ``[PROB_EPS, 1 - PROB_EPS]``."""
    pc = np.clip(np.asarray(p, dtype=np.float64), PROB_EPS, 1.0 - PROB_EPS)
    yy = np.asarray(y, dtype=np.float64)
    return float(-np.mean(yy * np.log(pc) + (1.0 - yy) * np.log1p(-pc)))


def calibration_table(p: ArrayLike, y: ArrayLike, n_bins: int) -> tuple[CalibrationBin, ...]:
    """Predicted-probability bins (``n_bins`` of equal width on [0, 1]) vs observed inlier frequency; empty bins
    omitted."""
    pp = np.asarray(p, dtype=np.float64).reshape(-1)
    yy = np.asarray(y, dtype=np.float64).reshape(-1)
    edges = np.linspace(0.0, 1.0, n_bins + 1)
    idx = np.clip(np.searchsorted(edges, pp, side="right") - 1, 0, n_bins - 1)
    rows = []
    for k in range(n_bins):
        m = idx == k
        n = int(m.sum())
        if n == 0:
            continue
        f = float(yy[m].mean())
        rows.append(
            CalibrationBin(
                float(edges[k]), float(edges[k + 1]), n, float(pp[m].mean()), f, math.sqrt(f * (1.0 - f) / n)
            )
        )
    return tuple(rows)


def binned_r2(model: PerceptionModel, binned: BinnedFrequencies) -> float:
    """The count-weighted R^2 of ``model`` against the bin frequencies (NaN with fewer than two used bins)."""
    if binned.count.size < 2:
        return math.nan
    return weighted_r2(binned.frequency, model.probability(binned.alpha, binned.theta), binned.count)


def evaluate(model: PerceptionModel, samples: Samples, settings: FitSettings = DEFAULT_SETTINGS) -> Evaluation:
    """Log-loss, Brier score, binned R^2 (``settings.bins``) and calibration (``settings.calibration_bins``) of
    ``model`` on checked samples."""
    p = model.probability(samples.alpha, samples.theta)
    y = samples.inlier
    binned = bin_observations(samples, settings.bins)
    return Evaluation(
        n=len(samples),
        n_inliers=samples.n_inliers,
        log_loss=log_loss(p, y),
        brier=float(np.mean((p - y) ** 2)),
        r2=binned_r2(model, binned),
        n_bins=int(binned.count.size),
        calibration=calibration_table(p, y, settings.calibration_bins),
    )


__all__ = ["PROB_EPS", "binned_r2", "calibration_table", "evaluate", "log_loss", "weighted_r2"]
