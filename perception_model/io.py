"""Readers and writers for perception-model data files.

``landmarks.csv`` (one row per matched teach landmark per localization, written by the repeat
pipeline; DESIGN.md §4): columns ``t_ns, leaf_id, trunk_id, landmark_id, inlier, parallax_deg,
view_deg, range_m`` (any order, extra columns ignored). ``inlier`` is 0/1 (or true/false);
angles are degrees in the file and radians in memory; ``range_m`` is the landmark range in
metres (may be empty/NaN; informational).

Landmark positions (``read_points``): CSV with a header containing ``x,y,z`` or a ``.npy`` array
``(M, 3)``; metres in frame ``o``.

Camera positions along a path (``read_positions``): CSV with columns ``x,y,z`` and optionally
``yaw`` (radians) or ``yaw_deg``; metres in frame ``o``.

Every error is an ``InputDataError`` naming the file and, where possible, the line.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import InputDataError

LANDMARK_COLUMNS = (
    "t_ns",
    "leaf_id",
    "trunk_id",
    "landmark_id",
    "inlier",
    "parallax_deg",
    "view_deg",
    "range_m",
)
_INT_COLUMNS = ("t_ns", "leaf_id", "trunk_id", "landmark_id")
_ANGLE_COLUMNS = ("parallax_deg", "view_deg")
_TRUE = frozenset({"1", "true", "yes"})
_FALSE = frozenset({"0", "false", "no"})
_MAX_ANGLE_DEG = 180.0
_POINT_COLUMNS = ("x", "y", "z")
_VECTOR_DIM = 3


@dataclass(frozen=True)
class SourceSpan:
    """Rows ``[start, start + count)`` of an ``Observations`` came from ``path``."""

    path: str
    start: int
    count: int


@dataclass(frozen=True)
class Observations:
    """Landmark match records: one entry per (localization, trunk landmark).

    Angles in radians; ``inlier`` is bool. ``sources`` maps row ranges back to files.
    """

    alpha: NDArray[np.float64]
    theta: NDArray[np.float64]
    inlier: NDArray[np.bool_]
    t_ns: NDArray[np.int64]
    leaf_id: NDArray[np.int64]
    trunk_id: NDArray[np.int64]
    landmark_id: NDArray[np.int64]
    range_m: NDArray[np.float64]
    sources: tuple[SourceSpan, ...] = ()

    def __len__(self) -> int:
        return int(self.alpha.shape[0])

    @property
    def source_names(self) -> str:
        """Comma-separated file names (for messages)."""
        return ", ".join(s.path for s in self.sources) or "<memory>"

    def frame_groups(self) -> NDArray[np.int64]:
        """Integer group per row: one group per (source file, t_ns) localization."""
        file_idx = np.zeros(len(self), dtype=np.int64)
        for k, span in enumerate(self.sources):
            file_idx[span.start : span.start + span.count] = k
        _, groups = np.unique(np.stack([file_idx, self.t_ns]), axis=1, return_inverse=True)
        return groups.reshape(-1)

    def take(self, index: NDArray[Any]) -> Observations:
        """Subset by boolean mask or integer index (``sources`` are dropped)."""
        return Observations(
            self.alpha[index],
            self.theta[index],
            self.inlier[index],
            self.t_ns[index],
            self.leaf_id[index],
            self.trunk_id[index],
            self.landmark_id[index],
            self.range_m[index],
            (),
        )

    def describe(self) -> dict[str, Any]:
        """Summary for model files and reports (angles in degrees)."""
        n = len(self)
        return {
            "files": [{"path": s.path, "rows": s.count} for s in self.sources],
            "n_observations": n,
            "n_inliers": int(self.inlier.sum()),
            "n_localizations": int(np.unique(self.frame_groups()).size) if n else 0,
            "parallax_deg_range": [float(np.degrees(self.alpha.min())), float(np.degrees(self.alpha.max()))]
            if n
            else None,
            "view_deg_range": [float(np.degrees(self.theta.min())), float(np.degrees(self.theta.max()))]
            if n
            else None,
        }

    @staticmethod
    def concatenate(parts: Sequence[Observations]) -> Observations:
        """Join several observation sets, keeping their source spans."""
        if not parts:
            raise InputDataError("no observations given")
        spans: list[SourceSpan] = []
        offset = 0
        for part in parts:
            spans.extend(SourceSpan(s.path, s.start + offset, s.count) for s in part.sources)
            offset += len(part)

        def cat(name: str) -> NDArray[Any]:
            return np.concatenate([getattr(p, name) for p in parts])

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


@dataclass(frozen=True)
class _Table:
    path: Path
    names: list[str]
    cols: dict[str, list[str]]
    lines: list[int]  # file line number of each data row

    def where(self, k: int) -> str:
        return f"{self.path}, line {self.lines[k]}"

#: a path position farther than this from the frame origin (m) is a unit or data error
MAX_POSITION_M = 1e7


def _read_table(path: Path, required: Sequence[str]) -> _Table:
    """Columns of a CSV file as lists of stripped strings, after checking the header."""
    try:
        with path.open(newline="") as fh:
            reader = csv.reader(fh)
            header = next(reader, None)
            if header is None:
                raise InputDataError(f"{path}: empty file (no header line)")
            names = [h.strip() for h in header]
            missing = [c for c in required if c not in names]
            if missing:
                raise InputDataError(
                    f"{path}: missing column(s) {', '.join(missing)} (header has: {', '.join(names)})"
                )
            index = {name: names.index(name) for name in names}
            cols: dict[str, list[str]] = {name: [] for name in names}
            lines: list[int] = []
            for row in reader:
                lineno = reader.line_num
                if not row or all(not cell.strip() for cell in row):
                    continue
                lines.append(lineno)
                if len(row) != len(names):
                    raise InputDataError(f"{path}, line {lineno}: {len(row)} fields, header has {len(names)}")
                for name, k in index.items():
                    cols[name].append(row[k].strip())
    except OSError as err:
        raise InputDataError(f"{path}: cannot read ({err.strerror or err})") from None
    except UnicodeDecodeError:
        raise InputDataError(f"{path}: not a text CSV file") from None
    return _Table(path, names, cols, lines)


def _first_bad(values: list[str], convert: Any) -> int:
    for k, v in enumerate(values):
        try:
            convert(v)
        except (ValueError, TypeError):
            return k
    return -1


def _floats(table: _Table, name: str) -> NDArray[np.float64]:
    values = table.cols[name]
    try:
        return np.array([float(v) if v else math.nan for v in values], dtype=np.float64)
    except ValueError:
        k = _first_bad(values, lambda v: float(v) if v else 0.0)
        raise InputDataError(f"{table.where(k)}: column {name}: not a number: {values[k]!r}") from None


def _ints(table: _Table, name: str) -> NDArray[np.int64]:
    values = table.cols[name]
    try:
        return np.array([int(v) for v in values], dtype=np.int64)
    except (ValueError, OverflowError):
        k = _first_bad(values, int)
        raise InputDataError(f"{table.where(k)}: column {name}: not an integer: {values[k]!r}") from None


def _bools(table: _Table, name: str) -> NDArray[np.bool_]:
    values = table.cols[name]
    out = np.empty(len(values), dtype=bool)
    for k, v in enumerate(values):
        low = v.lower()
        if low in _TRUE:
            out[k] = True
        elif low in _FALSE:
            out[k] = False
        else:
            raise InputDataError(f"{table.where(k)}: column {name}: expected 0/1, got {v!r}")
    return out


def read_landmarks_csv(path: str | Path) -> Observations:
    """Read one ``landmarks.csv`` file (see module docstring) into ``Observations``.

    Raises ``InputDataError`` for a missing file, missing columns, unparsable or NaN angles,
    angles outside [0, 180] degrees, labels other than 0/1, and files without data rows.
    """
    p = Path(path)
    table = _read_table(p, LANDMARK_COLUMNS)
    n = len(table.lines)
    if n == 0:
        raise InputDataError(f"{p}: no data rows")
    ints = {name: _ints(table, name) for name in _INT_COLUMNS}
    angles = {}
    for name in _ANGLE_COLUMNS:
        deg = _floats(table, name)
        bad = ~np.isfinite(deg)
        if bad.any():
            k = int(np.argmax(bad))
            raise InputDataError(f"{table.where(k)}: column {name} is {table.cols[name][k] or 'empty'!r}")
        out = (deg < 0.0) | (deg > _MAX_ANGLE_DEG)
        if out.any():
            k = int(np.argmax(out))
            raise InputDataError(f"{table.where(k)}: column {name} = {deg[k]} outside [0, 180] deg")
        angles[name] = np.radians(deg)
    inlier = _bools(table, "inlier")
    range_m = _floats(table, "range_m")
    return Observations(
        angles["parallax_deg"],
        angles["view_deg"],
        inlier,
        ints["t_ns"],
        ints["leaf_id"],
        ints["trunk_id"],
        ints["landmark_id"],
        range_m,
        (SourceSpan(str(p), 0, n),),
    )


def read_landmarks_csvs(paths: Sequence[str | Path]) -> Observations:
    """Read and concatenate several ``landmarks.csv`` files."""
    if not paths:
        raise InputDataError("no landmarks.csv files given")
    return Observations.concatenate([read_landmarks_csv(p) for p in paths])


def write_landmarks_csv(path: str | Path, obs: Observations) -> None:
    """Write ``Observations`` in the ``landmarks.csv`` format (angles in degrees)."""
    with Path(path).open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(LANDMARK_COLUMNS)
        a_deg = np.degrees(obs.alpha)
        t_deg = np.degrees(obs.theta)
        for k in range(len(obs)):
            w.writerow(
                [
                    int(obs.t_ns[k]),
                    int(obs.leaf_id[k]),
                    int(obs.trunk_id[k]),
                    int(obs.landmark_id[k]),
                    int(obs.inlier[k]),
                    repr(float(a_deg[k])),
                    repr(float(t_deg[k])),
                    repr(float(obs.range_m[k])),
                ]
            )


def _finite_matrix(table: _Table, names: Sequence[str]) -> NDArray[np.float64]:
    arr = np.stack([_floats(table, name) for name in names], axis=-1)
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        k = int(np.argmax(bad))
        raise InputDataError(f"{table.where(k)}: non-finite or empty value in {', '.join(names)}")
    return arr


def read_points(path: str | Path) -> NDArray[np.float64]:
    """Landmark positions ``(M, 3)`` (metres, frame ``o``) from a CSV with ``x,y,z`` or a ``.npy``."""
    p = Path(path)
    if p.suffix.lower() == ".npy":
        try:
            arr = np.load(p, allow_pickle=False)
        except (OSError, ValueError) as err:
            raise InputDataError(f"{p}: cannot read .npy ({err})") from None
        arr = np.asarray(arr, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != _VECTOR_DIM:
            raise InputDataError(f"{p}: expected an (M, 3) array, got shape {arr.shape}")
        bad = ~np.isfinite(arr).all(axis=1)
        if bad.any():
            raise InputDataError(f"{p}: non-finite landmark coordinates at row {int(np.argmax(bad))}")
    else:
        arr = _finite_matrix(_read_table(p, _POINT_COLUMNS), _POINT_COLUMNS)
    if arr.shape[0] == 0:
        raise InputDataError(f"{p}: no landmark rows")
    return arr


@dataclass(frozen=True)
class PathPositions:
    """Current-camera positions ``(N, 3)`` (metres, frame ``o``) and yaws ``(N,)`` (radians or None)."""

    positions: NDArray[np.float64]
    yaw: NDArray[np.float64] | None


def read_positions(path: str | Path) -> PathPositions:
    """Camera positions along a path: CSV ``x,y,z[,yaw]`` (yaw radians) or ``x,y,z,yaw_deg``."""
    p = Path(path)
    table = _read_table(p, _POINT_COLUMNS)
    if not table.lines:
        raise InputDataError(f"{p}: no position rows")
    xyz = _finite_matrix(table, _POINT_COLUMNS)
    far = np.abs(xyz).max(axis=1) > MAX_POSITION_M
    if far.any():
        k = int(np.argmax(far))
        raise InputDataError(f"{table.where(k)}: position {xyz[k].tolist()} is beyond {MAX_POSITION_M:g} m "
                             "(metres expected)")
    yaw = None
    if "yaw" in table.names:
        yaw = _finite_matrix(table, ("yaw",))[:, 0]
    elif "yaw_deg" in table.names:
        yaw = np.radians(_finite_matrix(table, ("yaw_deg",))[:, 0])
    return PathPositions(xyz, yaw)
