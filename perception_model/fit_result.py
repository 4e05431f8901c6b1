"""What a fit returns: the records of its result, its held-out evaluation and its binned frequencies.

:class:`FitResult` (model, intervals, covariance, R^2, log-loss, counts, the binned data, the held-out
:class:`Evaluation`) with its JSON form for the model file's ``fit`` section and the identifiability check
that refuses a degenerate fit; :class:`ConstantInterval`, :class:`CalibrationBin`, :class:`BinnedFrequencies`.
See ``docs/perception_model.md`` ("Model and fit").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import FitError
from .model import PerceptionModel
from .settings import UNIT_SCALE

#: Upper bound on c1 during fits: p = c1 cos(c2 theta) exp(c3 alpha) is a probability, and its
#: value at alpha = theta = 0 is c1 (its largest value when c3 <= 0).
C1_MAX = 1.0
CONSTANT_NAMES = ("c1", "c2", "c3")


# --------------------------------------------------------------------------- result types
@dataclass(frozen=True)
class ConstantInterval:
    """Estimate and confidence interval of one constant (model angle unit)."""

    name: str
    estimate: float
    low: float
    high: float
    std_err: float

    def contains(self, value: float) -> bool:
        """True if ``low <= value <= high``."""
        return self.low <= value <= self.high


@dataclass(frozen=True)
class CalibrationBin:
    """One row of a calibration table: predictions in ``[p_low, p_high)`` vs observed frequency."""

    p_low: float
    p_high: float
    n: int
    mean_predicted: float
    observed: float
    std_err: float


@dataclass(frozen=True)
class BinnedFrequencies:
    """Inlier frequency per (alpha, theta) bin (radians).

    Flat arrays hold the used bins (count >= ``min_count``): mean angles, counts, inliers,
    frequencies. Grid arrays ``(n_alpha_bins, n_theta_bins)`` hold all bins, for heatmaps.
    """

    alpha: NDArray[np.float64]
    theta: NDArray[np.float64]
    count: NDArray[np.int64]
    inliers: NDArray[np.int64]
    alpha_edges: NDArray[np.float64]
    theta_edges: NDArray[np.float64]
    count_grid: NDArray[np.int64]
    inlier_grid: NDArray[np.int64]

    @property
    def frequency(self) -> NDArray[np.float64]:
        """Normalized inlier frequency of the used bins."""
        return self.inliers / self.count

    @property
    def frequency_grid(self) -> NDArray[np.float64]:
        """Frequency per grid cell, NaN for empty cells."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.count_grid > 0, self.inlier_grid / self.count_grid, np.nan)


@dataclass(frozen=True)
class Evaluation:
    """Quality of a model on a set of observations."""

    n: int
    n_inliers: int
    log_loss: float
    brier: float
    r2: float
    n_bins: int
    calibration: tuple[CalibrationBin, ...]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "n": self.n,
            "n_inliers": self.n_inliers,
            "log_loss": self.log_loss,
            "brier": self.brier,
            # None (JSON null) when no held-out bin holds enough observations: NaN is not JSON
            "r2_binned": self.r2 if math.isfinite(self.r2) else None,
            "n_bins": self.n_bins,
            "calibration": [vars(c) for c in self.calibration],
        }


#: A constant is unidentifiable from the data when one standard error of it changes the model, over the data's angle
#: range, by more than this: c1 by this much (the probability scale), c2 theta_max by this many radians of the
#: cosine's argument, c3 alpha_max by this much of the exponent (a factor e). The data then cannot tell its value.
MAX_IDENTIFIABLE_EFFECT = 1.0


@dataclass(frozen=True)
class FitResult:
    """Outcome of a fit: model, intervals (model unit), quality on training and held-out data."""

    model: PerceptionModel
    method: str
    n: int
    n_inliers: int
    intervals: tuple[ConstantInterval, ...]
    covariance: NDArray[np.float64]
    confidence: float
    ci_method: str
    r2: float
    log_loss: float
    n_bins: int
    binned: BinnedFrequencies
    converged: bool
    message: str
    holdout: Evaluation | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    c1_at_bound: bool = False

    def effect_of_one_std_err(self) -> dict[str, float]:
        """How much one standard error of each constant changes the model over the data's angle range (see
        :data:`MAX_IDENTIFIABLE_EFFECT`); NaN when the fit gave no standard error."""
        k = UNIT_SCALE[self.model.angle_unit]
        scale = {"c1": 1.0, "c2": self.model.theta_max * k, "c3": self.model.alpha_max * k}
        return {c.name: c.std_err * scale[c.name] if math.isfinite(c.std_err) else math.nan for c in self.intervals}

    @property
    def unidentifiable(self) -> tuple[str, ...]:
        """The constants these data cannot determine (no finite standard error, or one standard error changes the
        model by more than :data:`MAX_IDENTIFIABLE_EFFECT` over the data's angle range)."""
        return tuple(
            name
            for name, e in self.effect_of_one_std_err().items()
            if not math.isfinite(e) or e > MAX_IDENTIFIABLE_EFFECT
        )

    def check_identified(self, source: str) -> FitResult:
        """This result, or ``FitError`` naming every constant the data cannot determine (a degenerate fit is not a
        result: ``c2 = +7.7e-16`` with a 95 % interval of +-4.7e10 was once printed as one)."""
        bad = self.unidentifiable
        if not bad:
            return self
        effect = self.effect_of_one_std_err()
        by = {c.name: c for c in self.intervals}
        angles = (
            f"parallax up to {math.degrees(self.model.alpha_max):.3g} deg, view up to "
            f"{math.degrees(self.model.theta_max):.3g} deg"
        )
        if not all(math.isfinite(effect[n]) for n in bad):
            why = f"the fit's matrix is singular: no standard errors; {angles}"
        else:
            why = "; ".join(f"{n} = {by[n].estimate:+.3g}, standard error {by[n].std_err:.2g}" for n in bad) + (
                f": one standard error changes the model by more than {MAX_IDENTIFIABLE_EFFECT:g} over the data's "
                f"angles, {angles}"
            )
        raise FitError(
            f"{source}: the data cannot identify {', '.join(bad)} ({why}): not a result; collect "
            "observations over a wider range of angles"
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary for the model file's ``fit`` section."""
        out: dict[str, Any] = {
            "method": self.method,
            "angle_unit": self.model.angle_unit,
            "n": self.n,
            "n_inliers": self.n_inliers,
            "confidence": self.confidence,
            "ci_method": self.ci_method,
            "intervals": {
                c.name: {"estimate": c.estimate, "low": c.low, "high": c.high, "std_err": c.std_err}
                for c in self.intervals
            },
            "covariance": self.covariance.tolist(),
            "r2_binned": self.r2,
            "log_loss": self.log_loss,
            "n_bins": self.n_bins,
            "converged": self.converged,
            "message": self.message,
            "c1_max": C1_MAX,
            "c1_at_bound": self.c1_at_bound,
            "holdout": None if self.holdout is None else self.holdout.to_dict(),
        }
        out.update(self.extra)
        return out


__all__ = [
    "C1_MAX",
    "CONSTANT_NAMES",
    "MAX_IDENTIFIABLE_EFFECT",
    "BinnedFrequencies",
    "CalibrationBin",
    "ConstantInterval",
    "Evaluation",
    "FitResult",
]
