"""The ``perception-model`` command: fit, evaluate and apply the perception model (the group and its shared
helpers in :mod:`.common`, ``fit``/``evaluate`` in :mod:`.fit_commands`, ``constraint`` and its options in
:mod:`.constraint_commands`, all re-exported here).

    perception-model fit LANDMARKS.csv|.parquet... --out DIR [--method binned|mle]   # DIR/model.json, DIR/fit.png
    perception-model evaluate DIR/model.json LANDMARKS.csv|.parquet... [--out DIR] [--json]
    perception-model constraint DIR/model.json --landmarks L.csv --positions P.csv [--out DIR | --out -]

The conventions of both console scripts (one-line usage errors, ``--out DIR`` always a folder, ``--force``
to replace outputs, ``--json`` a flag) are written in ``perception_model.commandline``.

This package imports nothing from ``vtr`` and its command knows no maps: the ``perception-model`` console
script installed with ``vtr`` (``vtr.cli.perception_model``) holds ``fit`` and ``evaluate`` from here and
declares the map-aware commands itself (``constraint`` with ``--map`` as well as ``--landmarks``,
``envelope``), built from the options and helpers of ``constraint`` here (``landmarks_option``,
``confidence_options``, ``constraint_output_options``, ``resolve_c_bar``, ``report_constraint``...).

A thin adapter over the library: known errors (``PerceptionModelError``, unreadable files)
become one line ``perception-model: error: ...`` on stderr and exit code 1; library warnings are
shown as ``perception-model: warning: ...``. Angles are printed in the model's unit. The defaults of the
options are the library's (``perception_model.settings``); ``fit`` and ``evaluate`` build one
``FitSettings`` record from their options (bin widths converted from degrees there, once).
"""

from __future__ import annotations

from .common import DIST, FIT_DEFAULTS, PITCH_DEG, PROG, bin_options, check_output, deprecated, main
from .common import _Group as _Group
from .constraint_commands import (
    COMMON_FMT,
    MAX_CHUNK_ELEMENTS,
    MAX_PRINTED_ROWS,
    PROGRESS_ABOVE_POSITIONS,
    Table,
    confidence_options,
    constraint_cmd,
    constraint_on_landmarks,
    constraint_output,
    constraint_output_options,
    landmarks_option,
    position_chunks,
    report_constraint,
    resolve_c_bar,
    taught_camera_option,
)
from .constraint_commands import _parse_vector as _parse_vector
from .fit_commands import evaluate_cmd, fit_cmd

__all__ = [
    "COMMON_FMT",
    "DIST",
    "FIT_DEFAULTS",
    "MAX_CHUNK_ELEMENTS",
    "MAX_PRINTED_ROWS",
    "PITCH_DEG",
    "PROG",
    "PROGRESS_ABOVE_POSITIONS",
    "Table",
    "bin_options",
    "check_output",
    "confidence_options",
    "constraint_cmd",
    "constraint_on_landmarks",
    "constraint_output",
    "constraint_output_options",
    "deprecated",
    "evaluate_cmd",
    "fit_cmd",
    "landmarks_option",
    "main",
    "position_chunks",
    "report_constraint",
    "resolve_c_bar",
    "taught_camera_option",
]
