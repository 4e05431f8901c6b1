"""The write rule of every file the distribution writes, owned here (no click, nothing from ``vtr``).

Both console scripts and the libraries (``perception_model`` and ``vtr``) use these primitives; ``vtr``'s forms
(:mod:`vtr.io.outputs`, :class:`vtr.app.outputs.OutputFolder`) build on them and ``tests/test_output_rule.py``
ties the two. The rule, for every output file, with or without ``--force``:

- never replace an existing output unless ``--force`` (:func:`existing_output`);
- never write through or over a symbolic link, a folder, or anything that is not a regular file
  (:func:`entry_problem`);
- never write over one of the command's own inputs (``inputs=``: the same file, by any name or link);
- write whole files to a new temporary name beside the output, created exclusively without following links
  (:func:`create_exclusive`), and rename it over the output when complete (:func:`replace_file`): a rename
  replaces a name and never follows a link, and the output is the old content or the new, never half.

See :mod:`perception_model.commandline` for the conventions of both console scripts and the documented
exceptions; docs/outputs.md describes the rule and its owner.
"""

from __future__ import annotations

import os
import secrets
import stat
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

#: Temporary names: ``<TMP_TAG><hex>-<name>`` beside the output, renamed to ``<name>`` when complete
#: (the suffix is kept: writers that choose a format by extension, matplotlib and open3d, still see it).
TMP_TAG = ".vtr-tmp-"
_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
_CLOEXEC = getattr(os, "O_CLOEXEC", 0)


def entry_problem(path: Path) -> str | None:
    """What is at ``path`` that no output may be written through or over, as words (``"is a symbolic link"``,
    ``"is a folder"``, ``"is not a regular file"``), or None when nothing is there or it is a regular file.
    The link itself is examined (``lstat``), never its target."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return None
    if stat.S_ISLNK(st.st_mode):
        return "is a symbolic link"
    if stat.S_ISDIR(st.st_mode):
        return "is a folder"
    if not stat.S_ISREG(st.st_mode):
        return "is not a regular file"
    return None


def input_clash(path: Path, inputs: Iterable[Path | str | None]) -> Path | None:
    """The input among ``inputs`` that ``path`` names (the same file by any name, hard or symbolic link), or None."""
    path = Path(path)
    try:
        out_st = os.stat(path)
    except OSError:
        out_st = None
    resolved = path.resolve()
    for inp in inputs:
        if inp is None:
            continue
        inp = Path(inp)
        if inp.resolve() == resolved:
            return inp
        if out_st is not None:
            try:
                st = os.stat(inp)
            except OSError:
                continue
            if (st.st_dev, st.st_ino) == (out_st.st_dev, out_st.st_ino):
                return inp
    return None


def existing_output(
    path: Path,
    force: bool,
    *,
    folder: bool = False,
    option: str | None = None,
    can_force: bool = True,
    empty_folder_ok: bool = False,
    inputs: Iterable[Path | str | None] = (),
) -> str | None:
    """Why ``path`` may not be written, as one line, or None when it may.

    A file (``folder=False``): refused when it names one of ``inputs``, or a symbolic link, a folder or a
    non-regular file is there (with or without ``force``); an existing regular file is refused unless
    ``force``. An empty folder is accepted when ``empty_folder_ok`` (a writer that fills a folder).
    An output folder (``folder=True``): refused when ``path`` is not a folder, or holds files, unless
    ``force``. ``option`` names the command-line option in the message; ``can_force`` says whether the
    command has ``--force`` (the message then offers it).
    """
    path = Path(path)
    name = f"{option} {path}" if option else str(path)
    hint = "; pass --force to replace it" if can_force else ""
    clash = input_clash(path, inputs)
    if clash is not None:
        return f"{name}: is the input {clash} (not writing over an input, with or without --force)"
    if not path.exists() and not path.is_symlink():
        return None
    if folder:
        if not path.is_dir():
            return f"{name}: exists and is not a folder"
        if force or not any(path.iterdir()):
            return None
        hint = "; pass --force to write into it" if can_force else ""
        return f"{name}: already exists and holds files (not overwriting{hint})"
    what = entry_problem(path)
    if what == "is a folder":
        if empty_folder_ok and not any(path.iterdir()):
            return None
        return f"{name}: already exists and is a folder (not overwriting)"
    if what is not None:
        return (
            f"{name}: {what}; not writing through or over it, with or without --force (remove it or choose "
            "another path)"
        )
    if force and can_force:
        return None
    return f"{name}: already exists (not overwriting{hint})"


def create_exclusive(path: Path, mode: int = 0o644) -> int:
    """A new file at ``path``, opened for writing, that did not exist before and is not a link
    (``O_CREAT | O_EXCL | O_NOFOLLOW``): its file descriptor. ``FileExistsError`` when anything is there."""
    return os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | _NOFOLLOW | _CLOEXEC, mode)


def temporary_name(name: str) -> str:
    """A fresh temporary name for output ``name`` (same folder, same suffix)."""
    return f"{TMP_TAG}{secrets.token_hex(4)}-{name}"


def replace_file(path: Path | str, writer: Callable[[Path], Any]) -> Path:
    """Write ``path`` whole: ``writer(tmp)`` writes a new temporary file beside it (created exclusively, never a
    link), which is renamed over ``path`` when ``writer`` returns; on any error the temporary file is removed
    and ``path`` is untouched (its folder must exist). Never follows a link at ``path`` (a rename replaces the
    name); callers refuse a link there first (:func:`existing_output`) so that a user's link is not silently
    replaced either.
    ``OSError`` when the folder cannot be written or ``writer`` left something other than a regular file."""
    path = Path(path)
    tmp = path.parent / temporary_name(path.name)
    failed: OSError | None = None
    try:
        os.close(create_exclusive(tmp))
    except OSError as err:
        failed = err
    if failed is not None:  # named after the output (its folder is missing, not writable...)
        raise OSError(failed.errno, failed.strerror, str(path))
    try:
        writer(tmp)
        if entry_problem(tmp) is not None:
            raise OSError(0, "replaced by something else while it was written", str(tmp))
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path


def replace_text(path: Path | str, text: str) -> Path:
    """:func:`replace_file` with ``text`` as the content."""
    return replace_file(path, lambda p: Path(p).write_text(text))
