"""The output rule of every command, as a check the libraries can call too (no click, nothing from ``vtr``).

Never replace an existing output unless ``--force``; see :mod:`perception_model.commandline` for the
conventions of both console scripts and the documented exceptions.
"""

from __future__ import annotations

from pathlib import Path


def existing_output(path: Path, force: bool, *, folder: bool = False, option: str | None = None,
                    can_force: bool = True, empty_folder_ok: bool = False) -> str | None:
    """Why ``path`` may not be written, as one line, or None when it may.

    A file (``folder=False``): refused when anything exists at ``path``, unless ``force`` and it is a
    file (a folder is never replaced by a file); an empty folder is accepted when ``empty_folder_ok``.
    An output folder (``folder=True``): refused when ``path`` is a folder holding files, unless ``force``,
    or is not a folder. ``option`` names the command-line option in the message; ``can_force`` says
    whether the command has ``--force`` (the message then offers it).
    """
    path = Path(path)
    name = f"{option} {path}" if option else str(path)
    hint = "; pass --force to replace it" if can_force else ""
    if not path.exists() and not path.is_symlink():
        return None
    if folder:
        if not path.is_dir():
            return f"{name}: exists and is not a folder"
        if force or not any(path.iterdir()):
            return None
        hint = "; pass --force to write into it" if can_force else ""
        return f"{name}: already exists and holds files (not overwriting{hint})"
    if path.is_dir():
        if empty_folder_ok and not any(path.iterdir()):
            return None
        return f"{name}: already exists and is a folder (not overwriting)"
    if force and can_force:
        return None
    return f"{name}: already exists (not overwriting{hint})"
