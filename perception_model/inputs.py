"""What an input file may be: a regular file (never a pipe, a device or a folder, which would block or never end),
and for the small files (a model) a bounded size. Click-free, nothing from ``vtr``; vtr's readers use it too."""

from __future__ import annotations

import os
import stat
from pathlib import Path

#: A model file is an object of a few constants and the fit's report: far below this (a larger one is not a model).
MAX_MODEL_FILE_BYTES = 1 << 24


def input_problem(path: Path | str) -> str | None:
    """Why ``path`` cannot be read as an input file, as words after its name, or None when it is a regular file
    (a link to one is fine: inputs are only read). A named pipe or a device would block or never end."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return "cannot read it (no such file)"
    except OSError as err:
        return f"cannot read it ({err.strerror or err})"
    if stat.S_ISDIR(st.st_mode):
        return "is a folder, not a file"
    if not stat.S_ISREG(st.st_mode):
        kind = (
            "a named pipe"
            if stat.S_ISFIFO(st.st_mode)
            else "a device"
            if (stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode))
            else "a socket or special file"
        )
        return f"is {kind}, not a regular file (not reading it: it could block or never end)"
    return None


def read_small_text(path: Path | str, limit: int) -> str:
    """The text of regular file ``path`` if it holds at most ``limit`` bytes; ``ValueError`` naming the problem
    otherwise (a pipe, a device, too large), ``OSError``/``UnicodeDecodeError`` as raised."""
    problem = input_problem(path)
    if problem is not None:
        raise ValueError(problem)
    with open(path, "rb") as fh:
        data = fh.read(limit + 1)
    if len(data) > limit:
        raise ValueError(f"larger than {limit} bytes (not a file of this kind)")
    return data.decode("utf-8")
