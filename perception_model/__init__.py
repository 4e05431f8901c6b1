"""Perception model for visual teach and repeat (thesis §7.3): angles, model, fits, chance constraint.

- ``angles``: parallax and view angles of trunk landmarks (radians, frame ``o``);
- ``model``: ``PerceptionModel`` ``p = c1 cos(c2 theta) exp(c3 alpha)`` with JSON save/load;
- ``settings``: ``FitSettings`` (the fit's settings record: defaults, domains) and the thesis ``L_min``,
  ``c_bar``;
- ``fit``: binned least squares (thesis protocol) and Bernoulli maximum likelihood, evaluation, on
  ``Samples`` (``samples``, checked when built) and ``FitSettings``, returning ``FitResult``;
- ``constraint``: the chance constraint ``mu - c_bar sigma >= L_min`` with analytic gradients over
  an MPC horizon; ``tails``: the exact Poisson-binomial tail of the inlier count and a Monte Carlo check;
- ``landmarks_file``: the ``landmarks.csv``/``.parquet`` format (schema, ``Observations``, writer,
  columnar reader); ``io``: landmark/camera position readers; ``synthetic``: synthetic data;
- ``plots``: the figure of a fit;
- ``cli``: the ``perception-model`` command.

The package does not depend on ``vtr``; its errors derive from ``PerceptionModelError``.
"""

from __future__ import annotations

import importlib
from typing import Any

from .errors import PerceptionModelError, PerceptionModelWarning

# public name -> defining module; imported on first use so that e.g. a controller importing
# ``perception_model.constraint`` does not pay for scipy.optimize (fitting) at start-up
_LAZY = {
    "optical_axis": "angles",
    "parallax_angle": "angles",
    "view_angle": "angles",
    "ConstraintEvaluation": "constraint",
    "Linearization": "constraint",
    "PerceptionConstraint": "constraint",
    "c_bar_from_delta": "tails",
    "poisson_binomial_tail": "tails",
    "FitResult": "fit",
    "Samples": "samples",
    "evaluate": "fit",
    "fit_binned": "fit",
    "fit_mle": "fit",
    "fit_observations": "fit",
    "LandmarksWriter": "landmarks_file",
    "Observations": "landmarks_file",
    "read_landmarks": "landmarks_file",
    "read_landmarks_files": "landmarks_file",
    "write_landmarks": "landmarks_file",
    "PerceptionModel": "model",
    "FitSettings": "settings",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'perception_model' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


__all__ = [
    "ConstraintEvaluation",
    "FitResult",
    "FitSettings",
    "LandmarksWriter",
    "Linearization",
    "Observations",
    "PerceptionConstraint",
    "PerceptionModel",
    "PerceptionModelError",
    "PerceptionModelWarning",
    "Samples",
    "c_bar_from_delta",
    "evaluate",
    "fit_binned",
    "fit_mle",
    "fit_observations",
    "optical_axis",
    "parallax_angle",
    "poisson_binomial_tail",
    "read_landmarks",
    "read_landmarks_files",
    "view_angle",
    "write_landmarks",
]
