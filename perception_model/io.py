"""Readers of the constraint's input files: landmark positions and camera positions.

(The ``landmarks.csv`` format, its record, writer and reader live in ``landmarks_file``.)

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
from .inputs import input_problem
from .landmarks_file import check_unique_columns

_POINT_COLUMNS = ("x", "y", "z")
_VECTOR_DIM = 3


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
    problem = input_problem(path)
    if problem is not None:
        raise InputDataError(f"{path}: {problem}")
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:  # a UTF-8 BOM is not part of the header
            reader = csv.reader(fh)
            header = next(reader, None)
            if header is None:
                raise InputDataError(f"{path}: empty file (no header line)")
            names = [h.strip() for h in header]
            check_unique_columns(path, names)
            missing = [c for c in required if c not in names]
            if missing:
                raise InputDataError(f"{path}: missing column(s) {', '.join(missing)} (header has: {', '.join(names)})")
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
        problem = input_problem(p)
        if problem is not None:
            raise InputDataError(f"{p}: {problem}")
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
        raise InputDataError(
            f"{table.where(k)}: position {xyz[k].tolist()} is beyond {MAX_POSITION_M:g} m (metres expected)"
        )
    yaw = None
    if "yaw" in table.names:
        yaw = _finite_matrix(table, ("yaw",))[:, 0]
    elif "yaw_deg" in table.names:
        yaw = np.radians(_finite_matrix(table, ("yaw_deg",))[:, 0])
    return PathPositions(xyz, yaw)
