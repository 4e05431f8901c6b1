"""A CSV file declared by its columns: one schema gives the header, the writer's number formats and the
reader's types and checks, so a run file's format is written once (:mod:`vtr.app.runfiles`).

A :class:`CsvSchema` is a tuple of :class:`Column` (name, kind, write format, unit). Writing formats each
value with its column's format (``format(value, spec)``; an empty cell for None); reading checks the
header and parses every column into a numpy array of its kind, with one-line errors naming the file, the
line and the column. Rows are written with the schema's line end (``csv.writer`` writes ``\\r\\n``); a text cell
holding a comma, a quote or a line break is quoted as ``csv.writer`` quotes it. An ``optional`` column may be empty
(None): it is read as an object array with None there.
"""

from __future__ import annotations

import csv
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Literal

import numpy as np

from ..errors import DataError

Kind = Literal["int", "float", "bool", "str"]
_DTYPES = {"int": np.int64, "float": np.float64, "bool": np.bool_, "str": object}
_PARSE = {"int": int, "float": float, "str": str}
_QUOTE_IF = (",", '"', "\r", "\n")  # csv.writer's minimal quoting (delimiter, quote, line breaks)


@dataclass(frozen=True)
class Column:
    """One column: its header name, kind (``int``, ``float``, ``bool`` written 0/1, ``str``), the format spec
    its values are written with (``""``: ``str(value)``), its unit (for documentation) and whether a cell may be
    empty (``optional``: None)."""

    name: str
    kind: Kind = "float"
    spec: str = ""
    unit: str = ""
    optional: bool = False

    def text(self, value: Any) -> str:
        """The cell of ``value`` (empty for None)."""
        if value is None:
            return ""
        if self.kind == "bool":
            return "1" if value else "0"
        if self.kind == "int":
            return format(int(value), self.spec)
        if self.kind == "float":
            return format(float(value), self.spec)
        text = str(value)
        if any(c in text for c in _QUOTE_IF):
            return '"' + text.replace('"', '""') + '"'
        return text

    def parse(self, cells: Sequence[str], where: Path, first_line: int) -> np.ndarray:
        """The column's cells as an array of its kind; ``DataError`` naming the file, line and column."""
        if self.optional and self.kind != "bool":
            return self._parse_optional(cells, where, first_line)
        if self.kind == "str":
            return np.array(cells, dtype=object)
        if self.kind == "bool":
            bad = [i for i, c in enumerate(cells) if c not in ("0", "1")]
            if bad:
                raise DataError(f"{where}:{first_line + bad[0]}: column {self.name}: {cells[bad[0]]!r} is not 0 or 1")
            return np.array([c == "1" for c in cells], bool)
        try:
            return np.array(cells, dtype=_DTYPES[self.kind]) if cells else np.zeros(0, _DTYPES[self.kind])
        except ValueError:
            for i, c in enumerate(cells):
                try:
                    _DTYPES[self.kind](c)
                except ValueError:
                    raise DataError(
                        f"{where}:{first_line + i}: column {self.name}: {c!r} is not "
                        f"{'an integer' if self.kind == 'int' else 'a number'}"
                    ) from None
            raise DataError(f"{where}: column {self.name}: unreadable values") from None

    def _parse_optional(self, cells: Sequence[str], where: Path, first_line: int) -> np.ndarray:
        """An object array: None for an empty cell, else the value of the column's kind."""
        out = np.empty(len(cells), dtype=object)
        parse = _PARSE[self.kind]
        for i, c in enumerate(cells):
            try:
                out[i] = None if c == "" else parse(c)
            except ValueError:
                raise DataError(
                    f"{where}:{first_line + i}: column {self.name}: {c!r} is not "
                    f"{'an integer' if self.kind == 'int' else 'a number'}"
                ) from None
        return out


@dataclass(frozen=True)
class CsvSchema:
    """The columns of one CSV file, in the order they are written, and its line end."""

    what: str  # the file's name in messages ("localization.csv")
    columns: tuple[Column, ...]
    line_end: str = "\r\n"

    @property
    def header(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.columns)

    def row(self, values: Sequence[Any]) -> str:
        """One line (with its line end) of ``values``, one per column."""
        return ",".join(c.text(v) for c, v in zip(self.columns, values, strict=True)) + self.line_end

    def header_line(self) -> str:
        return ",".join(self.header) + self.line_end

    def write(self, path: str | Path, rows: Iterable[Sequence[Any]]) -> None:
        """The whole file: header and ``rows`` (for a new path; atomic writes go through the output folder)."""
        with open(path, "w", newline="") as f:
            f.write(self.header_line())
            f.writelines(self.row(r) for r in rows)

    def writer(self, file: IO[str]) -> CsvRowWriter:
        """A row writer on an open text file (opened with ``newline=""``); writes the header now."""
        return CsvRowWriter(self, file)

    def read(self, path: str | Path) -> dict[str, np.ndarray]:
        """Every column of the file at ``path`` as an array of its kind; ``DataError`` (one line naming the file)
        on a wrong header, a short row or a cell that is not of its column's kind."""
        path = Path(path)
        try:
            with open(path, newline="") as f:
                rows = list(csv.reader(f))
        except UnicodeDecodeError:
            raise DataError(f"{path}: not a text file (expected a {self.what})") from None
        if not rows or tuple(rows[0]) != self.header:
            raise DataError(f"{path}: not a {self.what} (header {','.join(self.header)})")
        body = [r for r in rows[1:] if r]
        short = [i for i, r in enumerate(body) if len(r) != len(self.columns)]
        if short:
            raise DataError(f"{path}:{short[0] + 2}: {len(body[short[0]])} cells, the header has {len(self.columns)}")
        cells = list(zip(*body, strict=True)) if body else [()] * len(self.columns)
        return {c.name: c.parse(list(cells[j]), path, 2) for j, c in enumerate(self.columns)}


class CsvRowWriter:
    """Appends rows of a :class:`CsvSchema` to an open file, flushed after each (readable while a run goes on)."""

    def __init__(self, schema: CsvSchema, file: IO[str]):
        self.schema = schema
        self._file = file
        file.write(schema.header_line())

    def write(self, values: Sequence[Any]) -> None:
        self._file.write(self.schema.row(values))
        self._file.flush()


__all__ = ["Column", "CsvRowWriter", "CsvSchema"]
