"""The one rule for what a command writes into its output folder (``--out``, a batch's run folders).

- A command writes only inside its output folder, and only files it made there: every name it writes
  is first added to the folder's record (``.vtr-outputs``, one name a line), so a rerun, a batch's
  resume or a cleanup removes exactly those (:meth:`OutputFolder.clear`) and nothing the user put there.
- It never writes through a link it did not make: an entry at an output's name that is a symbolic
  link, a folder, a file with other hard links or a file the record does not hold is refused before
  any work starts (:meth:`OutputFolder.prepare`, one line naming the file). Whole files are written to
  a new temporary name (``O_CREAT | O_EXCL | O_NOFOLLOW``) and renamed over the final name (a rename
  replaces a name, it never follows a link); streamed files are created the same exclusive way.
- It refuses an output folder that contains, or is inside, any of its inputs (``--out DATA`` with the
  recording in ``DATA/route1/teach``).

Every refusal (a writable ``--out``, never replacing an output without ``--force``, an output folder apart
from the inputs, no link on the way into a run folder) is :mod:`vtr.io.outputs`'s, vtr's one owner of the rule,
built on :mod:`perception_model.outputs`'s primitives; this folder adds its record (``tests/test_output_rule.py``
ties the two). See ``docs/outputs.md``.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import stat
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import IO, Any

from perception_model.outputs import TMP_TAG, create_exclusive, entry_problem, replace_text, temporary_name

from ..errors import OutputError
from ..io.outputs import check_apart
from ..map.database import SIDE_FILES

RECORD = ".vtr-outputs"  # the names this folder's commands made, one a line
__all__ = ["RECORD", "TMP_TAG", "OutputFolder"]
_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
_CLOEXEC = getattr(os, "O_CLOEXEC", 0)


def _is_safe_name(name: str) -> bool:
    return bool(name) and "/" not in name and "\0" not in name and name not in (".", "..")


class OutputFolder:
    """An output folder and the record of what vtr made in it; see the module doc."""

    def __init__(self, path: Path, option: str = "--out"):
        self.path = Path(path)
        self.option = option
        self.made = self._read_record()

    # ------------------------------------------------------------------ opening

    @classmethod
    def prepare(
        cls, path: Path, inputs: Iterable[Path | None] = (), names: Iterable[str] = (), option: str = "--out"
    ) -> OutputFolder:
        """The folder ``path`` (created if needed) after checking it is apart from ``inputs`` and that
        every output ``names`` can be written without touching what vtr did not make there."""
        path = Path(path)
        check_apart(path, inputs, option)
        try:
            path.mkdir(parents=True, exist_ok=True)
        except FileExistsError:
            raise OutputError(f"{option} {path}: exists and is not a folder") from None
        except OSError as err:
            raise OutputError(f"{option} {path}: cannot create the folder ({err.strerror})") from None
        folder = cls(path, option)
        for name in names:
            folder.check_writable(name)
        return folder

    def _read_record(self) -> set[str]:
        p = self.path / RECORD
        try:
            fd = os.open(p, os.O_RDONLY | _NOFOLLOW | _CLOEXEC)
        except FileNotFoundError:
            return set()
        except OSError as err:
            raise OutputError(
                f"{p}: cannot read the record of vtr's outputs ({err.strerror or err}; a symbolic "
                "link?); remove it or choose another folder"
            ) from None
        with os.fdopen(fd, "rb") as f:
            text = f.read(1 << 20).decode("utf-8", "replace")
        return {line for line in text.splitlines() if _is_safe_name(line)}

    def _record(self, name: str) -> None:
        if name in self.made:
            return
        p = self.path / RECORD
        try:
            fd = os.open(p, os.O_WRONLY | os.O_APPEND | os.O_CREAT | _NOFOLLOW | _CLOEXEC, 0o644)
        except OSError as err:
            raise OutputError(
                f"{p}: cannot write the record of vtr's outputs ({err.strerror or err}; a symbolic link?)"
            ) from None
        with os.fdopen(fd, "ab") as f:
            f.write(f"{name}\n".encode())
        self.made.add(name)

    # ------------------------------------------------------------------ checks

    def check_writable(self, name: str) -> None:
        """``OutputError`` (one line naming the file) unless ``name`` is absent, or a plain file vtr made."""
        if not _is_safe_name(name):
            raise OutputError(f"{self.path}: {name!r} is not a file name")
        p = self.path / name
        try:
            st = os.lstat(p)
        except FileNotFoundError:
            return
        what = entry_problem(p)  # the rule's own words: a link, a folder, not a regular file
        if what is None:
            if name in self.made:
                return  # vtr's own earlier output: replaced by a rename, never written through
            what = "has other hard links" if st.st_nlink > 1 else f"was not made by vtr here (not in {RECORD})"
        raise OutputError(f"{p}: {what}; not writing through or over it (remove it or choose another {self.option})")

    # ------------------------------------------------------------------ reading back

    def own_file(self, name: str) -> Path | None:
        """``name`` for reading back (a resume, ``batch --fit``): its path when it is a regular file vtr made here
        (in the record, no other hard links), None when absent. Anything else (a symbolic link planted at
        ``landmarks.csv``, a file vtr did not make) is an ``OutputError`` naming it: vtr reads back only what
        it wrote."""
        p = self.path / name
        try:
            st = os.lstat(p)
        except FileNotFoundError:
            return None
        what = entry_problem(p)
        if what is None and st.st_nlink > 1:
            what = "has other hard links"
        if what is None and name not in self.made:
            what = f"was not made by vtr here (not in {RECORD})"
        if what is not None:
            raise OutputError(
                f"{p}: {what}; vtr reads back only the files it made (not reading it: remove it to run this again)"
            )
        return p

    def read_own(self, name: str, limit: int = 1 << 26) -> bytes | None:
        """The bytes of :meth:`own_file` ``name`` (None when absent), opened without following a link."""
        p = self.own_file(name)
        if p is None:
            return None
        try:
            fd = os.open(p, os.O_RDONLY | _NOFOLLOW | _CLOEXEC)
        except OSError as err:
            raise OutputError(f"{p}: cannot read it ({err.strerror or err})") from None
        with os.fdopen(fd, "rb") as f:
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                raise OutputError(f"{p}: is not a regular file; not reading it")
            return f.read(limit)

    def _remove_own(self, name: str) -> None:
        self.check_writable(name)
        with _ignore_missing():
            os.unlink(self.path / name)

    # ------------------------------------------------------------------ writing

    def write(self, name: str, writer: Callable[..., Any], *args: Any, **kwargs: Any) -> Path:
        """Whole-file output: ``writer(tmp_path, *args, **kwargs)`` writes a new temporary file, renamed to
        ``name`` when it returns (so ``name`` is the old content or the new one, never a half-written file,
        and never a file a link pointed to). Returns the final path."""
        self.check_writable(name)
        tmp_name = temporary_name(name)
        tmp = self.path / tmp_name
        self._record(tmp_name)
        os.close(self._create(tmp))
        try:
            writer(tmp, *args, **kwargs)
            if entry_problem(tmp) is not None:
                raise OutputError(f"{tmp}: replaced by something else while vtr wrote it")
            self._record(name)
            os.replace(tmp, self.path / name)
        except BaseException:
            with _ignore_missing():
                os.unlink(tmp)
            raise
        return self.path / name

    def write_text(self, name: str, text: str) -> Path:
        return self.write(name, lambda p: Path(p).write_text(text))

    def open(self, name: str, newline: str | None = "") -> IO[str]:
        """A streamed text output, created exclusively (an earlier file of vtr's at that name is removed first)."""
        return os.fdopen(self.create(name, keep_open=True), "w", newline=newline)

    def create(self, name: str, keep_open: bool = False) -> Any:
        """Create ``name`` empty and exclusively (``O_EXCL | O_NOFOLLOW``) for a writer that opens it by path;
        returns the path (or, with ``keep_open``, the file descriptor)."""
        self._remove_own(name)
        self._record(name)
        fd = self._create(self.path / name)
        if keep_open:
            return fd
        os.close(fd)
        return self.path / name

    def claim(self, name: str) -> Path:
        """Record ``name`` for a file the caller creates exclusively itself (a map: ``Map.create``)."""
        self.check_writable(name)
        self._record(name)
        return self.path / name

    def _create(self, p: Path) -> int:
        try:
            return create_exclusive(p)
        except FileExistsError:
            raise OutputError(f"{p}: appeared while vtr was writing (another process?); not writing over it") from None
        except OSError as err:
            raise OutputError(f"{p}: cannot create it ({err.strerror or err})") from None

    # ------------------------------------------------------------------ whole entries of a command's own

    def claim_entries(self, names: Iterable[str]) -> None:
        """For a command that rewrites whole entries (files or folders, ``vtr demo``): every ``names`` that exists
        must be one vtr made here (in the record; never a symbolic link), else ``OutputError`` naming it before
        anything is touched; then all are recorded. A user's ``route.vtrmap`` or ``aerial/teach/`` is refused,
        never removed."""
        names = list(names)
        for name in names:
            if not _is_safe_name(name):
                raise OutputError(f"{self.path}: {name!r} is not a file name")
            p = self.path / name
            if not p.exists() and not p.is_symlink():
                continue
            what = (
                "is a symbolic link"
                if p.is_symlink()
                else (None if name in self.made else f"was not made by vtr here (not in {RECORD})")
            )
            if what is not None:
                raise OutputError(f"{p}: {what}; not replacing it (move it away or choose another {self.option})")
        for name in names:
            self._record(name)

    def remove_entry(self, name: str) -> None:
        """Remove entry ``name`` that vtr made here (a file, with a map's SQLite side files, or a whole folder);
        ``OutputError`` for anything vtr did not make (see :meth:`claim_entries`)."""

        self.claim_entries([name])
        p = self.path / name
        if p.is_dir():
            shutil.rmtree(p)
        else:
            for n in (name, *(name + s for s in SIDE_FILES)):
                self._unlink_regular(self.path / n)

    # ------------------------------------------------------------------ replacing a finished run

    def adopt(self, staged: OutputFolder, last: Iterable[str] = ()) -> None:
        """Move the complete outputs of ``staged`` (a run built beside this folder) in, replacing this folder's own
        files of the same names, then remove this folder's other own files; ``staged`` is removed when empty.
        Each file moves by one rename (never half a file); ``last`` are moved after every other file, in that
        order (``run.json`` last: until it moves, this folder still says which run it holds). Files vtr did not
        make here are kept, and a link or a file vtr did not make at an incoming name stops the move
        (``OutputError``) before anything is replaced."""

        staged.made, self.made = staged._read_record(), self._read_record()  # other writers recorded files too
        last = [n for n in last if n in staged.made]
        incoming = sorted(n for n in staged.made if not n.startswith(TMP_TAG) and n not in last) + last
        incoming = [n for n in incoming if staged.own_file(n) is not None]
        for name in incoming:
            self.check_writable(name)
        for name in incoming:
            self._record(name)
            for side in SIDE_FILES:  # an old map's SQLite files never meet the new map
                self._unlink_regular(self.path / (name + side))
            os.replace(staged.path / name, self.path / name)
        for name in sorted(self.made - set(incoming)):
            if name == RECORD:
                continue
            for n in (name, *(name + s for s in SIDE_FILES)):
                self._unlink_regular(self.path / n)
        self._write_record(set(incoming))
        staged.clear()
        with contextlib.suppress(OSError):
            staged.path.rmdir()  # kept when something else is in it

    def _write_record(self, names: set[str]) -> None:
        replace_text(self.path / RECORD, "".join(f"{n}\n" for n in sorted(names)))
        self.made = set(names)

    @staticmethod
    def _unlink_regular(p: Path) -> None:
        try:
            st = os.lstat(p)
        except FileNotFoundError:
            return
        if stat.S_ISREG(st.st_mode):
            with _ignore_missing():
                os.unlink(p)

    # ------------------------------------------------------------------ cleanup

    def clear(self) -> None:
        """Remove every file vtr made here (as recorded; a map with its SQLite side files), then the record.
        Nothing else is touched: entries that are links or folders are left alone."""

        for name in sorted(self.made):
            for n in (name, *(name + s for s in SIDE_FILES)):
                p = self.path / n
                try:
                    st = os.lstat(p)
                except FileNotFoundError:
                    continue
                if stat.S_ISREG(st.st_mode):
                    with _ignore_missing():
                        os.unlink(p)
        with _ignore_missing():
            st = os.lstat(self.path / RECORD)
            if stat.S_ISREG(st.st_mode):
                os.unlink(self.path / RECORD)
        self.made = set()

    def is_empty(self) -> bool:
        return not any(self.path.iterdir())


def _ignore_missing() -> contextlib.suppress:
    return contextlib.suppress(FileNotFoundError)
