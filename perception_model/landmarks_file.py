"""The ``landmarks.csv`` format: one schema, one in-memory record, one writer, one reader.

This module owns the file that ``vtr repeat`` writes and ``perception-model fit`` reads: one row
per taught landmark in the leaf camera's view per localization. Columns (``SCHEMA``):

=================  =======  ======================================================================
column             type     meaning
=================  =======  ======================================================================
``t_ns``           int64    time of the localization (leaf keyframe), nanoseconds
``leaf_id``        int64    repeat vertex id
``trunk_id``       int64    taught vertex id
``landmark_id``    int64    feature index of the landmark in the trunk vertex
``inlier``         0/1      the landmark was a localization inlier (``true``/``false``,
                            ``yes``/``no`` are read too)
``parallax_deg``   float    parallax angle, **degrees** in [0, 180]
``view_deg``       float    view angle, **degrees** in [0, 180]
``range_m``        float    distance from the leaf camera, metres (may be empty: informational)
``matched``        0/1      the landmark was matched at all (optional column; empty = unknown)
=================  =======  ======================================================================

Angles are degrees in the file and radians everywhere in code (``Observations.alpha`` /
``theta``): the writer and the reader are the only places that convert. Columns may come in any
order; extra columns are ignored; ``matched`` may be missing (files written before it existed).

Two containers: CSV (``*.csv``, the default) and Parquet (``*.parquet``, same column names and
units, typed columns). Reading is columnar (pyarrow, imported on first use): only the requested
columns, numeric dtypes, streamed in blocks, never a Python object per cell. A CSV that the fast
reader refuses (or whose values fail the checks) is re-read by a strict streaming reader whose
only job is the one-line error naming the file, line and column — the same messages as ever.
Parquet errors name the file, data row (1-based) and column.

``Observations`` is the one in-memory record: ``vtr`` builds it for each localization and hands
it to ``LandmarksWriter``; the reader returns it; the fits consume it.
"""

from __future__ import annotations

import csv
from array import array
from collections.abc import Collection, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import InputDataError
from .inputs import input_problem
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
_BY_NAME = {c.name: c for c in SCHEMA}
_BY_FIELD = {c.field: c for c in SCHEMA}
#: Columns every landmarks file must have (header check).
LANDMARK_COLUMNS = tuple(c.name for c in SCHEMA if c.required)
#: ``Observations`` fields a fit needs (groups by ``t_ns``, labels, both angles).
FIT_FIELDS = ("t_ns", "inlier", "alpha", "theta")
ALL_FIELDS = tuple(c.field for c in SCHEMA)
_TRUE = ("1", "true", "yes")
_FALSE = ("0", "false", "no")
_MAX_ANGLE_DEG = 180.0
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

    __repr__ = short_repr        # arrays by shape: print(record) stays short

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
            "view_deg_range": [float(np.degrees(self.theta.min())), float(np.degrees(self.theta.max()))]
            if n
            else None,
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


def _is_parquet(path: Path) -> bool:
    return path.suffix.lower() == PARQUET_SUFFIX


