"""``frames.csv`` (``vtr odometry``, ``vtr teach``): one row per frame processed.

===============  =====  ==============================================================
column           kind   meaning
===============  =====  ==============================================================
``t_ns``         int    frame time, nanoseconds
``result``       str    odometry result (``vtr.types.FrameKind``: keyframe, frame, failure, ...)
``matches``      int    feature matches to the window
``inliers``      int    RANSAC / estimation inliers
``keyframe_id``  int    the map vertex (keyframe) the frame belongs to
===============  =====  ==============================================================
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ...io.csv_table import Column, CsvSchema
from ...types import FrameRecord

SCHEMA = CsvSchema(
    "frames.csv",
    (
        Column("t_ns", "int", unit="ns"),
        Column("result", "str"),
        Column("matches", "int"),
        Column("inliers", "int"),
        Column("keyframe_id", "int"),
    ),
)


def write_frames_csv(path: Path, records: Sequence[FrameRecord]) -> None:
    """The file at ``path``: one row per record."""
    SCHEMA.write(path, ((r.t_ns, r.kind.value, r.matches, r.inliers, r.vertex_id) for r in records))


def read_frames_csv(path: Path) -> dict[str, np.ndarray]:
    """The columns of a ``frames.csv`` (names as in :data:`SCHEMA`)."""
    return SCHEMA.read(path)


__all__ = ["SCHEMA", "read_frames_csv", "write_frames_csv"]
