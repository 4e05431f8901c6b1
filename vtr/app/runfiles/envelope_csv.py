"""``envelope.csv`` (``perception-model envelope``, the demo's mission): one row per taught vertex, how far the
vehicle may move from it before the perception bound fails.

Columns (:data:`SCHEMA`): ``vertex_id``; ``x_m y_m z_m`` (the taught camera centre in the map's gravity-aligned frame
g, rounded to 0.1 mm); ``heading_deg`` (the optical axis' heading in g); ``bound_taught`` (``mu - c_bar sigma`` at the
vertex); ``left_m right_m up_m down_m`` (the distances); ``<direction>_capped`` (0/1: no crossing within ``--max``,
the distance is a lower bound) and ``<direction>_extrapolated`` (0/1: the bound there rests mostly on angles beyond
the model's fitted range). See ``docs/perception_model.md``.
"""

from __future__ import annotations

from pathlib import Path
from typing import IO, Any

import numpy as np

from ...io.csv_table import Column, CsvSchema

#: The four directions of an envelope, in column order.
DIRECTIONS = ("left", "right", "up", "down")
#: Decimals of the written positions and distances (m), the heading (deg) and the bound.
POSITION_DECIMALS = 4
HEADING_DECIMALS = 3
BOUND_DECIMALS = 3

SCHEMA = CsvSchema(
    "envelope.csv",
    (
        Column("vertex_id", "int"),
        *(Column(f"{a}_m", "float", unit="m") for a in ("x", "y", "z")),
        Column("heading_deg", "float", unit="deg"),
        Column("bound_taught", "float"),
        *(Column(f"{d}_m", "float", unit="m") for d in DIRECTIONS),
        *(Column(f"{d}_capped", "bool") for d in DIRECTIONS),
        *(Column(f"{d}_extrapolated", "bool") for d in DIRECTIONS),
    ),
)


def envelope_row(
    vertex_id: int,
    position_g: np.ndarray,
    yaw_g: float,
    bound_taught: float,
    distance_m: dict[str, float],
    capped: dict[str, bool],
    extrapolated: dict[str, bool],
) -> list[Any]:
    """The cells of one vertex's row (rounded as written)."""
    return [
        vertex_id,
        *np.round(position_g, POSITION_DECIMALS).tolist(),
        round(float(np.degrees(yaw_g)), HEADING_DECIMALS),
        round(bound_taught, BOUND_DECIMALS),
        *(round(distance_m[d], POSITION_DECIMALS) for d in DIRECTIONS),
        *(bool(capped[d]) for d in DIRECTIONS),
        *(bool(extrapolated.get(d, False)) for d in DIRECTIONS),
    ]


def write_envelope_rows(file: IO[str], rows: list[list[Any]]) -> None:
    """Header and rows (from :func:`envelope_row`) on an open text file (opened with ``newline=""``)."""
    writer = SCHEMA.writer(file)
    for row in rows:
        writer.write(row)


def read_envelope_csv(path: Path) -> dict[str, np.ndarray]:
    """Every column of an ``envelope.csv`` as an array of its kind (``DataError`` naming the file on a damaged
    one)."""
    return SCHEMA.read(path)


__all__ = ["DIRECTIONS", "SCHEMA", "envelope_row", "read_envelope_csv", "write_envelope_rows"]