# --------------------------------------------------------------------------- writer
class LandmarksWriter:
    """Appends ``Observations`` blocks to a landmarks file (CSV, or Parquet for ``*.parquet``).

    Use as a context manager. Angles are converted to degrees here and nowhere else; floats are
    written in their shortest round-trip form, so reading gives the same numbers back (up to
    the radian-degree conversion, < 1 ulp). ``leaf_id``/``trunk_id``/``landmark_id``/``range_m``
    must be present; ``matched`` None is written as empty cells.
    """

    def __init__(self, path: str | Path):
        import pyarrow as pa

        self.path = Path(path)
        self.rows = 0
        self._pending: list[Any] = []  # Parquet: batches not yet written as a row group
        self._pending_rows = 0
        self._schema = pa.schema(
            [
                (c.name, pa.int64() if c.kind == "int" else pa.int8() if c.kind == "bool" else pa.float64())
                for c in SCHEMA
            ]
        )
        if _is_parquet(self.path):
            import pyarrow.parquet as pq

            self._writer: Any = pq.ParquetWriter(self.path, self._schema)
        else:
            import pyarrow.csv as pacsv

            # the header is written here (plain names, as every earlier writer did), the rows by pyarrow
            self._file: Any = self.path.open("wb")
            self._file.write((",".join(self._schema.names) + "\n").encode())
            self._writer = pacsv.CSVWriter(
                self._file, self._schema, write_options=pacsv.WriteOptions(include_header=False)
            )

    def write(self, obs: Observations) -> None:
        """Append the rows of ``obs`` (nothing for an empty record)."""
        import pyarrow as pa

        n = len(obs)
        if n == 0:
            return
        values: dict[str, Any] = {}
        for c in SCHEMA:
            x = getattr(obs, c.field)
            if x is None and c.required:
                raise InputDataError(f"{self.path}: cannot write landmarks without {c.field}")
            if x is not None and len(x) != n:
                raise InputDataError(f"{self.path}: {c.field} has {len(x)} rows, alpha has {n}")
            if c.kind == "angle":
                values[c.name] = np.degrees(x)
            elif c.kind == "bool":
                values[c.name] = pa.nulls(n, pa.int8()) if x is None else np.asarray(x, dtype=np.int8)
            else:
                values[c.name] = x
        batch = pa.record_batch(values, schema=self._schema)
        self.rows += n
        if not _is_parquet(self.path):
            self._writer.write_batch(batch)
            return
        self._pending.append(batch)
        self._pending_rows += n
        if self._pending_rows >= PARQUET_ROW_GROUP_ROWS:
            self._flush()

    def _flush(self) -> None:
        import pyarrow as pa

        if self._pending:
            self._writer.write_table(pa.Table.from_batches(self._pending, schema=self._schema))
            self._pending, self._pending_rows = [], 0

    def close(self) -> None:
        """Finish the file (an empty CSV still has its header)."""
        if _is_parquet(self.path):
            self._flush()
        self._writer.close()
        file = getattr(self, "_file", None)
        if file is not None and not file.closed:
            file.close()

    def __enter__(self) -> LandmarksWriter:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, value: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def write_landmarks(path: str | Path, obs: Observations) -> None:
    """Write one ``Observations`` as a landmarks file (CSV, or Parquet for ``*.parquet``)."""
    with LandmarksWriter(path) as w:
        w.write(obs)


# --------------------------------------------------------------------------- reader
def _fields(fields: Collection[str] | None) -> tuple[str, ...]:
    if fields is None:
        return ALL_FIELDS
    unknown = sorted(set(fields) - set(ALL_FIELDS))
    if unknown:
        raise InputDataError(f"unknown landmarks field(s) {', '.join(unknown)} (known: {', '.join(ALL_FIELDS)})")
    return tuple(f for f in ALL_FIELDS if f in fields or f in FIT_FIELDS)


def _check_header(path: Path, names: Sequence[str]) -> None:
    check_unique_columns(path, names)
    missing = [c for c in LANDMARK_COLUMNS if c not in names]
    if missing:
        raise InputDataError(f"{path}: missing column(s) {', '.join(missing)} (header has: {', '.join(names)})")


def check_unique_columns(path: Path, names: Sequence[str]) -> None:
    """``InputDataError`` when a header names a column twice (which one would be read is a guess)."""
    seen: dict[str, int] = {}
    for k, name in enumerate(names):
        if name in seen:
            raise InputDataError(f"{path}: column {name!r} appears twice in the header (columns {seen[name] + 1} "
                                 f"and {k + 1})")
        seen[name] = k


class _Bad(Exception):
    """A block failed a value check: the CSV strict reader finds and names the row."""

    def __init__(self, row: int, message: str):
        super().__init__(message)
        self.row = row
        self.message = message


