"""The rules for output paths a command writes, checked before any work starts.

The rule itself (never replace an existing output unless ``--force``; never write through a link or over an
input, with or without it; whole files written beside and renamed) is owned by :mod:`perception_model.outputs`
(shared by the ``vtr`` and ``perception-model`` commands); these are its ``OutputError`` forms.
:func:`check_new_output`: a new output file (``vtr convert`` always refuses, the other commands replace it
with ``--force``); :func:`write_output` writes it by that rule. :func:`check_output_folder`: an ``--out``
folder must be a writable folder, or creatable; one that already holds files is refused unless ``--force``.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from perception_model.outputs import existing_output, replace_file

from ..errors import OutputError


def check_new_output(path: Path, force: bool = False, *, can_force: bool = True, empty_folder_ok: bool = False,
                     inputs: Iterable[Path | None] = ()) -> None:
    """Raise ``OutputError`` (one line naming ``path``) when ``path`` exists, unless ``force`` (a regular file
    is then replaced) or it is an empty folder and ``empty_folder_ok``. A folder, a symbolic link, anything
    not a regular file, and any of ``inputs`` are never replaced. ``can_force`` says whether the command has
    ``--force`` (the message offers it)."""
    problem = existing_output(Path(path), force, can_force=can_force, empty_folder_ok=empty_folder_ok,
                              inputs=inputs)
    if problem is not None:
        raise OutputError(problem)


def write_output(path: Path, writer: Callable[[Path], Any], force: bool = False, *,
                 inputs: Iterable[Path | None] = ()) -> Path:
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
