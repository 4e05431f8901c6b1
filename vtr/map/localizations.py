"""A repeat's localization records in the map: one row per repeat vertex, written in that vertex's own transaction.

Table ``localizations`` (additive, created by the first repeat that writes one, so the map format stays version 3 and
older maps open as before): per repeat vertex (``leaf_id``) the fields of its ``localization.csv`` row (time, trunk,
twig and branch ids, success, matches, inliers, ``T_leaf_trunk`` and its full 6x6 covariance, the chain's counters,
status, direction, the experiences used). :meth:`vtr.map.Map.add_leaf` writes the vertex, its temporal edge, its
spatial edge (a success), its experience use and this record in one transaction, so after a kill at any point the map
holds exactly the repeat vertices whose records it holds, and ``vtr map localizations`` gives the run's rows back
(docs/map.md, "Localization records"). Rows are append-only (triggers), like vertices and edges.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import MapError
from .database import Connection
from .records import INDEX_MASK, RUN_SHIFT, blob_matrix, matrix_blob
from .schema import MATRIX4_BYTES, MATRIX6_BYTES

TABLE = "localizations"
#: the separator of the ``experiences`` field (run ids), as in ``localization.csv``
EXPERIENCE_SEPARATOR = ";"

SCHEMA = (
    f"CREATE TABLE IF NOT EXISTS {TABLE} ("
    "leaf_id INTEGER PRIMARY KEY REFERENCES vertices(id), t_ns INTEGER NOT NULL, trunk_id INTEGER NOT NULL, "
    "twig_id INTEGER NOT NULL, branch_id INTEGER NOT NULL, success INTEGER NOT NULL CHECK (success IN (0, 1)), "
    "matches INTEGER NOT NULL CHECK (matches >= 0), inliers INTEGER NOT NULL CHECK (inliers >= 0), "
    f"T_leaf_trunk BLOB NOT NULL CHECK (length(T_leaf_trunk) = {MATRIX4_BYTES}), "
    f"covariance BLOB NOT NULL CHECK (length(covariance) = {MATRIX6_BYTES}), "
    "consecutive_failures INTEGER NOT NULL, distance_since_success_m REAL, status TEXT NOT NULL, "
    "direction INTEGER NOT NULL CHECK (direction IN (-1, 0, 1)), experiences TEXT NOT NULL)",
    f"CREATE TRIGGER IF NOT EXISTS {TABLE}_append_only_update BEFORE UPDATE ON {TABLE} "
    "BEGIN SELECT RAISE(ABORT, 'map localization records are immutable'); END",
    f"CREATE TRIGGER IF NOT EXISTS {TABLE}_append_only_delete BEFORE DELETE ON {TABLE} "
    "BEGIN SELECT RAISE(ABORT, 'map localization records are immutable'); END",
)
COLUMNS = (
    "leaf_id",
    "t_ns",
    "trunk_id",
    "twig_id",
    "branch_id",
    "success",
    "matches",
    "inliers",
    "T_leaf_trunk",
    "covariance",
    "consecutive_failures",
    "distance_since_success_m",
    "status",
    "direction",
    "experiences",
)


@dataclass(frozen=True)
class LocalizationRecord:
    """What the map keeps of one repeat vertex's localization attempt: the fields of its ``localization.csv`` row,
    with the full 6x6 ``covariance`` ([rot, trans]) of ``T_leaf_trunk`` (trunk-camera coordinates into the leaf
    camera; the prior on a failure). ``status`` is the attempt's ``LocalizationStatus`` value."""

    t_ns: int
    leaf_id: int
    trunk_id: int
    twig_id: int
    branch_id: int
    success: bool
    matches: int
    inliers: int
    T_leaf_trunk: np.ndarray
    covariance: np.ndarray
    consecutive_failures: int
    distance_since_success_m: float
    status: str
    direction: int
    experiences: tuple[int, ...] = ()

    def row(self) -> tuple:
        """The record as the table's row (``COLUMNS`` order); ``MapError`` naming a field of the wrong shape. Values
        are stored as they are (a failure's prior and covariance may be infinite; a NaN distance is stored NULL)."""
        T = np.asarray(self.T_leaf_trunk, dtype=np.float64)
        C = np.asarray(self.covariance, dtype=np.float64)
        for name, value, shape in (("T_leaf_trunk", T, (4, 4)), ("covariance", C, (6, 6))):
            if value.shape != shape:
                raise MapError(
                    f"localization of vertex {self.leaf_id}: {name} must be {shape[0]}x{shape[1]}, got "
                    f"shape {value.shape}"
                )
        distance = float(self.distance_since_success_m)
        return (
            int(self.leaf_id),
            int(self.t_ns),
            int(self.trunk_id),
            int(self.twig_id),
            int(self.branch_id),
            int(bool(self.success)),
            int(self.matches),
            int(self.inliers),
            matrix_blob(T),
            matrix_blob(C),
            int(self.consecutive_failures),
            None if np.isnan(distance) else distance,
            str(self.status),
            int(self.direction),
            EXPERIENCE_SEPARATOR.join(str(int(e)) for e in self.experiences),
        )

    @classmethod
    def of_row(cls, r: Sequence) -> LocalizationRecord:
        return cls(
            leaf_id=int(r[0]),
            t_ns=int(r[1]),
            trunk_id=int(r[2]),
            twig_id=int(r[3]),
            branch_id=int(r[4]),
            success=bool(r[5]),
            matches=int(r[6]),
            inliers=int(r[7]),
            T_leaf_trunk=blob_matrix(r[8], (4, 4)),
            covariance=blob_matrix(r[9], (6, 6)),
            consecutive_failures=int(r[10]),
            distance_since_success_m=float("nan") if r[11] is None else float(r[11]),
            status=str(r[12]),
            direction=int(r[13]),
            experiences=tuple(int(e) for e in str(r[14]).split(EXPERIENCE_SEPARATOR) if e),
        )


