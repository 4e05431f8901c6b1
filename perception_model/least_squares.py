"""The binned fit of the thesis protocol (§7.3.1): weighted least squares of the model to per-bin inlier
frequencies, in memory (:func:`fit_binned`) or streamed chunk by chunk (:func:`fit_binned_stream`).

Observations are grouped into (alpha, theta) bins (:mod:`perception_model.binning`, one path for both); the
model, evaluated at each bin's mean angles, is fitted by ``scipy.optimize.least_squares`` with the bin counts
as weights and ``0 < c1 <= 1``. Intervals from the heteroscedasticity-robust (sandwich) covariance, or, in
memory, from a bootstrap over observations. See ``docs/perception_model.md`` ("Model and fit").
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import optimize

from .binning import BinAccumulator, bin_observations
from .errors import FitError
from .fit_core import C1_FLOOR, initial_constants, make_model, prob_and_jac, safe_inverse, snap_c1, wald_intervals
from .fit_result import C1_MAX, CONSTANT_NAMES, BinnedFrequencies, ConstantInterval, FitResult
from .samples import Samples
from .scores import log_loss, weighted_r2
from .settings import DEFAULT_SETTINGS, UNIT_SCALE, BinSpec, FitSettings, check_bootstrap

#: A binned fit needs at least this many usable bins (3 constants + residual freedom).
MIN_FIT_BINS = 6
#: Optimizer tolerance (function, step and gradient).
LSQ_TOL = 1e-12
#: A start on a bound is moved inside it by this much (``least_squares`` needs a strictly feasible start).
START_MARGIN = 1e-12

#: A fresh iterable of checked samples per call (e.g. one per landmarks file); iterated twice.
Chunks = Callable[[], Iterable[Samples]]


@dataclass(frozen=True)
class _BinnedSolution:
    """The least-squares constants on some bins, with what the intervals and the result need."""

    c: NDArray[np.float64]
    c1_at_bound: bool
    success: bool
    message: str
    p_bins: NDArray[np.float64]
    jac: NDArray[np.float64]
    n_b: NDArray[np.float64]
    frequency: NDArray[np.float64]

    def sandwich(self) -> NDArray[np.float64]:
        """Robust covariance ``B^-1 (sum n_b^2 e_b^2 J_b J_b^T) B^-1`` with ``B = sum n_b J_b J_b^T``."""
        bread = safe_inverse(self.jac.T @ (self.n_b[:, None] * self.jac), "the least-squares normal matrix")
        e_b = self.frequency - self.p_bins
        meat = (self.jac * ((self.n_b * e_b) ** 2)[:, None]).T @ self.jac
        out: NDArray[np.float64] = bread @ meat @ bread
        return out


def _lsq_binned(binned: BinnedFrequencies, k: float, x0: NDArray[np.float64]) -> optimize.OptimizeResult:
    a_u = binned.alpha * k
    t_u = binned.theta * k
    w = np.sqrt(binned.count.astype(np.float64))
    f = binned.frequency

    def resid(c: NDArray[np.float64]) -> NDArray[np.float64]:
        return w * (prob_and_jac(c, a_u, t_u, 0.0, 1.0)[0] - f)

    def jac(c: NDArray[np.float64]) -> NDArray[np.float64]:
        return w[:, None] * prob_and_jac(c, a_u, t_u, 0.0, 1.0)[1]

    lower = np.array([C1_FLOOR, 0.0, -np.inf])
    upper = np.array([C1_MAX, np.inf, np.inf])
    start = np.clip(x0, lower + START_MARGIN, upper)
    return optimize.least_squares(
        resid, start, jac=jac, bounds=(lower, upper), method="trf", x_scale="jac", ftol=LSQ_TOL, xtol=LSQ_TOL,
        gtol=LSQ_TOL,
    )  # fmt: skip


def _solve(binned: BinnedFrequencies, settings: FitSettings, initial: ArrayLike | None, source: str) -> _BinnedSolution:
    """The constants of the bins (at least ``MIN_FIT_BINS`` used ones), c1 snapped to its bound when there."""
    spec = settings.bins
    if binned.count.size < MIN_FIT_BINS:
        raise FitError(
            f"{source}: only {binned.count.size} (alpha, theta) bins hold >= {spec.min_count} "
            f"observations; need {MIN_FIT_BINS} (collect more data or widen the bins)"
        )
    k = UNIT_SCALE[settings.angle_unit]
    x0 = initial_constants(settings.angle_unit) if initial is None else np.asarray(initial, dtype=np.float64)
    res = _lsq_binned(binned, k, x0)
    c, c1_at_bound = snap_c1(res.x, bool(res.active_mask[0] == 1))
    p_bins, jac = prob_and_jac(c, binned.alpha * k, binned.theta * k, 0.0, 1.0)
    return _BinnedSolution(
        c,
        c1_at_bound,
        bool(res.success),
        str(res.message),
        p_bins,
        jac,
        binned.count.astype(np.float64),
        binned.frequency,
    )


def _bins_report(spec: BinSpec, angle_unit: str) -> dict[str, Any]:
    k = UNIT_SCALE[angle_unit]
    return {
        "alpha_width": spec.alpha_width * k,
        "theta_width": spec.theta_width * k,
        "min_count": spec.min_count,
        "unit": angle_unit,
    }


def fit_binned(
    samples: Samples, settings: FitSettings = DEFAULT_SETTINGS, *, initial: ArrayLike | None = None
) -> FitResult:
    """Thesis protocol on samples held in memory: weighted least squares of the model to per-bin frequencies.

    Constants returned for ``settings.angle_unit``, bins ``settings.bins``; ``settings.ci="sandwich"`` gives
    the robust covariance, ``"bootstrap"`` resamples observations ``settings.n_bootstrap`` times (percentile
    intervals, ``settings.seed``). ``initial`` (default: the thesis constants) starts the optimizer.
    """
    samples.require_both_labels()
    binned = bin_observations(samples, settings.bins)
    sol = _solve(binned, settings, initial, samples.source)
    if settings.ci == "bootstrap":
        cov, intervals = _bootstrap(samples, settings, sol.c)
    else:  # "sandwich"
        cov = sol.sandwich()
        intervals = wald_intervals(sol.c, cov, settings.confidence)
    model = make_model(
        sol.c,
        settings.angle_unit,
        float(samples.alpha.max()),
        float(samples.theta.max()),
        samples.source,
        sol.success,
        sol.message,
    )
    return FitResult(
        model=model,
        method="binned",
        n=len(samples),
        n_inliers=samples.n_inliers,
        intervals=intervals,
        covariance=cov,
        confidence=settings.confidence,
        ci_method=settings.ci,
        r2=weighted_r2(binned.frequency, sol.p_bins, sol.n_b),
        log_loss=log_loss(model.probability(samples.alpha, samples.theta), samples.inlier),
        n_bins=int(binned.count.size),
        binned=binned,
        converged=sol.success,
        message=sol.message,
        extra={"bins": _bins_report(settings.bins, settings.angle_unit)},
        c1_at_bound=sol.c1_at_bound,
    )


def _bootstrap(
    samples: Samples, settings: FitSettings, c: NDArray[np.float64]
) -> tuple[NDArray[np.float64], tuple[ConstantInterval, ...]]:
    """Covariance and percentile intervals of the constants over ``settings.n_bootstrap`` resamples."""
    check_bootstrap(settings.n_bootstrap)
    k = UNIT_SCALE[settings.angle_unit]
    rng = np.random.default_rng(settings.seed)
    n = len(samples)
    draws = []
    for _ in range(settings.n_bootstrap):
        b = bin_observations(samples.take(rng.integers(0, n, n)), settings.bins)
        if b.count.size < MIN_FIT_BINS:
            continue
        draws.append(snap_c1(_lsq_binned(b, k, c).x)[0])
    if len(draws) < 2:
        raise FitError("bootstrap failed: too few resamples had enough bins")
    d = np.array(draws)
    cov = np.cov(d, rowvar=False)
    lo_q, hi_q = 0.5 - 0.5 * settings.confidence, 0.5 + 0.5 * settings.confidence
    lo, hi = np.quantile(d, lo_q, axis=0), np.quantile(d, hi_q, axis=0)
    se = d.std(axis=0, ddof=1)
    intervals = tuple(
        ConstantInterval(n, float(e), float(low), float(high), float(s))
        for n, e, low, high, s in zip(CONSTANT_NAMES, c, lo, hi, se, strict=True)
    )
    return cov, intervals


def fit_binned_stream(
    chunks: Chunks, settings: FitSettings = DEFAULT_SETTINGS, *, source: str, initial: ArrayLike | None = None
) -> FitResult:
    """``fit_binned`` (sandwich intervals) over samples that need not fit in memory together.

    ``chunks()`` returns a fresh iterable of :class:`Samples` (e.g. one per landmarks file); it is iterated
    twice: once to bin, once for the per-observation log-loss. The constants equal ``fit_binned`` on all chunks
    together (up to summation order). ``source`` names the whole data set in messages.
    """
    if settings.ci != "sandwich":
        raise FitError(f"{source}: a streamed fit gives sandwich intervals only (ci={settings.ci!r})")
    acc = BinAccumulator(settings.bins)
    for part in chunks():
        acc.add(part)
    if acc.n == 0:
        raise FitError(f"{source}: no observations")
    n_inliers = int(acc.inliers.sum())
    if n_inliers in (0, acc.n):
        raise FitError(f"{source}: all {acc.n} observations have the same inlier label; nothing to fit")
    binned = acc.binned()
    sol = _solve(binned, settings, initial, source)
    cov = sol.sandwich()
    model = make_model(sol.c, settings.angle_unit, acc.alpha_max, acc.theta_max, source, sol.success, sol.message)
    loss = 0.0
    for part in chunks():
        loss += log_loss(model.probability(part.alpha, part.theta), part.inlier) * len(part)
    return FitResult(
        model=model,
        method="binned",
        n=acc.n,
        n_inliers=n_inliers,
        intervals=wald_intervals(sol.c, cov, settings.confidence),
        covariance=cov,
        confidence=settings.confidence,
        ci_method="sandwich",
        r2=weighted_r2(binned.frequency, sol.p_bins, sol.n_b),
        log_loss=loss / acc.n,
        n_bins=int(binned.count.size),
        binned=binned,
        converged=sol.success,
        message=sol.message,
        extra={"bins": _bins_report(settings.bins, settings.angle_unit), "streamed": True},
        c1_at_bound=sol.c1_at_bound,
    ).check_identified(source)


__all__ = ["LSQ_TOL", "MIN_FIT_BINS", "Chunks", "fit_binned", "fit_binned_stream"]
