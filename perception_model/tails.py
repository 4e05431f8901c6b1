"""The distribution of the inlier count ``L`` of a trunk: Poisson-binomial over independent landmarks.

Its moments (``mu = sum p``, ``sigma^2 = sum p (1 - p)``), the exact distribution (recursion or DFT) and its tail,
the normal approximation's tail, a Monte Carlo estimate, and the map between the chance constraint's ``delta`` and
its normal quantile ``c_bar``: what :mod:`perception_model.constraint` approximates, to check it. See
``docs/perception_model.md`` ("Chance constraint").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from statistics import NormalDist
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import PerceptionModelError

#: Default Monte Carlo sample count and chunk size (rows of Bernoulli draws held at once).
DEFAULT_MC_SAMPLES = 100_000
MC_CHUNK_ELEMENTS = 4_000_000

PmfMethod = Literal["recursion", "dft"]


# --------------------------------------------------------------------------- scalar helpers
def _normal_cdf(x: float) -> float:
    """Standard normal cdf via ``erfc`` (accurate in both tails)."""
    return 0.5 * math.erfc(-x / math.sqrt(2.0))


def c_bar_from_delta(delta: float) -> float:
    """``c_bar = sqrt(2) erfinv(1 - 2 delta)``: the one-sided normal quantile for risk ``delta``."""
    if not 0.0 < delta < 0.5:
        raise PerceptionModelError(f"delta must be in (0, 0.5), got {delta}")
    # sqrt(2) erfinv(1 - 2 delta) is the standard normal quantile at 1 - delta
    return float(NormalDist().inv_cdf(1.0 - delta))


def delta_from_c_bar(c_bar: float) -> float:
    """Inverse of ``c_bar_from_delta``: ``delta = (1 - erf(c_bar / sqrt(2))) / 2``."""
    return _normal_cdf(-c_bar)


def inlier_moments(p: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(mu, sigma^2)`` of the Poisson-binomial count, summing over the last axis of ``p``."""
    pp = np.asarray(p, dtype=np.float64)
    return pp.sum(axis=-1), (pp * (1.0 - pp)).sum(axis=-1)


# --------------------------------------------------------------------------- exact distribution
def poisson_binomial_pmf(p: ArrayLike, method: PmfMethod = "recursion") -> NDArray[np.float64]:
    """Exact pmf ``P(L = k)``, ``k = 0..M``, of the sum of independent Bernoulli(``p_i``).

    ``"recursion"`` convolves one Bernoulli at a time (O(M^2), all terms non-negative, accurate
    far into the tails); ``"dft"`` evaluates the characteristic function at the M+1 roots of unity
    and inverts with an FFT (O(M^2) too; absolute error ~1e-15, so tiny tails are not resolved).
    """
    pp = np.asarray(p, dtype=np.float64).reshape(-1)
    if pp.size and (not np.all(np.isfinite(pp)) or pp.min() < 0.0 or pp.max() > 1.0):
        raise PerceptionModelError("probabilities must be finite and in [0, 1]")
    m = pp.size
    if method == "recursion":
        pmf = np.zeros(m + 1)
        pmf[0] = 1.0
        for j, pj in enumerate(pp):
            head = pmf[: j + 1].copy()
            pmf[: j + 1] *= 1.0 - pj
            pmf[1 : j + 2] += pj * head
        return pmf
    if method == "dft":
        omega = np.exp(2j * np.pi * np.arange(m + 1) / (m + 1))
        terms = 1.0 - pp[None, :] + pp[None, :] * omega[:, None]
        # product over landmarks via sum of logs (no under/overflow); terms are never 0 unless p = 1/2 at -1
        mag = np.abs(terms)
        with np.errstate(divide="ignore"):
            log_mag = np.log(mag).sum(axis=1)
        phase = np.angle(terms).sum(axis=1)
        zero = (mag == 0.0).any(axis=1)
        phi = np.where(zero, 0.0, np.exp(log_mag + 1j * phase))
        pmf = np.fft.fft(phi).real / (m + 1)
        return np.clip(pmf, 0.0, None)
    raise PerceptionModelError(f"unknown method {method!r} (use 'recursion' or 'dft')")


