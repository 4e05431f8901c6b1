"""The rules for output paths a command writes, checked before any work starts.

A new output file or folder (:func:`check_new_output`): never replace an existing one silently.
``vtr convert`` always refuses; ``vtr export-trajectory`` and ``vtr export-map`` replace it only with
``--force``. An output folder that may already exist and receives the command's files
(:func:`check_output_folder`, ``--out`` of ``vtr odometry``/``teach``/``repeat``/``demo``): it must be
a writable folder, or creatable.
"""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import OutputError


def check_new_output(path: Path, force: bool = False, *, can_force: bool = True, empty_folder_ok: bool = False) -> None:
    """Raise ``OutputError`` (one line naming ``path``) when ``path`` exists, unless ``force`` (a file is
    then replaced) or it is an empty folder and ``empty_folder_ok``. A folder is never replaced.
    ``can_force`` says whether the command has ``--force`` (the message offers it)."""
    path = Path(path)
    if not path.exists() and not path.is_symlink():
        return
    if path.is_dir():
        if empty_folder_ok and not any(path.iterdir()):
            return
        raise OutputError(f"{path}: already exists and is a folder (not overwriting)")
    if not force:
        hint = "; pass --force to replace it" if can_force else ""
        raise OutputError(f"{path}: already exists (not overwriting{hint})")


def check_output_folder(path: Path, option: str = "--out") -> None:
    """Raise ``OutputError`` (one line naming ``option`` and ``path``) unless ``path`` is a writable
    folder or can be created (its nearest existing ancestor is a writable folder)."""
    path = Path(path)
    if path.exists():
        if not path.is_dir():
            raise OutputError(f"{option} {path}: exists and is not a folder")
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
