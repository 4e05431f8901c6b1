"""The rules for output paths a command writes, checked before any work starts.

The rule itself (never replace an existing output unless ``--force``; its documented exceptions) is written
once, in :mod:`perception_model.commandline` (shared by the ``vtr`` and ``perception-model`` commands);
these are its ``OutputError`` forms. :func:`check_new_output`: a new output file (``vtr convert`` always
refuses, the other commands replace it with ``--force``). :func:`check_output_folder`: an ``--out`` folder
must be a writable folder, or creatable; one that already holds files is refused unless ``--force``.
"""

from __future__ import annotations

import os
from pathlib import Path

from perception_model.outputs import existing_output

from ..errors import OutputError


def check_new_output(path: Path, force: bool = False, *, can_force: bool = True, empty_folder_ok: bool = False) -> None:
    """Raise ``OutputError`` (one line naming ``path``) when ``path`` exists, unless ``force`` (a file is
    then replaced) or it is an empty folder and ``empty_folder_ok``. A folder is never replaced.
    ``can_force`` says whether the command has ``--force`` (the message offers it)."""
    problem = existing_output(Path(path), force, can_force=can_force, empty_folder_ok=empty_folder_ok)
    if problem is not None:
        raise OutputError(problem)


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
