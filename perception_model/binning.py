"""Observations grouped on a regular (alpha, theta) grid: the one binning path of every fit and score.

:class:`BinAccumulator` adds :class:`~perception_model.samples.Samples` chunk by chunk (one landmarks file at a
time: memory grows with the number of bins, never with the number of observations); :func:`bin_observations`
is the same accumulator given all the samples at once, so the in-memory and the streamed fits bin alike. The
grid starts at 0 with the widths of a :class:`~perception_model.settings.BinSpec`. See
``docs/perception_model.md`` ("Model and fit").
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .fit_result import BinnedFrequencies
from .samples import Samples
from .settings import BinSpec


class BinAccumulator:
    """Counts, inliers and angle sums per (alpha, theta) bin, grown as chunks arrive. ``binned()`` equals
    ``bin_observations`` over all chunks together (up to summation order)."""

    def __init__(self, spec: BinSpec) -> None:
        self.spec = spec
        self.count: NDArray[np.int64] = np.zeros((1, 1), np.int64)
        self.inliers: NDArray[np.int64] = np.zeros((1, 1), np.int64)
        self.sum_alpha: NDArray[np.float64] = np.zeros((1, 1))
        self.sum_theta: NDArray[np.float64] = np.zeros((1, 1))
        self.n = 0
        self.alpha_max = 0.0
        self.theta_max = 0.0

    def add(self, samples: Samples) -> None:
        """Bin one chunk of checked samples."""
        a, t, y = samples.alpha, samples.theta, samples.inlier
        if a.size == 0:
            return
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
        """The bins so far: mean angles of the used bins (count >= ``spec.min_count``) and the whole grid."""
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


def bin_observations(samples: Samples, spec: BinSpec) -> BinnedFrequencies:
    """Group samples (radians) on the regular grid of ``spec`` starting at 0; mean angles per bin."""
    acc = BinAccumulator(spec)
    acc.add(samples)
    return acc.binned()


__all__ = ["BinAccumulator", "bin_observations"]
