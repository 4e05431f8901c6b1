"""The ``landmarks.csv`` schema and its in-memory record :class:`Observations` (angles in radians).

The columns, their units and the ``Observations`` field each fills (:data:`SCHEMA`), the field sets a reader may
ask for, and the record the writer takes and the readers return (:mod:`perception_model.landmarks_file`: the file
itself, its writer and readers, and the table of columns). See ``docs/perception_model.md``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import InputDataError
from .records import short_repr
from .samples import Samples


@dataclass(frozen=True)
class Column:
    """One column of the file: name, kind (``int``, ``bool``, ``angle``, ``float``) and unit."""

    name: str
    kind: str
    unit: str
    field: str  # the ``Observations`` field it fills
    required: bool = True


#: The landmarks file schema, in the order the writer writes it.
SCHEMA: tuple[Column, ...] = (
    Column("t_ns", "int", "ns", "t_ns"),
    Column("leaf_id", "int", "", "leaf_id"),
    Column("trunk_id", "int", "", "trunk_id"),
    Column("landmark_id", "int", "", "landmark_id"),
    Column("inlier", "bool", "", "inlier"),
    Column("parallax_deg", "angle", "deg", "alpha"),
    Column("view_deg", "angle", "deg", "theta"),
    Column("range_m", "float", "m", "range_m"),
    Column("matched", "bool", "", "matched", required=False),
)
BY_NAME = {c.name: c for c in SCHEMA}
BY_FIELD = {c.field: c for c in SCHEMA}
#: Columns every landmarks file must have (header check).
LANDMARK_COLUMNS = tuple(c.name for c in SCHEMA if c.required)
#: ``Observations`` fields a fit needs (groups by ``t_ns``, labels, both angles).
FIT_FIELDS = ("t_ns", "inlier", "alpha", "theta")
ALL_FIELDS = tuple(c.field for c in SCHEMA)
TRUE_WORDS = ("1", "true", "yes")
FALSE_WORDS = ("0", "false", "no")
MAX_ANGLE_DEG = 180.0
#: Bytes of CSV the fast reader parses per block, and Parquet rows per batch (bounded memory).
CSV_BLOCK_BYTES = 1 << 24
PARQUET_BATCH_ROWS = 1 << 20
#: The Parquet writer gathers small blocks (one localization each in ``vtr repeat``) into row groups of this size.
PARQUET_ROW_GROUP_ROWS = 1 << 17
PARQUET_SUFFIX = ".parquet"


# --------------------------------------------------------------------------- the record
@dataclass(frozen=True)
class SourceSpan:
    """Rows ``[start, start + count)`` of an ``Observations`` came from ``path``."""

    path: str
    start: int
    count: int


@dataclass(frozen=True)
class Observations:
    """Landmark match records: one entry per (localization, taught landmark in view).

    Angles in radians (``alpha`` parallax, ``theta`` view); ``inlier`` and ``matched`` are bool.
    ``leaf_id``, ``trunk_id``, ``landmark_id``, ``range_m`` and ``matched`` are None when not
    read (a fit reads only ``FIT_FIELDS``) or, for ``matched``, not recorded. ``sources`` maps row
    ranges back to files.
    """

    __repr__ = short_repr  # arrays by shape: print(record) stays short

    alpha: NDArray[np.float64]
    theta: NDArray[np.float64]
    inlier: NDArray[np.bool_]
    t_ns: NDArray[np.int64]
    leaf_id: NDArray[np.int64] | None = None
    trunk_id: NDArray[np.int64] | None = None
    landmark_id: NDArray[np.int64] | None = None
    range_m: NDArray[np.float64] | None = None
    sources: tuple[SourceSpan, ...] = ()
    matched: NDArray[np.bool_] | None = None

    def __len__(self) -> int:
        return int(self.alpha.shape[0])

    @property
    def source_names(self) -> str:
        """Comma-separated file names (for messages)."""
        return ", ".join(s.path for s in self.sources) or "<memory>"

    def frame_groups(self) -> NDArray[np.int64]:
        """Integer group per row: one group per (source file, t_ns) localization, numbered in that order."""
        n = len(self)
        spans = self.sources or (SourceSpan("<memory>", 0, n),)
        out = np.zeros(n, dtype=np.int64)
        next_id = 0
        for span in spans:
            t = self.t_ns[span.start : span.start + span.count]
            if t.size == 0:
                continue
            if np.all(t[1:] >= t[:-1]):  # written in time order: one pass, no sort
                ids = np.empty(t.size, dtype=np.int64)
                ids[0] = 0
                np.cumsum(t[1:] != t[:-1], out=ids[1:])
            else:
                ids = np.unique(t, return_inverse=True)[1].reshape(-1).astype(np.int64)
            out[span.start : span.start + span.count] = ids + next_id
            next_id += int(ids.max()) + 1
        return out

    def samples(self) -> Samples:
        """The labelled angles a fit reads, checked (``FitError`` naming the files on bad data)."""
        return Samples(self.alpha, self.theta, self.inlier, self.source_names)

    def take(self, index: NDArray[Any]) -> Observations:
        """Subset by boolean mask or integer index (``sources`` are dropped)."""

        def sub(x: NDArray[Any] | None) -> NDArray[Any] | None:
            return None if x is None else x[index]

        return Observations(
            self.alpha[index],
            self.theta[index],
            self.inlier[index],
            self.t_ns[index],
            sub(self.leaf_id),
            sub(self.trunk_id),
            sub(self.landmark_id),
            sub(self.range_m),
            (),
            sub(self.matched),
        )

    def describe(self, groups: NDArray[np.int64] | None = None) -> dict[str, Any]:
        """Summary for model files and reports (angles in degrees); ``groups`` = ``frame_groups()`` if known."""
        n = len(self)
        if n and groups is None:
            groups = self.frame_groups()
        return {
            "files": [{"path": s.path, "rows": s.count} for s in self.sources],
            "n_observations": n,
            "n_inliers": int(self.inlier.sum()),
            "n_localizations": int(groups.max()) + 1 if n and groups is not None else 0,
            "parallax_deg_range": [float(np.degrees(self.alpha.min())), float(np.degrees(self.alpha.max()))]
            if n
            else None,
            "view_deg_range": [float(np.degrees(self.theta.min())), float(np.degrees(self.theta.max()))] if n else None,
        }

    @staticmethod
    def concatenate(parts: Sequence[Observations]) -> Observations:
        """Join several observation sets, keeping their source spans (optional fields kept if all have them)."""
        if not parts:
            raise InputDataError("no observations given")
        if len(parts) == 1:
            return parts[0]
        spans: list[SourceSpan] = []
        offset = 0
        for part in parts:
            spans.extend(SourceSpan(s.path, s.start + offset, s.count) for s in part.sources)
            offset += len(part)

        def cat(name: str) -> Any:
            arrays = [getattr(p, name) for p in parts]
            return None if any(a is None for a in arrays) else np.concatenate(arrays)

        return Observations(
            cat("alpha"),
            cat("theta"),
            cat("inlier"),
            cat("t_ns"),
            cat("leaf_id"),
            cat("trunk_id"),
            cat("landmark_id"),
            cat("range_m"),
            tuple(spans),
            cat("matched"),
        )

    @staticmethod
    def from_arrays(alpha: Any, theta: Any, inlier: Any, *, name: str = "<memory>") -> Observations:
        """Observations from angle arrays (radians) and labels; ids are zero, one localization."""
        a = np.asarray(alpha, dtype=np.float64).reshape(-1)
        t = np.asarray(theta, dtype=np.float64).reshape(-1)
        y = np.asarray(inlier).reshape(-1).astype(bool)
        if not (a.shape == t.shape == y.shape):
            raise InputDataError(f"{name}: alpha, theta and inlier must have the same length")
        zeros = np.zeros(a.shape, dtype=np.int64)
        return Observations(
            a, t, y, zeros, zeros, zeros, zeros, np.full(a.shape, np.nan), (SourceSpan(name, 0, a.size),)
        )


def is_parquet(path: Path) -> bool:
    return path.suffix.lower() == PARQUET_SUFFIX
