"""The ``landmarks.csv`` format (``vtr repeat`` writes it, ``perception-model fit`` reads it): the writer
(``LandmarksWriter``) and the columnar readers (CSV or Parquet through pyarrow, a strict streaming re-read for the
one-line error naming file, line and column) of the schema and the ``Observations`` record that live in
:mod:`perception_model.landmarks_schema` (re-exported here). Columns, units and containers: docs/perception_model.md,
"In code" (The landmarks file)."""

from __future__ import annotations

import csv
from array import array
from collections.abc import Collection, Iterator, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import InputDataError
from .inputs import input_problem
from .landmarks_schema import (  # noqa: F401 - re-exported: the schema and the record belong to the file
    ALL_FIELDS,
    BY_FIELD,
    BY_NAME,
    CSV_BLOCK_BYTES,
    FALSE_WORDS,
    FIT_FIELDS,
    LANDMARK_COLUMNS,
    MAX_ANGLE_DEG,
    PARQUET_BATCH_ROWS,
    PARQUET_ROW_GROUP_ROWS,
    PARQUET_SUFFIX,
    SCHEMA,
    TRUE_WORDS,
    Column,
    Observations,
    SourceSpan,
    is_parquet,
)


# --------------------------------------------------------------------------- writer
class LandmarksWriter:
    """Appends ``Observations`` blocks to a landmarks file (CSV, or Parquet for ``*.parquet``).

    Use as a context manager. Angles are converted to degrees here and nowhere else; floats are
    written in their shortest round-trip form, so reading gives the same numbers back (up to
    the radian-degree conversion, < 1 ulp). ``leaf_id``/``trunk_id``/``landmark_id``/``range_m``
    must be present; ``matched`` None is written as empty cells.
    """

    def __init__(self, path: str | Path):
        import pyarrow as pa  # pyarrow (~0.1 s) on first use, here and below

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
        if is_parquet(self.path):
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
        import pyarrow as pa  # pyarrow on first use

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
        if not is_parquet(self.path):
            self._writer.write_batch(batch)
            return
        self._pending.append(batch)
        self._pending_rows += n
        if self._pending_rows >= PARQUET_ROW_GROUP_ROWS:
            self._flush()

    def _flush(self) -> None:
        import pyarrow as pa  # pyarrow on first use

        if self._pending:
            self._writer.write_table(pa.Table.from_batches(self._pending, schema=self._schema))
            self._pending, self._pending_rows = [], 0

    def close(self) -> None:
        """Finish the file (an empty CSV still has its header)."""
        if is_parquet(self.path):
            self._flush()
        self._writer.close()
        file = getattr(self, "_file", None)
        if file is not None and not file.closed:
            file.close()

    def __enter__(self) -> LandmarksWriter:
        return self

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None, tb: TracebackType | None) -> None:
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
            raise InputDataError(
                f"{path}: column {name!r} appears twice in the header (columns {seen[name] + 1} and {k + 1})"
            )
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
        c = BY_NAME[name]
        if c.kind == "angle":
            bad = ~np.isfinite(x)
            if bad.any():
                k = int(np.argmax(bad))
                raise _Bad(offset + k, f"column {name} is {str(x[k])!r}")  # nan/inf: empty cells were caught before
            out = (x < 0.0) | (x > MAX_ANGLE_DEG)
            if out.any():
                k = int(np.argmax(out))
                raise _Bad(offset + k, f"column {name} = {x[k]} outside [0, 180] deg")


def _finish(path: Path, parts: dict[str, list[NDArray[Any]]], n: int, fields: tuple[str, ...]) -> Observations:
    if n == 0:
        raise InputDataError(f"{path}: no data rows")
    got: dict[str, Any] = {}
    for f in fields:
        c = BY_FIELD[f]
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
    import pyarrow as pa  # pyarrow on first use
    import pyarrow.csv as pacsv

    wanted = [BY_FIELD[f].name for f in fields if BY_FIELD[f].name in names]
    types = {}
    for name in wanted:
        kind = BY_NAME[name].kind
        types[name] = pa.int64() if kind == "int" else pa.bool_() if kind == "bool" else pa.float64()
    # the strict reader takes any case; these spellings cover what writers produce
    true_values = [v for s in TRUE_WORDS for v in (s, s.capitalize(), s.upper())]
    false_values = [v for s in FALSE_WORDS for v in (s, s.capitalize(), s.upper())]
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
            kind = BY_NAME[name].kind
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
    wanted = [(BY_FIELD[f].name, BY_FIELD[f].kind) for f in fields]
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
                            raise InputDataError(f"{path}, line {line}: column {name}: not an integer: {v!r}") from None
                    elif kind == "bool":
                        low = v.lower()
                        if low in TRUE_WORDS:
                            bufs[name].append(1)
                        elif low in FALSE_WORDS:
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
                            if x < 0.0 or x > MAX_ANGLE_DEG:
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
        kind = BY_NAME[name].kind
        dtype = np.int64 if kind == "int" else np.float64
        column = np.frombuffer(buf, dtype=np.int8).astype(bool) if kind == "bool" else np.frombuffer(buf, dtype=dtype)
        parts[name] = [column.copy()]
    return _finish(path, parts, n, fields)


def read_landmarks_csv_strict(path: str | Path, fields: Collection[str] | None = None) -> Observations:
    """The strict row-by-row CSV reader alone (slow; the reference the columnar reader is tested against)."""
    return _read_csv_strict(Path(path), _fields(fields))


# ----------------------------------------------------------------- Parquet
def _read_parquet(path: Path, fields: tuple[str, ...]) -> Observations:
    import pyarrow as pa  # pyarrow on first use
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
    wanted = [BY_FIELD[f].name for f in fields if BY_FIELD[f].name in names]
    for name in wanted:
        t = pf.schema_arrow.field(name).type
        kind = BY_NAME[name].kind
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
                kind = BY_NAME[name].kind
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
    import pyarrow as pa  # pyarrow on first use

    p = Path(path)
    problem = input_problem(p)
    if problem is not None:
        raise InputDataError(f"{p}: {problem}")
    want = _fields(fields)
    if is_parquet(p):
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
