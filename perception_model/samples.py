"""The labelled angles a fit or an evaluation reads: a record checked when it is built.

:class:`Samples` holds parallax ``alpha`` and view ``theta`` (radians) with 0/1 inlier labels and the name of
their source (for messages). Building one checks the data once, in the order a reader meets the problems
(lengths, emptiness, NaN/inf or negative angles, labels other than 0/1), so the fits receive data already
checked; whether both labels occur is a fit's need, not an evaluation's (:meth:`Samples.require_both_labels`).
``Observations.samples()`` gives the record of a landmarks file. See ``docs/perception_model.md``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import FitError
from .records import short_repr

#: The source named in messages when the caller gives none.
UNNAMED_SOURCE = "<data>"


@dataclass(frozen=True, eq=False, init=False)
class Samples:
    """Angles (radians, flat float64) and inlier labels (flat float64, 0 or 1) of one data set, checked."""

    __repr__ = short_repr

    alpha: NDArray[np.float64]
    theta: NDArray[np.float64]
    inlier: NDArray[np.float64]
    source: str

    def __init__(self, alpha: ArrayLike, theta: ArrayLike, inlier: ArrayLike, source: str = UNNAMED_SOURCE) -> None:
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
            raise FitError(f"{source}: {int(bad.sum())} observation(s) with NaN/inf angles (first at row {first})")
        if (a < 0).any() or (t < 0).any():
            raise FitError(f"{source}: negative angles (parallax/view angles are in [0, pi])")
        yf = y.astype(np.float64)
        if y.dtype != np.bool_ and not np.isin(yf, (0.0, 1.0)).all():
            raise FitError(f"{source}: inlier labels must be 0/1")
        self._set(a, t, yf, source)

    def _set(self, a: NDArray[np.float64], t: NDArray[np.float64], y: NDArray[np.float64], source: str) -> None:
        object.__setattr__(self, "alpha", a)
        object.__setattr__(self, "theta", t)
        object.__setattr__(self, "inlier", y)
        object.__setattr__(self, "source", source)

    def __len__(self) -> int:
        return int(self.alpha.size)

    @property
    def n_inliers(self) -> int:
        return int(self.inlier.sum())

    def take(self, index: NDArray[Any]) -> Samples:
        """The rows at ``index`` (a boolean mask or integer index): a part of checked data, not checked again
        (it may be empty: a fit then says which label is missing)."""
        part = object.__new__(Samples)
        part._set(self.alpha[index], self.theta[index], self.inlier[index], self.source)
        return part

    def require_both_labels(self) -> Samples:
        """These samples, or ``FitError`` when every label is the same (a fit needs inliers and outliers)."""
        k = self.n_inliers
        if k == 0:
            raise FitError(f"{self.source}: all {len(self)} observations are outliers (inlier = 0); nothing to fit")
        if k == len(self):
            raise FitError(f"{self.source}: all {len(self)} observations are inliers (inlier = 1); nothing to fit")
        return self


__all__ = ["UNNAMED_SOURCE", "Samples"]
