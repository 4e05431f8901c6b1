"""The numerics both estimators share: the model's probability and Jacobian in the constants, the bound on c1,
Wald intervals, a guarded inverse and the fitted model with its range warnings.

Sign convention: ``cos`` is even, so only ``|c2|`` is identifiable; fits constrain ``c2 >= 0`` and
``0 < c1 <= C1_MAX`` (a probability). See ``docs/perception_model.md`` ("Model and fit").
"""

from __future__ import annotations

import math
import warnings
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import special

from .errors import FitError, PerceptionModelError, PerceptionModelWarning
from .fit_result import C1_MAX, CONSTANT_NAMES, ConstantInterval
from .model import DEFAULT_ALPHA_MAX_RAD, DEFAULT_THETA_MAX_RAD, THESIS_CONSTANTS_DEG, PerceptionModel
from .settings import UNIT_SCALE

#: Lower bound on c1 during fits (the model requires c1 > 0).
C1_FLOOR = 1e-9
#: c1 within this relative distance of C1_MAX counts as at the bound (and is set to C1_MAX).
C1_BOUND_RTOL = 1e-6


def snap_c1(c: NDArray[np.float64], active: bool = False) -> tuple[NDArray[np.float64], bool]:
    """``(c, at_bound)``: c1 set to ``C1_MAX`` when the optimizer left it at (or reports it on) the bound."""
    at_bound = bool(active or c[0] >= C1_MAX * (1.0 - C1_BOUND_RTOL))
    if at_bound:
        c = c.copy()
        c[0] = C1_MAX
    return c, at_bound


def prob_and_jac(
    c: NDArray[np.float64], a_u: NDArray[np.float64], t_u: NDArray[np.float64], lo: float, hi: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Clipped probability and its Jacobian ``(n, 3)`` w.r.t. c, for angles in the model unit.

    Clipped to ``[lo, hi]``; ``p = lo`` beyond the cosine's first zero. Jacobian zero where clipped.
    """
    c1, c2, c3 = float(c[0]), float(c[1]), float(c[2])
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


def wald_intervals(
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


def safe_inverse(m: NDArray[np.float64], what: str) -> NDArray[np.float64]:
    """``m``'s inverse, or NaNs with a ``PerceptionModelWarning`` naming ``what`` when it is singular."""
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


def make_model(
    c: NDArray[np.float64],
    angle_unit: str,
    alpha_max: float,
    theta_max: float,
    source: str,
    converged: bool,
    message: str,
) -> PerceptionModel:
    """Model with the fitted constants, documented for the angle range of the data (its largest angles,
    radians).

    Warns (``PerceptionModelWarning``) when the optimizer did not converge or the fitted surface
    leaves [0, 1] inside the data range.
    """
    a_max = float(min(math.pi, alpha_max)) if alpha_max > 0 else DEFAULT_ALPHA_MAX_RAD
    t_max = float(min(math.pi, theta_max)) if theta_max > 0 else DEFAULT_THETA_MAX_RAD
    try:
        model = PerceptionModel(float(c[0]), float(abs(c[1])), float(c[2]), angle_unit, a_max, t_max)
    except PerceptionModelError as err:
        raise FitError(f"{source}: the fit gave unusable constants {c.tolist()} ({err})") from None
    if not converged:
        warnings.warn(f"{source}: the optimizer did not converge ({message})", PerceptionModelWarning, stacklevel=3)
    for problem in model.range_problems():
        warnings.warn(f"{source}: fitted model: {problem}", PerceptionModelWarning, stacklevel=3)
    return model


__all__ = [
    "C1_BOUND_RTOL",
    "C1_FLOOR",
    "initial_constants",
    "make_model",
    "prob_and_jac",
    "safe_inverse",
    "snap_c1",
    "wald_intervals",
]
