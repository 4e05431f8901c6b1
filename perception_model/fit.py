"""Fitting the perception model to inlier labels, and judging a model on held-out data.

Two estimators of ``c = (c1, c2, c3)`` (constants in the model's angle unit, inputs in radians):

- ``fit_binned`` - the thesis protocol (§7.3.1): group observations into (alpha, theta) bins,
  take the normalized inlier frequency of each bin, and fit the model by weighted nonlinear least
  squares (``scipy.optimize.least_squares``, weights = bin counts, the model evaluated at each
  bin's mean angles). Reports the count-weighted R^2 over bins. Confidence intervals from the
  heteroscedasticity-robust (sandwich) covariance of the weighted least-squares estimate, or
  from a bootstrap over observations (``ci="bootstrap"``).
- ``fit_mle`` - per-observation Bernoulli maximum likelihood (``scipy.optimize.minimize``,
  L-BFGS-B with the analytic gradient of the log-likelihood). Probabilities are clipped to
  ``[PROB_EPS, 1 - PROB_EPS]`` inside the logarithms; the gradient is zero where clipped.
  Confidence intervals from the expected Fisher information ``sum J J^T / (p (1 - p))``.

Both return a ``FitResult`` with the model, intervals, R^2, log-loss and counts, and optionally an
``Evaluation`` on held-out observations (log-loss, Brier score, R^2, calibration table).
``fit_observations`` splits by localization (so landmarks of one keyframe never straddle the
split) and runs either estimator.

Sign convention: ``cos`` is even, so only ``|c2|`` is identifiable; fits constrain ``c2 >= 0``.
The model is a probability, so both fits constrain ``0 < c1 <= 1`` (bounded ``least_squares`` /
L-BFGS-B). When the data would push ``c1`` above 1 the fit stops at ``c1 = 1`` and says so:
``FitResult.c1_at_bound`` (also ``c1_at_bound`` in the model file's ``fit`` section); the c1
interval is then cut at 1. Bad input (empty, NaN angles, all labels equal, too few bins) raises
``FitError`` naming the data source; the data are checked once per fit. The settings of a fit (bins,
hold-out, intervals) and their defaults are one record, ``perception_model.settings.FitSettings``, checked
when it is built.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import optimize, special

from .errors import FitError, PerceptionModelError, PerceptionModelWarning
from .landmarks_file import Observations
from .model import DEFAULT_ALPHA_MAX_RAD, DEFAULT_THETA_MAX_RAD, THESIS_CONSTANTS_DEG, PerceptionModel
from .settings import (
    UNIT_SCALE,
    BinSpec,
    CiMethod,
    FitSettings,
    check_angle_unit,
    check_bootstrap,
    check_ci,
    check_holdout_fraction,
)

#: Probabilities are clipped to [PROB_EPS, 1 - PROB_EPS] in log-likelihoods and log-loss.
PROB_EPS = 1e-6
#: The defaults of every setting (bins, hold-out, intervals, calibration): ``perception_model.settings``.
_DEFAULT = FitSettings()
#: A binned fit needs at least this many usable bins (3 constants + residual freedom).
MIN_FIT_BINS = 6
#: Optimizer tolerances.
LSQ_TOL = 1e-12
MLE_FTOL = 1e-15
MLE_GTOL = 1e-10
MLE_MAXITER = 2000
#: Lower bound on c1 during fits (the model requires c1 > 0).
C1_FLOOR = 1e-9
#: Upper bound on c1 during fits: p = c1 cos(c2 theta) exp(c3 alpha) is a probability, and its
#: value at alpha = theta = 0 is c1 (its largest value when c3 <= 0).
C1_MAX = 1.0
#: c1 within this relative distance of C1_MAX counts as at the bound (and is set to C1_MAX).
C1_BOUND_RTOL = 1e-6
#: Observations per chunk when evaluating the likelihood (bounds the temporaries on large data).
MLE_CHUNK = 1 << 20
#: An MLE counts as converged when the remaining Fisher-scoring step is below this many standard errors.
MLE_STEP_TOL = 1e-3

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
        return tuple(name for name, e in self.effect_of_one_std_err().items()
                     if not math.isfinite(e) or e > MAX_IDENTIFIABLE_EFFECT)

    def check_identified(self, source: str) -> FitResult:
        """This result, or ``FitError`` naming every constant the data cannot determine (a degenerate fit is not a
        result: ``c2 = +7.7e-16`` with a 95 % interval of +-4.7e10 was once printed as one)."""
        bad = self.unidentifiable
        if not bad:
            return self
        effect = self.effect_of_one_std_err()
        by = {c.name: c for c in self.intervals}
        angles = (f"parallax up to {math.degrees(self.model.alpha_max):.3g} deg, view up to "
                  f"{math.degrees(self.model.theta_max):.3g} deg")
        if not all(math.isfinite(effect[n]) for n in bad):
            why = f"the fit's matrix is singular: no standard errors; {angles}"
        else:
            why = "; ".join(f"{n} = {by[n].estimate:+.3g}, standard error {by[n].std_err:.2g}" for n in bad) + (
                f": one standard error changes the model by more than {MAX_IDENTIFIABLE_EFFECT:g} over the data's "
                f"angles, {angles}")
        raise FitError(f"{source}: the data cannot identify {', '.join(bad)} ({why}): not a result; collect "
                       "observations over a wider range of angles")

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


# --------------------------------------------------------------------------- helpers
def _check_data(
    alpha: ArrayLike, theta: ArrayLike, inlier: ArrayLike, source: str, *, need_both: bool = True
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    a = np.asarray(alpha, dtype=np.float64).reshape(-1)
    t = np.asarray(theta, dtype=np.float64).reshape(-1)
    y = np.asarray(inlier).reshape(-1)
    if not (a.shape == t.shape == y.shape):
        raise FitError(f"{source}: alpha, theta and inlier lengths differ ({a.size}, {t.size}, {y.size})")
    if a.size == 0:
        raise FitError(f"{source}: no observations")
    bad = ~(np.isfinite(a) & np.isfinite(t))
    if bad.any():
        first = int(np.argmax(bad))
        raise FitError(
            f"{source}: {int(bad.sum())} observation(s) with NaN/inf angles (first at row {first})"
        )
    if (a < 0).any() or (t < 0).any():
        raise FitError(f"{source}: negative angles (parallax/view angles are in [0, pi])")
    yf = y.astype(np.float64)
    if y.dtype != np.bool_ and not np.isin(yf, (0.0, 1.0)).all():
        raise FitError(f"{source}: inlier labels must be 0/1")
    if need_both:
        _check_both_labels(yf, source)
    return a, t, yf


def _check_both_labels(y: NDArray[np.float64], source: str) -> None:
    k = int(y.sum())
    if k == 0:
        raise FitError(f"{source}: all {y.size} observations are outliers (inlier = 0); nothing to fit")
    if k == y.size:
        raise FitError(f"{source}: all {y.size} observations are inliers (inlier = 1); nothing to fit")


def _snap_c1(c: NDArray[np.float64], active: bool = False) -> tuple[NDArray[np.float64], bool]:
    """``(c, at_bound)``: c1 set to ``C1_MAX`` when the optimizer left it at (or reports it on) the bound."""
    at_bound = bool(active or c[0] >= C1_MAX * (1.0 - C1_BOUND_RTOL))
    if at_bound:
        c = c.copy()
        c[0] = C1_MAX
    return c, at_bound


def _unit_constants(c: NDArray[np.float64]) -> tuple[float, float, float]:
    return float(c[0]), float(c[1]), float(c[2])


def _prob_and_jac(
    c: NDArray[np.float64], a_u: NDArray[np.float64], t_u: NDArray[np.float64], lo: float, hi: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Clipped probability and its Jacobian ``(n, 3)`` w.r.t. c, for angles in the model unit.

    Clipped to ``[lo, hi]``; ``p = lo`` beyond the cosine's first zero. Jacobian zero where clipped.
    """
    c1, c2, c3 = _unit_constants(c)
    e = np.exp(c3 * a_u)
    arg = c2 * t_u
    cs = np.cos(arg)
    raw = c1 * cs * e
    cut = np.abs(arg) > 0.5 * math.pi
    inside = ~cut & (raw > lo) & (raw < hi)
    p = np.where(cut, lo, np.clip(raw, lo, hi))
    jac = np.stack([cs * e, -c1 * t_u * np.sin(arg) * e, a_u * raw], axis=-1)
    jac *= inside[:, None]
    return p, jac