def poisson_binomial_tail(p: ArrayLike, k: float, method: PmfMethod = "recursion", *, lower: bool = False) -> float:
    """Exact ``P(L >= k)`` (or ``P(L < k)`` with ``lower=True``) of the Poisson-binomial count.

    ``k`` is rounded up to an integer. The requested tail is summed directly from the pmf, so
    small tail probabilities keep their relative accuracy (no ``1 - x`` cancellation).
    """
    pmf = poisson_binomial_pmf(p, method)
    kk = min(max(0, math.ceil(k)), pmf.size)
    part = pmf[:kk] if lower else pmf[kk:]
    return float(min(1.0, part.sum()))


def normal_tail(mu: float, sigma: float, k: float, *, continuity: bool = False, lower: bool = False) -> float:
    """Normal approximation of ``P(L >= k)`` (or ``P(L < k)``) for ``L ~ N(mu, sigma^2)``.

    ``P(L >= k) = Phi((mu - k) / sigma)`` as in the thesis constraint; with ``continuity=True``
    the integer correction ``Phi((mu - k + 1/2) / sigma)`` is used instead.
    """
    shift = 0.5 if continuity else 0.0
    z_up = mu - k + shift
    if sigma <= 0.0:
        upper = float(z_up >= 0.0)
        return 1.0 - upper if lower else upper
    return _normal_cdf((-z_up if lower else z_up) / sigma)


def monte_carlo_tail(
    p: ArrayLike,
    k: float,
    n_samples: int = DEFAULT_MC_SAMPLES,
    *,
    rng: np.random.Generator | None = None,
    lower: bool = False,
) -> tuple[float, float]:
    """Monte Carlo ``P(L >= k)`` (or ``P(L < k)``) from ``n_samples`` joint draws: ``(estimate, std_err)``.

    The standard error is ``sqrt(max(q (1 - q), 1 / n) / n)`` (never 0, also when no hit occurred).
    """
    pp = np.asarray(p, dtype=np.float64).reshape(-1)
    if n_samples < 1:
        raise PerceptionModelError("n_samples must be >= 1")
    gen = rng if rng is not None else np.random.default_rng()
    chunk = max(1, MC_CHUNK_ELEMENTS // max(1, pp.size))
    hits = 0
    done = 0
    while done < n_samples:
        rows = min(chunk, n_samples - done)
        counts = (gen.random((rows, pp.size)) < pp).sum(axis=1)
        hits += int((counts < k).sum() if lower else (counts >= k).sum())
        done += rows
    est = hits / n_samples
    return est, math.sqrt(max(est * (1.0 - est), 1.0 / n_samples) / n_samples)


@dataclass(frozen=True)
class TailComparison:
    """Failure probability ``P(L < L_min)`` by the normal approximation, exactly, and by Monte Carlo."""

    n_landmarks: int
    mu: float
    sigma: float
    l_min: float
    normal: float
    normal_continuity: float
    exact: float
    exact_dft: float
    monte_carlo: float
    monte_carlo_se: float


def compare_tails(
    p: ArrayLike, l_min: float, *, n_samples: int = DEFAULT_MC_SAMPLES, rng: np.random.Generator | None = None
) -> TailComparison:
    """Compare ways of computing the failure probability ``P(L < l_min)`` for landmark probabilities ``p``."""
    pp = np.asarray(p, dtype=np.float64).reshape(-1)
    mu, var = inlier_moments(pp)
    sigma = float(np.sqrt(var))
    mc, se = monte_carlo_tail(pp, l_min, n_samples, rng=rng, lower=True)
    return TailComparison(
        n_landmarks=int(pp.size),
        mu=float(mu),
        sigma=sigma,
        l_min=float(l_min),
        normal=normal_tail(float(mu), sigma, l_min, lower=True),
        normal_continuity=normal_tail(float(mu), sigma, l_min, continuity=True, lower=True),
        exact=poisson_binomial_tail(pp, l_min, lower=True),
        exact_dft=poisson_binomial_tail(pp, l_min, "dft", lower=True),
        monte_carlo=mc,
        monte_carlo_se=se,
    )
