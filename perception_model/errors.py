"""Exceptions and warnings of the perception-model package.

One root, ``PerceptionModelError``, independent of ``vtr`` so the package can be used alone.
The ``perception-model`` CLI turns any of them into one line on stderr and exit code 1.
"""

from __future__ import annotations


class PerceptionModelError(Exception):
    """Root of every error this package raises on purpose."""


class InputDataError(PerceptionModelError):
    """An input file or array is missing, malformed or inconsistent (names the file and row)."""


class ModelFileError(PerceptionModelError):
    """A model JSON file is missing, malformed, or holds unusable constants (names the file)."""


class FitError(PerceptionModelError):
    """Data cannot support a fit (too few bins, one label only) or the optimizer failed."""


class GeometryError(PerceptionModelError):
    """Degenerate geometry: a zero-length vector where a direction is needed, non-finite input."""


class PerceptionModelWarning(UserWarning):
    """A usable but suspicious model or data set (e.g. probabilities clipped inside the range)."""