def _intervals(
    est: NDArray[np.float64], cov: NDArray[np.float64], confidence: float
) -> tuple[ConstantInterval, ...]:
    """Wald intervals; c1's upper end is cut at ``C1_MAX`` (the constraint of the fit)."""
    z = float(special.ndtri(0.5 + 0.5 * confidence))
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None)) if np.all(np.isfinite(cov)) else np.full(3, np.nan)
    high = est + z * se
    high[0] = min(high[0], C1_MAX)
    return tuple(
        ConstantInterval(name, float(e), float(e - z * s), float(h), float(s))
        for name, e, s, h in zip(CONSTANT_NAMES, est, se, high, strict=True)
    )


def _safe_inverse(m: NDArray[np.float64], what: str) -> NDArray[np.float64]:
    try:
        inv: NDArray[Any] = np.linalg.inv(m)
    except np.linalg.LinAlgError:
        inv = np.full_like(m, np.nan)
    if not np.all(np.isfinite(inv)) or np.any(np.diag(inv) < 0):
        warnings.warn(
            f"{what} is singular; confidence intervals are not available",
            PerceptionModelWarning,
            stacklevel=3,
        )
        return np.full_like(m, np.nan)
    return inv


def initial_constants(angle_unit: str) -> NDArray[np.float64]:
    """Starting point of fits: the thesis constants expressed in ``angle_unit``."""
    f = UNIT_SCALE["deg"] / UNIT_SCALE[angle_unit]
    c1, c2, c3 = THESIS_CONSTANTS_DEG
    return np.array([c1, c2 * f, c3 * f])