def _check_block(cols: dict[str, NDArray[Any]], offset: int) -> None:
    """Value checks of one block of converted columns (by file column name); raises ``_Bad``."""
    for name, x in cols.items():
        c = _BY_NAME[name]
        if c.kind == "angle":
            bad = ~np.isfinite(x)
            if bad.any():
                k = int(np.argmax(bad))
                raise _Bad(offset + k, f"column {name} is {str(x[k])!r}")  # nan/inf: empty cells were caught before
            out = (x < 0.0) | (x > _MAX_ANGLE_DEG)
            if out.any():
                k = int(np.argmax(out))
                raise _Bad(offset + k, f"column {name} = {x[k]} outside [0, 180] deg")


def _finish(path: Path, parts: dict[str, list[NDArray[Any]]], n: int, fields: tuple[str, ...]) -> Observations:
    if n == 0:
        raise InputDataError(f"{path}: no data rows")
    got: dict[str, Any] = {}
    for f in fields:
        c = _BY_FIELD[f]
        chunks = parts.get(c.name)
        if chunks is None:  # optional column absent
            got[f] = None
            continue
        x = chunks[0] if len(chunks) == 1 else np.concatenate(chunks)
        chunks.clear()
        if c.kind == "angle":  # the one degree -> radian conversion of the reader
            x = np.radians(x, out=x) if x.flags.writeable else np.radians(x)
        got[f] = x
    return Observations(**got, sources=(SourceSpan(str(path), 0, n),))


def _csv_header(path: Path) -> list[str]:
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:  # a UTF-8 BOM is not a header
            header = next(csv.reader(fh), None)
    except OSError as err:
        raise InputDataError(f"{path}: cannot read ({err.strerror or err})") from None
    except (UnicodeDecodeError, csv.Error):
        raise InputDataError(f"{path}: not a text CSV file") from None
    if header is None:
        raise InputDataError(f"{path}: empty file (no header line)")
    return [h.strip() for h in header]


