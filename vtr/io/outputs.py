"""The one rule for output files and folders a command writes: never replace an existing one
silently. ``vtr convert`` always refuses; ``vtr export-trajectory`` and ``vtr export-map`` replace
it only with ``--force``.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import DataError


def check_new_output(path: Path, force: bool = False, *, can_force: bool = True, empty_folder_ok: bool = False) -> None:
    """Raise ``DataError`` (one line naming ``path``) when ``path`` exists, unless ``force`` (a file is
    then replaced) or it is an empty folder and ``empty_folder_ok``. A folder is never replaced.
    ``can_force`` says whether the command has ``--force`` (the message offers it)."""
    path = Path(path)
    if not path.exists() and not path.is_symlink():
        return
    if path.is_dir():
        if empty_folder_ok and not any(path.iterdir()):
            return
        raise DataError(f"{path}: already exists and is a folder (not overwriting)")
    if not force:
        hint = "; pass --force to replace it" if can_force else ""
        raise DataError(f"{path}: already exists (not overwriting{hint})")
