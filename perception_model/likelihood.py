"""Per-observation Bernoulli maximum likelihood of the model's constants (:func:`fit_mle`).

``scipy.optimize.minimize`` (L-BFGS-B, ``0 < c1 <= 1``, ``c2 >= 0``) on the mean negative log-likelihood with
its analytic gradient; probabilities are clipped to ``[PROB_EPS, 1 - PROB_EPS]`` inside the logarithms (the
gradient is zero where clipped). Intervals from the expected Fisher information ``sum J J^T / (p (1 - p))``.
See ``docs/perception_model.md`` ("Model and fit").
"""

from __future__ import annotations

import warnings

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import optimize

from .binning import bin_observations
from .errors import FitError, PerceptionModelWarning
from .fit_core import C1_FLOOR, initial_constants, make_model, prob_and_jac, safe_inverse, snap_c1, wald_intervals
from .fit_result import C1_MAX, FitResult
from .least_squares import fit_binned
from .samples import Samples
from .scores import PROB_EPS, binned_r2, log_loss
from .settings import DEFAULT_SETTINGS, UNIT_SCALE, FitSettings

#: Optimizer tolerances and iteration limit.
MLE_FTOL = 1e-15
MLE_GTOL = 1e-10
MLE_MAXITER = 2000
#: Observations per chunk when evaluating the likelihood (bounds the temporaries on large data).
MLE_CHUNK = 1 << 20
#: An MLE counts as converged when the remaining Fisher-scoring step is below this many standard errors.
MLE_STEP_TOL = 1e-3


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
        p, jac = prob_and_jac(cc, a_u[sl], t_u[sl], PROB_EPS, 1.0 - PROB_EPS)
        total += float(np.sum(yy * np.log(p) + (1.0 - yy) * np.log1p(-p)))
        dl_dp = yy / p - (1.0 - yy) / (1.0 - p)
        grad -= dl_dp @ jac
    return -total / n, grad / n


def fisher_information(c: ArrayLike, a_u: NDArray[np.float64], t_u: NDArray[np.float64]) -> NDArray[np.float64]:
    """Expected Fisher information ``sum J J^T / (p (1 - p))`` of n Bernoulli observations (model unit)."""
    cc = np.asarray(c, dtype=np.float64)
    info = np.zeros((3, 3))
    for s in range(0, a_u.size, MLE_CHUNK):
        p, jac = prob_and_jac(cc, a_u[s : s + MLE_CHUNK], t_u[s : s + MLE_CHUNK], PROB_EPS, 1.0 - PROB_EPS)
        w = 1.0 / (p * (1.0 - p))
        info += (jac * w[:, None]).T @ jac
    return info


def _start(samples: Samples, settings: FitSettings) -> NDArray[np.float64]:
    """A binned fit's constants when enough bins exist (its warnings do not concern the MLE), else the thesis
    constants."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PerceptionModelWarning)
            return fit_binned(samples, settings.replace(ci="sandwich")).model.constants
    except FitError:
        return initial_constants(settings.angle_unit)


def fit_mle(
    samples: Samples, settings: FitSettings = DEFAULT_SETTINGS, *, initial: ArrayLike | None = None
) -> FitResult:
    """Per-observation Bernoulli maximum likelihood; intervals from the Fisher information.

    Starts from ``initial`` (default: a binned fit when enough bins exist, else the thesis constants).
    Constants returned for ``settings.angle_unit``; ``settings.bins`` for the binned R^2.
    """
    samples.require_both_labels()
    a, t, y, source = samples.alpha, samples.theta, samples.inlier, samples.source
    for name, values in (("parallax angle", a), ("view angle", t)):
        if np.ptp(values) == 0:
            raise FitError(
                f"{source}: every observation has the same {name} ({values[0]:.6g} rad); "
                "the constants cannot be identified (collect data over a range of angles)"
            )
    k = UNIT_SCALE[settings.angle_unit]
    x0 = _start(samples, settings) if initial is None else np.asarray(initial, dtype=np.float64)
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
    c, c1_at_bound = snap_c1(res.x * scale)
    _, grad = neg_log_likelihood(c, a_u, t_u, y)
    info = fisher_information(c, a_u, t_u)
    cov = safe_inverse(info, "the Fisher information")
    # converged: the optimizer's verdict, or the remaining Fisher-scoring step is negligible next to
    # the standard errors (L-BFGS-B may stop on its function tolerance when already at the optimum);
    # with c1 held at its bound only (c2, c3) are free
    free = slice(1, 3) if c1_at_bound else slice(0, 3)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", PerceptionModelWarning)
        cov_free = safe_inverse(info[free, free], "the Fisher information") if c1_at_bound else cov
        step = cov_free @ (grad[free] * a.size)
        near_optimum = bool(np.all(np.abs(step) <= MLE_STEP_TOL * np.sqrt(np.diag(cov_free))))
    converged = bool(res.success) or near_optimum
    model = make_model(c, settings.angle_unit, float(a.max()), float(t.max()), source, converged, str(res.message))
    binned = bin_observations(samples, settings.bins)
    return FitResult(
        model=model,
        method="mle",
        n=len(samples),
        n_inliers=samples.n_inliers,
        intervals=wald_intervals(c, cov, settings.confidence),
        covariance=cov,
        confidence=settings.confidence,
        ci_method="fisher",
        r2=binned_r2(model, binned),
        log_loss=log_loss(model.probability(a, t), y),
        n_bins=int(binned.count.size),
        binned=binned,
        converged=converged,
        message=str(res.message),
        extra={"neg_log_likelihood_mean": float(res.fun), "iterations": int(res.nit)},
        c1_at_bound=c1_at_bound,
    )


__all__ = ["MLE_CHUNK", "fisher_information", "fit_mle", "neg_log_likelihood"]