def _make_model(
    c: NDArray[np.float64],
    angle_unit: str,
    a: NDArray[np.float64],
    t: NDArray[np.float64],
    source: str,
    converged: bool,
    message: str,
) -> PerceptionModel:
    """Model with the fitted constants, documented for the angle range of the data.

    Warns (``PerceptionModelWarning``) when the optimizer did not converge or the fitted surface
    leaves [0, 1] inside the data range.
    """
    alpha_max = float(min(math.pi, a.max())) if a.max() > 0 else DEFAULT_ALPHA_MAX_RAD
    theta_max = float(min(math.pi, t.max())) if t.max() > 0 else DEFAULT_THETA_MAX_RAD
    try:
        model = PerceptionModel(float(c[0]), float(abs(c[1])), float(c[2]), angle_unit, alpha_max, theta_max)
    except PerceptionModelError as err:
        raise FitError(f"{source}: the fit gave unusable constants {c.tolist()} ({err})") from None
    if not converged:
        warnings.warn(
            f"{source}: the optimizer did not converge ({message})", PerceptionModelWarning, stacklevel=3
        )
    for problem in model.range_problems():
        warnings.warn(f"{source}: fitted model: {problem}", PerceptionModelWarning, stacklevel=3)
    return model


# --------------------------------------------------------------------------- binning and scores
def bin_observations(
    alpha: ArrayLike, theta: ArrayLike, inlier: ArrayLike, spec: BinSpec | None = None
) -> BinnedFrequencies:
    """Group observations (radians) on a regular grid starting at 0; mean angles per bin."""
    spec = spec or BinSpec()
    a = np.asarray(alpha, dtype=np.float64).reshape(-1)
    t = np.asarray(theta, dtype=np.float64).reshape(-1)
    y = np.asarray(inlier, dtype=np.float64).reshape(-1)
    na = max(1, int(np.floor(a.max() / spec.alpha_width)) + 1) if a.size else 1
    nt = max(1, int(np.floor(t.max() / spec.theta_width)) + 1) if t.size else 1
    ia = np.minimum((a / spec.alpha_width).astype(np.int64), na - 1)
    it = np.minimum((t / spec.theta_width).astype(np.int64), nt - 1)
    flat = ia * nt + it
    size = na * nt
    count = np.bincount(flat, minlength=size)
    inl = np.bincount(flat, weights=y, minlength=size).round().astype(np.int64)
    sum_a = np.bincount(flat, weights=a, minlength=size)
    sum_t = np.bincount(flat, weights=t, minlength=size)
    used = count >= spec.min_count
    return BinnedFrequencies(
        alpha=sum_a[used] / count[used],
        theta=sum_t[used] / count[used],
        count=count[used].astype(np.int64),
        inliers=inl[used],
        alpha_edges=np.arange(na + 1, dtype=np.float64) * spec.alpha_width,
        theta_edges=np.arange(nt + 1, dtype=np.float64) * spec.theta_width,
        count_grid=count.reshape(na, nt).astype(np.int64),
        inlier_grid=inl.reshape(na, nt),
    )


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


def calibration_table(
    p: ArrayLike, y: ArrayLike, n_bins: int = _DEFAULT.calibration_bins
) -> tuple[CalibrationBin, ...]:
    """Predicted-probability bins (equal width on [0, 1]) vs observed inlier frequency; empty bins omitted."""
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


def evaluate(
    model: PerceptionModel,
    alpha: ArrayLike,
    theta: ArrayLike,
    inlier: ArrayLike,
    *,
    bins: BinSpec | None = None,
    calibration_bins: int = _DEFAULT.calibration_bins,
    source: str = "<data>",
) -> Evaluation:
    """Log-loss, Brier score, binned R^2 and calibration of ``model`` on observations (radians)."""
    a, t, y = _check_data(alpha, theta, inlier, source, need_both=False)
    return _evaluate(model, a, t, y, bins=bins, calibration_bins=calibration_bins)


