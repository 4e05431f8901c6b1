"""Fitting the perception model to inlier labels, and judging a model on held-out data: the public face.

Two estimators of ``c = (c1, c2, c3)`` (constants in the model's angle unit, inputs in radians), both taking
checked :class:`~perception_model.samples.Samples` and a :class:`~perception_model.settings.FitSettings` and
returning a :class:`~perception_model.fit_result.FitResult`: :func:`fit_binned` (the thesis protocol,
:mod:`perception_model.least_squares`) and :func:`fit_mle` (:mod:`perception_model.likelihood`);
:func:`evaluate` judges a model on samples (:mod:`perception_model.scores`). :func:`fit_observations` splits a
landmarks file's observations by localization (so the landmarks of one keyframe never straddle the split), runs
the estimator of the settings and evaluates on the held-out part. See ``docs/perception_model.md``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .binning import BinAccumulator, bin_observations
from .fit_core import initial_constants
from .fit_result import (
    C1_MAX,
    CONSTANT_NAMES,
    MAX_IDENTIFIABLE_EFFECT,
    BinnedFrequencies,
    CalibrationBin,
    ConstantInterval,
    Evaluation,
    FitResult,
)
from .landmarks_file import Observations
from .least_squares import MIN_FIT_BINS, Chunks, fit_binned, fit_binned_stream
from .likelihood import fisher_information, fit_mle, neg_log_likelihood
from .model import PerceptionModel
from .samples import Samples
from .scores import PROB_EPS, calibration_table, evaluate, log_loss, weighted_r2
from .settings import DEFAULT_SETTINGS, BinSpec, FitSettings, check_holdout_fraction


def holdout_split(groups: NDArray[np.int64], fraction: float, seed: int) -> NDArray[np.bool_]:
    """Boolean mask of held-out rows: a random ``fraction`` of the groups (localizations)."""
    check_holdout_fraction(fraction)
    uniq = np.unique(groups)
    if fraction == 0.0:
        return np.zeros(groups.shape, dtype=bool)
    rng = np.random.default_rng(seed)
    n_hold = int(round(fraction * uniq.size))
    if uniq.size < 2 or n_hold == 0:
        # one localization only: split rows instead of groups
        return rng.random(groups.shape) < fraction
    held = rng.choice(uniq, size=n_hold, replace=False)
    return np.isin(groups, held)


def fit_observations(obs: Observations, settings: FitSettings = DEFAULT_SETTINGS) -> FitResult:
    """Fit on a random ``1 - settings.holdout_fraction`` of the localizations, evaluate on the rest.

    The data are checked once, on the whole set (clearer messages); the training part is only checked for
    holding both labels. A fit the data cannot identify is refused (``FitResult.check_identified``).
    """
    samples = obs.samples().require_both_labels()
    held = holdout_split(obs.frame_groups(), settings.holdout_fraction, settings.seed)
    train = samples.take(~held) if held.any() else samples
    fit = fit_binned if settings.method == "binned" else fit_mle
    result = fit(train, settings)
    del train
    holdout = evaluate(result.model, samples.take(held), settings) if held.any() else None
    extra = dict(result.extra, holdout_fraction=settings.holdout_fraction, seed=settings.seed)
    return FitResult(**{**vars(result), "holdout": holdout, "extra": extra}).check_identified(samples.source)


def simulate_labels(
    model: PerceptionModel, alpha: ArrayLike, theta: ArrayLike, rng: np.random.Generator
) -> NDArray[np.bool_]:
    """Bernoulli inlier labels drawn from ``model`` at the given angles (radians)."""
    p = model.probability(alpha, theta)
    return rng.random(p.shape) < p


__all__ = [
    "C1_MAX",
    "CONSTANT_NAMES",
    "MAX_IDENTIFIABLE_EFFECT",
    "MIN_FIT_BINS",
    "PROB_EPS",
    "BinAccumulator",
    "BinSpec",
    "BinnedFrequencies",
    "CalibrationBin",
    "Chunks",
    "ConstantInterval",
    "Evaluation",
    "FitResult",
    "FitSettings",
    "Samples",
    "bin_observations",
    "calibration_table",
    "evaluate",
    "fisher_information",
    "fit_binned",
    "fit_binned_stream",
    "fit_mle",
    "fit_observations",
    "holdout_split",
    "initial_constants",
    "log_loss",
    "neg_log_likelihood",
    "simulate_labels",
    "weighted_r2",
]
