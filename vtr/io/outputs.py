"""May vtr write here: the one owner in ``vtr`` of the output rule, every refusal as one ``OutputError`` line.

Built on :mod:`perception_model.outputs` (the primitives both console scripts share: never replace an existing
output unless ``--force``; never write through a link or over an input, with or without it; whole files written
beside and renamed). :func:`check_new_output` / :func:`write_output`: one output file (``vtr convert`` and the bag
writer always refuse, the other commands replace it with ``--force``); :func:`check_output_folder`: an ``--out``
folder; :func:`check_apart`: an output folder apart from the inputs; :func:`check_no_links`: no link on the way
into a run folder. The CLI, the batch, ``OutputFolder`` (:mod:`vtr.app.outputs`, the record of what vtr made) and
the writers call these. See ``docs/outputs.md``.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from perception_model.outputs import existing_output, replace_file

from ..errors import OutputError


def check_new_output(
    path: Path,
    force: bool = False,
    *,
    can_force: bool = True,
    empty_folder_ok: bool = False,
    inputs: Iterable[Path | None] = (),
) -> None:
    """Raise ``OutputError`` (one line naming ``path``) when ``path`` exists, unless ``force`` (a regular file
    is then replaced) or it is an empty folder and ``empty_folder_ok``. A folder, a symbolic link, anything
    not a regular file, and any of ``inputs`` are never replaced. ``can_force`` says whether the command has
    ``--force`` (the message offers it)."""
    problem = existing_output(Path(path), force, can_force=can_force, empty_folder_ok=empty_folder_ok, inputs=inputs)
    if problem is not None:
        raise OutputError(problem)


def write_output(
    path: Path, writer: Callable[[Path], Any], force: bool = False, *, inputs: Iterable[Path | None] = ()
) -> Path:
    """Write output file ``path`` by the rule: checked again (:func:`check_new_output`: the checks before the
    work ran may be minutes old), then ``writer(tmp)`` writes a temporary file beside it, renamed over
    ``path`` when complete (:func:`perception_model.outputs.replace_file`)."""
    inputs = tuple(inputs)
    check_new_output(path, force, inputs=inputs)
    return replace_file(path, writer)


def check_output_folder(path: Path, option: str = "--out", force: bool = True) -> None:
    """Raise ``OutputError`` (one line naming ``option`` and ``path``) unless ``path`` is a writable
    folder or can be created (its nearest existing ancestor is a writable folder); a folder that holds
    files is refused unless ``force``."""
    path = Path(path)
    if path.exists():
        problem = existing_output(path, force, folder=True, option=option)
        if problem is not None:
            raise OutputError(problem)
        if not os.access(path, os.W_OK | os.X_OK):
            raise OutputError(f"{option} {path}: folder is not writable")
        return
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise OutputError(f"{option} {path}: {parent} is not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"{option} {path}: cannot create it ({parent} is not writable)")


def _inside(a: Path, b: Path) -> bool:
    """``a`` is ``b`` or below it (both resolved)."""
    return a == b or b in a.parents


def check_apart(out: Path, inputs: Iterable[Path | None], option: str = "--out") -> None:
    """``OutputError`` when output folder ``out`` contains, is, or is inside an input (symlinks resolved)."""
    o = Path(out).resolve()
    for inp in inputs:
        if inp is None:
            continue
        i = Path(inp).resolve()
        if _inside(i, o):
            raise OutputError(
                f"{option} {out}: contains the input {inp} (an output folder must be apart from "
                "the data it reads; choose another folder)"
            )
        if _inside(o, i) and i.is_dir():
            raise OutputError(
                f"{option} {out}: is inside the input {inp} (an output folder must be apart from "
                "the data it reads; choose another folder)"
            )


def check_no_links(base: Path, folder: Path, option: str = "--out") -> None:
    """``OutputError`` when a folder between ``base`` (excluded) and ``folder`` (included) is a symbolic link
    (or not a folder): a run folder inside an output folder is made by vtr, a link there is not."""
    base, folder = Path(base), Path(folder)
    rel = folder.relative_to(base)
    p = base
    for part in rel.parts:
        p = p / part
        try:
            st = os.lstat(p)
        except FileNotFoundError:
            return
        if stat.S_ISLNK(st.st_mode):
            raise OutputError(
                f"{option} {base}: {p} is a symbolic link that vtr did not make (not writing through "
                "it); remove it or choose another folder"
            )
        if not stat.S_ISDIR(st.st_mode):
            raise OutputError(f"{option} {base}: {p} exists and is not a folder")