def _evaluate(
    model: PerceptionModel,
    a: NDArray[np.float64],
    t: NDArray[np.float64],
    y: NDArray[np.float64],
    *,
    bins: BinSpec | None,
    calibration_bins: int,
) -> Evaluation:
    """``evaluate`` on checked data."""
    p = model.probability(a, t)
    binned = bin_observations(a, t, y, bins)
    r2 = math.nan
    if binned.count.size >= 2:
        r2 = weighted_r2(binned.frequency, model.probability(binned.alpha, binned.theta), binned.count)
    return Evaluation(
        n=int(a.size),
        n_inliers=int(y.sum()),
        log_loss=log_loss(p, y),
        brier=float(np.mean((p - y) ** 2)),
        r2=r2,
        n_bins=int(binned.count.size),
        calibration=calibration_table(p, y, calibration_bins),
    )


# --------------------------------------------------------------------------- binned least squares
def _lsq_binned(binned: BinnedFrequencies, k: float, x0: NDArray[np.float64]) -> optimize.OptimizeResult:
    a_u = binned.alpha * k
    t_u = binned.theta * k
    w = np.sqrt(binned.count.astype(np.float64))
    f = binned.frequency

    def resid(c: NDArray[np.float64]) -> NDArray[np.float64]:
        return w * (_prob_and_jac(c, a_u, t_u, 0.0, 1.0)[0] - f)

    def jac(c: NDArray[np.float64]) -> NDArray[np.float64]:
        return w[:, None] * _prob_and_jac(c, a_u, t_u, 0.0, 1.0)[1]

    lower = np.array([C1_FLOOR, 0.0, -np.inf])
    upper = np.array([C1_MAX, np.inf, np.inf])
    start = np.clip(x0, lower + 1e-12, upper)
    return optimize.least_squares(
        resid,
        start,
        jac=jac,
        bounds=(lower, upper),
        method="trf",
        x_scale="jac",
        ftol=LSQ_TOL,
        xtol=LSQ_TOL,
        gtol=LSQ_TOL,
    )


def fit_binned(
    alpha: ArrayLike,
    theta: ArrayLike,
    inlier: ArrayLike,
    *,
    angle_unit: str = "deg",
    bins: BinSpec | None = None,
    ci: CiMethod = "sandwich",
    n_bootstrap: int = _DEFAULT.n_bootstrap,
    confidence: float = _DEFAULT.confidence,
    seed: int = 0,
    initial: ArrayLike | None = None,
    source: str = "<data>",
) -> FitResult:
    """Thesis protocol: weighted least squares of the model to per-bin inlier frequencies.

    Angles in radians; constants returned for ``angle_unit``. ``ci="sandwich"`` uses the robust
    covariance ``B^-1 (sum n_b^2 e_b^2 J_b J_b^T) B^-1`` with ``B = sum n_b J_b J_b^T``;
    ``ci="bootstrap"`` resamples observations ``n_bootstrap`` times (percentile intervals).
    """
    a, t, y = _check_data(alpha, theta, inlier, source)
    check_angle_unit(angle_unit)
    check_ci(ci)
    if ci == "bootstrap":
        check_bootstrap(n_bootstrap)
    return _fit_binned(
        a, t, y, angle_unit=angle_unit, bins=bins, ci=ci, n_bootstrap=n_bootstrap, confidence=confidence,
        seed=seed, initial=initial, source=source,
    )  # fmt: skip