@dataclass(frozen=True)
class SpatialEdge:
    """A leaf's spatial edge to taught vertex ``to_id``: ``T_from_to`` (4x4, ``T_leaf_trunk``), its 6x6
    ``covariance`` and ``inliers`` (the edge's ``from_id`` is the leaf vertex)."""

    to_id: int
    T_from_to: np.ndarray
    covariance: np.ndarray
    inliers: int


@dataclass(frozen=True)
class Leaf:
    """What :meth:`vtr.map.Map.add_leaf` writes with a repeat keyframe: its localization ``record``, the ``spatial``
    edge of a success (None on a failure) and the experiences (earlier repeat runs) that gave it inliers."""

    record: LocalizationRecord
    spatial: SpatialEdge | None = None
    experience_use: tuple[int, ...] = ()


def has_table(conn: Connection) -> bool:
    return (
        conn.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = ?", (TABLE,)).fetchone() is not None
    )


def create(conn: Connection) -> None:
    """The table and its append-only triggers, if absent (inside the caller's transaction)."""
    for sql in SCHEMA:
        conn.execute(sql)


def insert(conn: Connection, row: tuple) -> None:
    """One record (a :meth:`LocalizationRecord.row`) inside the caller's transaction."""
    conn.execute(f"INSERT INTO {TABLE}({', '.join(COLUMNS)}) VALUES ({', '.join('?' * len(COLUMNS))})", row)


def read(conn: Connection, run: int) -> list[LocalizationRecord]:
    """The records of ``run``'s vertices in vertex order (none when the map has no such table)."""
    if not has_table(conn):
        return []
    lo = int(run) << RUN_SHIFT
    rows = conn.execute(
        f"SELECT {', '.join(COLUMNS)} FROM {TABLE} WHERE leaf_id BETWEEN ? AND ? ORDER BY leaf_id",
        (lo, lo | INDEX_MASK),
    ).fetchall()
    return [LocalizationRecord.of_row(r) for r in rows]


def count(conn: Connection, run: int) -> int:
    """How many records ``run`` has (0 when the map has no such table)."""
    if not has_table(conn):
        return 0
    lo = int(run) << RUN_SHIFT
    return int(
        conn.execute(f"SELECT COUNT(*) FROM {TABLE} WHERE leaf_id BETWEEN ? AND ?", (lo, lo | INDEX_MASK)).fetchone()[0]
    )


__all__ = [
    "COLUMNS",
    "TABLE",
    "Leaf",
    "LocalizationRecord",
    "SpatialEdge",
    "count",
    "create",
    "has_table",
    "insert",
    "read",
]
