"""``summary.csv`` (``vtr batch``): one row per run of the manifest, in manifest order (each route's teach first).

Columns (:data:`SCHEMA`): ``route``, ``name`` (the run's folder), ``kind`` (teach/repeat), ``status`` (finished,
resumed, failed, blocked); ``frames``, ``vertices``, ``localized`` (a repeat's localized vertices),
``median_inliers``, ``seconds`` (the run's wall time), ``error``, ``changed`` (why a finished run was run again) and
``localized_pct``; a cell is empty where the run has no such value. See the README's "Batches" section.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

from ...io.csv_table import Column, CsvSchema

SCHEMA = CsvSchema(
    "summary.csv",
    (
        Column("route", "str"),
        Column("name", "str"),
        Column("kind", "str"),
        Column("status", "str"),
        Column("frames", "int", optional=True),
        Column("vertices", "int", optional=True),
        Column("localized", "int", optional=True),
        Column("median_inliers", "float", optional=True),
        Column("seconds", "float", unit="s", optional=True),
        Column("error", "str", optional=True),
        Column("changed", "str", optional=True),
        Column("localized_pct", "float", unit="%", optional=True),
    ),
)


def write_summary_csv(path: Path, outcomes: Iterable[Any]) -> None:
    """The file at ``path``: the header and one row per outcome (``vtr.app.batch.outcome.RunOutcome``: its
    attribute of each column's name)."""
    SCHEMA.write(path, ([getattr(o, name) for name in SCHEMA.header] for o in outcomes))


def read_summary_csv(path: Path) -> list[dict[str, Any]]:
    """The rows of a ``summary.csv`` written by :func:`write_summary_csv`, each a mapping column -> value (None for
    an empty cell)."""
    columns = SCHEMA.read(path)
    n = len(columns["route"])
    return [{name: values[i] for name, values in columns.items()} for i in range(n)]


__all__ = ["SCHEMA", "read_summary_csv", "write_summary_csv"]