def _fit_binned(
    a: NDArray[np.float64],
    t: NDArray[np.float64],
    y: NDArray[np.float64],
    *,
    angle_unit: str,
    bins: BinSpec | None,
    ci: CiMethod,
    n_bootstrap: int,
    confidence: float,
    seed: int,
    initial: ArrayLike | None,
    source: str,
) -> FitResult:
    """``fit_binned`` on checked data (``_check_data``) and settings (``perception_model.settings``)."""
    spec = bins or BinSpec()
    k = UNIT_SCALE[angle_unit]
    binned = bin_observations(a, t, y, spec)
    if binned.count.size < MIN_FIT_BINS:
        raise FitError(
            f"{source}: only {binned.count.size} (alpha, theta) bins hold >= {spec.min_count} "
            f"observations; need {MIN_FIT_BINS} (collect more data or widen the bins)"
        )
    x0 = initial_constants(angle_unit) if initial is None else np.asarray(initial, dtype=np.float64)
    res = _lsq_binned(binned, k, x0)
    c, c1_at_bound = _snap_c1(res.x, bool(res.active_mask[0] == 1))
    p_bins, jac = _prob_and_jac(c, binned.alpha * k, binned.theta * k, 0.0, 1.0)
    n_b = binned.count.astype(np.float64)
    e_b = binned.frequency - p_bins
    if ci == "bootstrap":
        cov, intervals = _bootstrap(a, t, y, spec, k, c, n_bootstrap, confidence, seed)
    else:  # "sandwich"
        bread = _safe_inverse(jac.T @ (n_b[:, None] * jac), "the least-squares normal matrix")
        meat = (jac * ((n_b * e_b) ** 2)[:, None]).T @ jac
        cov = bread @ meat @ bread
        intervals = _intervals(c, cov, confidence)
    model = _make_model(c, angle_unit, a, t, source, bool(res.success), str(res.message))
    return FitResult(
        model=model,
        method="binned",
        n=int(a.size),
        n_inliers=int(y.sum()),
        intervals=intervals,
        covariance=cov,
        confidence=confidence,
        ci_method=ci,
        r2=weighted_r2(binned.frequency, p_bins, n_b),
        log_loss=log_loss(model.probability(a, t), y),
        n_bins=int(binned.count.size),
        binned=binned,
        converged=bool(res.success),
        message=str(res.message),
        extra={
            "bins": {
                "alpha_width": spec.alpha_width * k,
                "theta_width": spec.theta_width * k,
                "min_count": spec.min_count,
                "unit": angle_unit,
            }
        },
        c1_at_bound=c1_at_bound,
    )


def _bootstrap(
    a: NDArray[np.float64],
    t: NDArray[np.float64],
    y: NDArray[np.float64],
    spec: BinSpec,
    k: float,
    c: NDArray[np.float64],
    n_boot: int,
    confidence: float,
    seed: int,
) -> tuple[NDArray[np.float64], tuple[ConstantInterval, ...]]:
    rng = np.random.default_rng(seed)
    draws = []
    for _ in range(n_boot):
        idx = rng.integers(0, a.size, a.size)
        b = bin_observations(a[idx], t[idx], y[idx], spec)
        if b.count.size < MIN_FIT_BINS:
            continue
        draws.append(_snap_c1(_lsq_binned(b, k, c).x)[0])
    if len(draws) < 2:
        raise FitError("bootstrap failed: too few resamples had enough bins")
    d = np.array(draws)
    cov = np.cov(d, rowvar=False)
    lo_q, hi_q = 0.5 - 0.5 * confidence, 0.5 + 0.5 * confidence
    lo, hi = np.quantile(d, lo_q, axis=0), np.quantile(d, hi_q, axis=0)
    se = d.std(axis=0, ddof=1)
    intervals = tuple(
        ConstantInterval(n, float(e), float(low), float(high), float(s))
        for n, e, low, high, s in zip(CONSTANT_NAMES, c, lo, hi, se, strict=True)
    )
    return cov, intervals


# --------------------------------------------------------------------------- maximum likelihood
def neg_log_likelihood(
    c: ArrayLike, a_u: NDArray[np.float64], t_u: NDArray[np.float64], y: NDArray[np.float64]
) -> tuple[float, NDArray[np.float64]]:
    """Mean negative Bernoulli log-likelihood and its analytic gradient w.r.t. c (angles in model unit).

    Evaluated in chunks of ``MLE_CHUNK`` observations, so the temporaries stay small on large data.
    """
    cc = np.asarray(c, dtype=np.float64)
    n = y.size
    total = 0.0
    grad = np.zeros(3)
    for s in range(0, n, MLE_CHUNK):
        sl = slice(s, s + MLE_CHUNK)
        yy = y[sl]
        p, jac = _prob_and_jac(cc, a_u[sl], t_u[sl], PROB_EPS, 1.0 - PROB_EPS)
        total += float(np.sum(yy * np.log(p) + (1.0 - yy) * np.log1p(-p)))
        dl_dp = yy / p - (1.0 - yy) / (1.0 - p)
        grad -= dl_dp @ jac
    return -total / n, grad / n