def _read_csv_fast(path: Path, names: list[str], fields: tuple[str, ...]) -> Observations:
    """Columnar read with pyarrow; raises ``_Bad`` or pyarrow's error when the strict reader must judge."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    wanted = [_BY_FIELD[f].name for f in fields if _BY_FIELD[f].name in names]
    types = {}
    for name in wanted:
        kind = _BY_NAME[name].kind
        types[name] = pa.int64() if kind == "int" else pa.bool_() if kind == "bool" else pa.float64()
    # the strict reader takes any case; these spellings cover what writers produce
    true_values = [v for s in _TRUE for v in (s, s.capitalize(), s.upper())]
    false_values = [v for s in _FALSE for v in (s, s.capitalize(), s.upper())]
    reader = pacsv.open_csv(
        str(path),
        read_options=pacsv.ReadOptions(column_names=names, skip_rows=1, block_size=CSV_BLOCK_BYTES),
        convert_options=pacsv.ConvertOptions(
            include_columns=wanted,
            column_types=types,
            true_values=true_values,
            false_values=false_values,
            null_values=[""],
            strings_can_be_null=False,
        ),
    )
    parts: dict[str, list[NDArray[Any]]] = {name: [] for name in wanted}
    pool = pa.default_memory_pool()
    n = 0
    for batch in reader:
        block: dict[str, NDArray[Any]] = {}
        for name in wanted:
            col = batch.column(name)
            kind = _BY_NAME[name].kind
            if col.null_count:
                if name == "matched":  # unknown in some rows: not recorded
                    parts.pop(name, None)
                    continue
                if kind != "float":
                    k = int(np.argmax(col.is_null().to_numpy(zero_copy_only=False)))
                    raise _Bad(n + k, f"column {name} is empty")
            x = col.to_numpy(zero_copy_only=False)
            if kind == "float" and col.null_count:
                x = np.where(col.is_null().to_numpy(zero_copy_only=False), np.nan, x)
            block[name] = x
        _check_block(block, n)
        for name, x in block.items():
            if name in parts:
                parts[name].append(x)
        n += batch.num_rows
        del batch, block
        pool.release_unused()  # hand parsed-block memory back at once: peak RSS stays near the data size
    obs = _finish(path, parts, n, fields)
    pool.release_unused()
    return obs


# ----------------------------------------------------------------- strict CSV reader (the messages)
def _read_csv_strict(path: Path, fields: tuple[str, ...]) -> Observations:
    """Row-by-row reader with the exact one-line messages (file, line, column); numeric buffers only."""
    wanted = [(_BY_FIELD[f].name, _BY_FIELD[f].kind) for f in fields]
    bufs: dict[str, array[Any]] = {}
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:  # a UTF-8 BOM is not a header
            reader = csv.reader(fh)
            header = next(reader, None)
            if header is None:
                raise InputDataError(f"{path}: empty file (no header line)")
            names = [h.strip() for h in header]
            _check_header(path, names)
            cols = [(name, kind, names.index(name)) for name, kind in wanted if name in names]
            for name, kind, _ in cols:
                bufs[name] = array("q") if kind == "int" else array("b") if kind == "bool" else array("d")
            matched_known = True
            for row in reader:
                line = reader.line_num
                if not row or all(not cell.strip() for cell in row):
                    continue
                if len(row) != len(names):
                    raise InputDataError(f"{path}, line {line}: {len(row)} fields, header has {len(names)}")
                for name, kind, k in cols:
                    v = row[k].strip()
                    if kind == "int":
                        try:
                            bufs[name].append(int(v))
                        except (ValueError, OverflowError):
                            raise InputDataError(
                                f"{path}, line {line}: column {name}: not an integer: {v!r}"
                            ) from None
                    elif kind == "bool":
                        low = v.lower()
                        if low in _TRUE:
                            bufs[name].append(1)
                        elif low in _FALSE:
                            bufs[name].append(0)
                        elif name == "matched" and not v:
                            matched_known = False
                            bufs[name].append(0)
                        else:
                            raise InputDataError(f"{path}, line {line}: column {name}: expected 0/1, got {v!r}")
                    else:
                        try:
                            x = float(v) if v else float("nan")
                        except ValueError:
                            raise InputDataError(f"{path}, line {line}: column {name}: not a number: {v!r}") from None
                        if kind == "angle":
                            if not np.isfinite(x):
                                raise InputDataError(f"{path}, line {line}: column {name} is {v or 'empty'!r}")
                            if x < 0.0 or x > _MAX_ANGLE_DEG:
                                raise InputDataError(f"{path}, line {line}: column {name} = {x} outside [0, 180] deg")
                        bufs[name].append(x)
    except OSError as err:
        raise InputDataError(f"{path}: cannot read ({err.strerror or err})") from None
    except UnicodeDecodeError:
        raise InputDataError(f"{path}: not a text CSV file") from None
    except csv.Error as err:
        raise InputDataError(f"{path}: malformed CSV ({err})") from None
    n = len(bufs["t_ns"])
    parts: dict[str, list[NDArray[Any]]] = {}
    for name, buf in bufs.items():
        if name == "matched" and not matched_known:
            continue
        kind = _BY_NAME[name].kind
        dtype = np.int64 if kind == "int" else np.float64
        column = np.frombuffer(buf, dtype=np.int8).astype(bool) if kind == "bool" else np.frombuffer(buf, dtype=dtype)
        parts[name] = [column.copy()]
    return _finish(path, parts, n, fields)


def read_landmarks_csv_strict(path: str | Path, fields: Collection[str] | None = None) -> Observations:
    """The strict row-by-row CSV reader alone (slow; the reference the columnar reader is tested against)."""
    return _read_csv_strict(Path(path), _fields(fields))


# ----------------------------------------------------------------- Parquet
def _read_parquet(path: Path, fields: tuple[str, ...]) -> Observations:
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        pf = pq.ParquetFile(path)
    except OSError as err:
        if isinstance(err, FileNotFoundError | PermissionError | IsADirectoryError):
            raise InputDataError(f"{path}: cannot read ({err.strerror or err})") from None
        raise InputDataError(f"{path}: not a Parquet file ({' '.join(str(err).split())})") from None
    except pa.ArrowException as err:
        raise InputDataError(f"{path}: not a Parquet file ({' '.join(str(err).split())})") from None
    names = list(pf.schema_arrow.names)
    _check_header(path, names)
    wanted = [_BY_FIELD[f].name for f in fields if _BY_FIELD[f].name in names]
    for name in wanted:
        t = pf.schema_arrow.field(name).type
        kind = _BY_NAME[name].kind
        ok = pa.types.is_integer(t) or (kind == "bool" and pa.types.is_boolean(t))
        if kind in ("angle", "float"):
            ok = ok or pa.types.is_floating(t)
        if not ok:
            raise InputDataError(f"{path}: column {name} has type {t}, expected {kind} values")
    parts: dict[str, list[NDArray[Any]]] = {name: [] for name in wanted}
    n = 0
    try:
        batches: Iterator[Any] = pf.iter_batches(batch_size=PARQUET_BATCH_ROWS, columns=wanted)
        for batch in batches:
            block: dict[str, NDArray[Any]] = {}
            for name in wanted:
                col = batch.column(name)
                kind = _BY_NAME[name].kind
                nulls = col.is_null().to_numpy(zero_copy_only=False) if col.null_count else None
                if nulls is not None and kind in ("int", "bool", "angle") and name != "matched":
                    k = int(np.argmax(nulls))
                    raise InputDataError(f"{path}, row {n + k + 1}: column {name} is empty")
                if nulls is not None and name == "matched":
                    parts.pop(name, None)
                    continue
                x = col.to_numpy(zero_copy_only=False)
                if kind == "int":
                    x = x.astype(np.int64, copy=False)
                elif kind == "bool":
                    y = x.astype(np.int64, copy=False)
                    bad = (y != 0) & (y != 1)
                    if bad.any():
                        k = int(np.argmax(bad))
                        got = x[k].item()
                        raise InputDataError(f"{path}, row {n + k + 1}: column {name}: expected 0/1, got {got!r}")
                    x = y.astype(bool)
                else:
                    x = np.asarray(x, dtype=np.float64)
                    if nulls is not None:
                        x = np.where(nulls, np.nan, x)
                block[name] = x
            try:
                _check_block(block, n)
            except _Bad as bad:
                raise InputDataError(f"{path}, row {bad.row + 1}: {bad.message}") from None
            for name, x in block.items():
                if name in parts:
                    parts[name].append(x)
            n += batch.num_rows
            del batch, block
            pa.default_memory_pool().release_unused()
    except (OSError, pa.ArrowException) as err:
        raise InputDataError(f"{path}: cannot read Parquet data ({' '.join(str(err).split())})") from None
    obs = _finish(path, parts, n, fields)
    pa.default_memory_pool().release_unused()
    return obs


# ----------------------------------------------------------------- front ends
def read_landmarks(path: str | Path, fields: Collection[str] | None = None) -> Observations:
    """Read one landmarks file (CSV, or Parquet for ``*.parquet``) into ``Observations``.

    ``fields``: the ``Observations`` fields to read (``FIT_FIELDS`` are always read); None = all.
    Fields not read are None. Raises ``InputDataError`` (one line naming the file and the line or
    row) for a missing file, missing columns, unparsable values, NaN or empty angles, angles
    outside [0, 180] degrees, labels other than 0/1 and files without data rows.
    """
    import pyarrow as pa

    p = Path(path)
    problem = input_problem(p)
    if problem is not None:
        raise InputDataError(f"{p}: {problem}")
    want = _fields(fields)
    if _is_parquet(p):
        return _read_parquet(p, want)
    names = _csv_header(p)
    _check_header(p, names)
    if len(set(names)) == len(names):
        try:
            return _read_csv_fast(p, names, want)
        except (_Bad, pa.ArrowException, UnicodeDecodeError):
            pass  # the strict reader names the line (or reads what the fast one refuses, e.g. "TrUe")
        except OSError as err:
            raise InputDataError(f"{p}: cannot read ({err.strerror or err})") from None
    return _read_csv_strict(p, want)


def read_landmarks_files(paths: Sequence[str | Path], fields: Collection[str] | None = None) -> Observations:
    """Read and concatenate several landmarks files (CSV and/or Parquet)."""
    if not paths:
        raise InputDataError("no landmarks files given")
    return Observations.concatenate([read_landmarks(p, fields) for p in paths])