def fisher_information(
    c: ArrayLike, a_u: NDArray[np.float64], t_u: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Expected Fisher information ``sum J J^T / (p (1 - p))`` of n Bernoulli observations (model unit)."""
    cc = np.asarray(c, dtype=np.float64)
    info = np.zeros((3, 3))
    for s in range(0, a_u.size, MLE_CHUNK):
        p, jac = _prob_and_jac(cc, a_u[s : s + MLE_CHUNK], t_u[s : s + MLE_CHUNK], PROB_EPS, 1.0 - PROB_EPS)
        w = 1.0 / (p * (1.0 - p))
        info += (jac * w[:, None]).T @ jac
    return info


def fit_mle(
    alpha: ArrayLike,
    theta: ArrayLike,
    inlier: ArrayLike,
    *,
    angle_unit: str = "deg",
    bins: BinSpec | None = None,
    confidence: float = _DEFAULT.confidence,
    initial: ArrayLike | None = None,
    source: str = "<data>",
) -> FitResult:
    """Per-observation Bernoulli maximum likelihood; intervals from the Fisher information.

    Starts from ``initial`` (default: a binned fit when enough bins exist, else the thesis
    constants). Angles in radians; constants returned for ``angle_unit``.
    """
    a, t, y = _check_data(alpha, theta, inlier, source)
    check_angle_unit(angle_unit)
    return _fit_mle(a, t, y, angle_unit=angle_unit, bins=bins, confidence=confidence, initial=initial, source=source)


def _fit_mle(
    a: NDArray[np.float64],
    t: NDArray[np.float64],
    y: NDArray[np.float64],
    *,
    angle_unit: str,
    bins: BinSpec | None,
    confidence: float,
    initial: ArrayLike | None,
    source: str,
) -> FitResult:
    """``fit_mle`` on checked data (``_check_data``) and settings (``perception_model.settings``)."""
    for name, values in (("parallax angle", a), ("view angle", t)):
        if np.ptp(values) == 0:
            raise FitError(f"{source}: every observation has the same {name} ({values[0]:.6g} rad); "
                           "the constants cannot be identified (collect data over a range of angles)")
    k = UNIT_SCALE[angle_unit]
    spec = bins or BinSpec()
    if initial is None:
        try:
            with warnings.catch_warnings():  # only a starting point: its warnings do not concern the MLE
                warnings.simplefilter("ignore", PerceptionModelWarning)
                x0 = _fit_binned(
                    a, t, y, angle_unit=angle_unit, bins=spec, ci="sandwich", n_bootstrap=_DEFAULT.n_bootstrap,
                    confidence=confidence, seed=0, initial=None, source=source,
                ).model.constants  # fmt: skip
        except FitError:
            x0 = initial_constants(angle_unit)
    else:
        x0 = np.asarray(initial, dtype=np.float64)
    a_u, t_u = a * k, t * k
    scale = np.where(np.abs(x0) > 0, np.abs(x0), 1.0)

    def fun(x: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
        v, g = neg_log_likelihood(x * scale, a_u, t_u, y)
        return v, g * scale

    bounds = [(C1_FLOOR / scale[0], C1_MAX / scale[0]), (0.0, None), (None, None)]
    x0 = np.asarray(x0, dtype=np.float64).copy()
    x0[0] = min(max(x0[0], C1_FLOOR), C1_MAX)
    res = optimize.minimize(
        fun,
        x0 / scale,
        jac=True,
        method="L-BFGS-B",
        bounds=bounds,
        options={"ftol": MLE_FTOL, "gtol": MLE_GTOL, "maxiter": MLE_MAXITER},
    )
    c, c1_at_bound = _snap_c1(res.x * scale)
    _, grad = neg_log_likelihood(c, a_u, t_u, y)
    info = fisher_information(c, a_u, t_u)
    cov = _safe_inverse(info, "the Fisher information")
    # converged: the optimizer's verdict, or the remaining Fisher-scoring step is negligible next to
    # the standard errors (L-BFGS-B may stop on its function tolerance when already at the optimum);
    # with c1 held at its bound only (c2, c3) are free
    free = slice(1, 3) if c1_at_bound else slice(0, 3)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", PerceptionModelWarning)
        cov_free = _safe_inverse(info[free, free], "the Fisher information") if c1_at_bound else cov
        step = cov_free @ (grad[free] * a.size)
        near_optimum = bool(np.all(np.abs(step) <= MLE_STEP_TOL * np.sqrt(np.diag(cov_free))))
    converged = bool(res.success) or near_optimum
    model = _make_model(c, angle_unit, a, t, source, converged, str(res.message))
    binned = bin_observations(a, t, y, spec)
    r2 = math.nan
    if binned.count.size >= 2:
        r2 = weighted_r2(binned.frequency, model.probability(binned.alpha, binned.theta), binned.count)
    return FitResult(
        model=model,
        method="mle",
        n=int(a.size),
        n_inliers=int(y.sum()),
        intervals=_intervals(c, cov, confidence),
        covariance=cov,
        confidence=confidence,
        ci_method="fisher",
        r2=r2,
        log_loss=log_loss(model.probability(a, t), y),
        n_bins=int(binned.count.size),
        binned=binned,
        converged=converged,
        message=str(res.message),
        extra={"neg_log_likelihood_mean": float(res.fun), "iterations": int(res.nit)},
        c1_at_bound=c1_at_bound,
    )


# --------------------------------------------------------------------------- observations front end
def holdout_split(groups: NDArray[np.int64], fraction: float, seed: int) -> NDArray[np.bool_]:
    """Boolean mask of held-out rows: a random ``fraction`` of the groups (localizations)."""
    check_holdout_fraction(fraction)
    return _holdout_mask(groups, fraction, seed)


def _holdout_mask(groups: NDArray[np.int64], fraction: float, seed: int) -> NDArray[np.bool_]:
    """``holdout_split`` with a checked ``fraction``."""
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


def fit_observations(obs: Observations, settings: FitSettings | None = None, **changes: Any) -> FitResult:
    """Fit on a random ``1 - holdout_fraction`` of the localizations, evaluate on the rest.

    ``settings`` (default ``FitSettings()``, the thesis protocol), with any of its fields changed by keyword
    (``method="mle"``, ``holdout_fraction=0.0``; ``bins=BinSpec(...)`` sets the three bin fields). The
    settings are checked when their record is built, the data once (here, on the whole set: clearer
    messages); the training part is only checked for holding both labels.
    """
    s = _DEFAULT if settings is None else settings
    bins = changes.pop("bins", None)
    if bins is not None:
        changes.update(alpha_bin_rad=bins.alpha_width, theta_bin_rad=bins.theta_width, min_bin_count=bins.min_count)
    if changes:
        s = s.replace(**changes)
    source = obs.source_names
    a, t, y = _check_data(obs.alpha, obs.theta, obs.inlier, source)
    held = _holdout_mask(obs.frame_groups(), s.holdout_fraction, s.seed)
    if held.any():
        train = ~held
        a_fit, t_fit, y_fit = a[train], t[train], y[train]
        _check_both_labels(y_fit, source)
    else:
        a_fit, t_fit, y_fit = a, t, y
    if s.method == "binned":
        result = _fit_binned(
            a_fit, t_fit, y_fit, angle_unit=s.angle_unit, bins=s.bins, ci=s.ci, n_bootstrap=s.n_bootstrap,
            confidence=s.confidence, seed=s.seed, initial=None, source=source,
        )  # fmt: skip
    else:
        result = _fit_mle(
            a_fit, t_fit, y_fit, angle_unit=s.angle_unit, bins=s.bins, confidence=s.confidence, initial=None,
            source=source,
        )  # fmt: skip
    del a_fit, t_fit, y_fit
    holdout = None
    if held.any():
        holdout = _evaluate(result.model, a[held], t[held], y[held], bins=s.bins, calibration_bins=s.calibration_bins)
    extra = dict(result.extra, holdout_fraction=s.holdout_fraction, seed=s.seed)
    return FitResult(**{**vars(result), "holdout": holdout, "extra": extra}).check_identified(source)


def simulate_labels(
    model: PerceptionModel, alpha: ArrayLike, theta: ArrayLike, rng: np.random.Generator
) -> NDArray[np.bool_]:
    """Bernoulli inlier labels drawn from ``model`` at the given angles (radians)."""
    p = model.probability(alpha, theta)
    return rng.random(p.shape) < p


# --------------------------------------------------------------------------- streamed binned fit
Chunks = Callable[[], Iterable[tuple[ArrayLike, ArrayLike, ArrayLike]]]


class BinAccumulator:
    """Observations binned chunk by chunk (e.g. one landmarks.csv at a time): memory grows with the
    number of (alpha, theta) bins, never with the number of observations. ``binned()`` equals
    ``bin_observations`` over all chunks together (up to summation order)."""

    def __init__(self, spec: BinSpec | None = None):
        self.spec = spec or BinSpec()
        self.count = np.zeros((1, 1), np.int64)
        self.inliers = np.zeros((1, 1), np.int64)
        self.sum_alpha = np.zeros((1, 1))
        self.sum_theta = np.zeros((1, 1))
        self.n = 0
        self.alpha_max = 0.0
        self.theta_max = 0.0

    def add(self, alpha: ArrayLike, theta: ArrayLike, inlier: ArrayLike, source: str = "<data>") -> None:
        a, t, y = _check_data(alpha, theta, inlier, source, need_both=False)
        ia = (a / self.spec.alpha_width).astype(np.int64)
        it = (t / self.spec.theta_width).astype(np.int64)
        shape = (max(self.count.shape[0], int(ia.max()) + 1), max(self.count.shape[1], int(it.max()) + 1))
        if shape != self.count.shape:
            for name in ("count", "inliers", "sum_alpha", "sum_theta"):
                old = getattr(self, name)
                grown = np.zeros(shape, old.dtype)
                grown[: old.shape[0], : old.shape[1]] = old
                setattr(self, name, grown)
        flat = ia * shape[1] + it
        size = shape[0] * shape[1]
        self.count += np.bincount(flat, minlength=size).reshape(shape)
        self.inliers += np.bincount(flat, weights=y, minlength=size).round().astype(np.int64).reshape(shape)
        self.sum_alpha += np.bincount(flat, weights=a, minlength=size).reshape(shape)
        self.sum_theta += np.bincount(flat, weights=t, minlength=size).reshape(shape)
        self.n += int(a.size)
        self.alpha_max = max(self.alpha_max, float(a.max()))
        self.theta_max = max(self.theta_max, float(t.max()))

    def binned(self) -> BinnedFrequencies:
        used = self.count >= self.spec.min_count
        na, nt = self.count.shape
        return BinnedFrequencies(
            alpha=self.sum_alpha[used] / self.count[used],
            theta=self.sum_theta[used] / self.count[used],
            count=self.count[used],
            inliers=self.inliers[used],
            alpha_edges=np.arange(na + 1, dtype=np.float64) * self.spec.alpha_width,
            theta_edges=np.arange(nt + 1, dtype=np.float64) * self.spec.theta_width,
            count_grid=self.count.copy(),
            inlier_grid=self.inliers.copy(),
        )


def fit_binned_stream(
    chunks: Chunks,
    *,
    angle_unit: str = "deg",
    bins: BinSpec | None = None,
    confidence: float = _DEFAULT.confidence,
    initial: ArrayLike | None = None,
    source: str = "<data>",
) -> FitResult:
    """``fit_binned`` (sandwich intervals) over observations that need not fit in memory together.

    ``chunks()`` returns a fresh iterable of ``(alpha, theta, inlier)`` arrays (radians), e.g. one per
    landmarks.csv; it is iterated twice: once to bin, once for the per-observation log-loss. The
    constants equal ``fit_binned`` on all chunks concatenated (up to summation order).
    """
    check_angle_unit(angle_unit)
    acc = BinAccumulator(bins)
    for a, t, y in chunks():
        acc.add(a, t, y, source)
    if acc.n == 0:
        raise FitError(f"{source}: no observations")
    n_inliers = int(acc.inliers.sum())
    if n_inliers in (0, acc.n):
        raise FitError(f"{source}: all {acc.n} observations have the same inlier label; nothing to fit")
    binned = acc.binned()
    spec = acc.spec
    if binned.count.size < MIN_FIT_BINS:
        raise FitError(
            f"{source}: only {binned.count.size} (alpha, theta) bins hold >= {spec.min_count} "
            f"observations; need {MIN_FIT_BINS} (collect more data or widen the bins)"
        )
    k = UNIT_SCALE[angle_unit]
    x0 = initial_constants(angle_unit) if initial is None else np.asarray(initial, dtype=np.float64)
    res = _lsq_binned(binned, k, x0)
    c = res.x
    p_bins, jac = _prob_and_jac(c, binned.alpha * k, binned.theta * k, 0.0, 1.0)
    n_b = binned.count.astype(np.float64)
    e_b = binned.frequency - p_bins
    bread = _safe_inverse(jac.T @ (n_b[:, None] * jac), "the least-squares normal matrix")
    cov = bread @ ((jac * ((n_b * e_b) ** 2)[:, None]).T @ jac) @ bread
    model = _make_model(c, angle_unit, np.array([acc.alpha_max]), np.array([acc.theta_max]), source,
                        bool(res.success), str(res.message))
    loss = 0.0
    for a, t, y in chunks():
        yf = np.asarray(y, dtype=np.float64).reshape(-1)
        loss += log_loss(model.probability(np.asarray(a, np.float64), np.asarray(t, np.float64)), yf) * yf.size
    return FitResult(
        model=model,
        method="binned",
        n=acc.n,
        n_inliers=n_inliers,
        intervals=_intervals(c, cov, confidence),
        covariance=cov,
        confidence=confidence,
        ci_method="sandwich",
        r2=weighted_r2(binned.frequency, p_bins, n_b),
        log_loss=loss / acc.n,
        n_bins=int(binned.count.size),
        binned=binned,
        converged=bool(res.success),
        message=str(res.message),
        extra={"bins": {"alpha_width": spec.alpha_width * k, "theta_width": spec.theta_width * k,
                        "min_count": spec.min_count, "unit": angle_unit}, "streamed": True},
    ).check_identified(source)
