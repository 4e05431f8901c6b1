"""The private map copy of a ``vtr repeat --read-only-map`` (docs/map.md, "Private copies").

The copy lives in a temporary folder named ``vtr-repeat-map-copy-*`` that holds a lock file flocked by the
process using it for as long as it runs; the folder is removed when the repeat ends, however it ends short of
SIGKILL or power loss. A folder left by a killed process is recognised at the next start by its name, its
owner (this user) and its lock, which nobody holds any more, and removed then (:func:`remove_stale_copies`).
"""

from __future__ import annotations

import os
import shutil
import stat
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from ..errors import MapError
from ..map.database import copy_map_read_only

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: no lock, so stale copies are not recognised
    fcntl = None  # type: ignore[assignment]

PREFIX = "vtr-repeat-map-copy-"  # name of a private copy's temporary folder
LOCK_NAME = ".owner.lock"  # flocked by the process using the copy; free once it ended
LOCK_PENDING = ".owner.lock.new"  # the lock file before it is locked (renamed to LOCK_NAME once locked)


def _try_lock(fd: int) -> bool:
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return False
    return True


def remove_stale_copies(root: Path | None = None) -> list[Path]:
    """Remove the private-copy folders in ``root`` (the temporary folder) that this user's processes left when
    they were killed (their lock free); returns them. A folder whose process still runs, another user's, one
    without its lock yet or anything that is not a plain folder is left alone."""
    if fcntl is None:
        return []
    root = Path(tempfile.gettempdir()) if root is None else root
    removed: list[Path] = []
    try:
        entries = [p for p in root.iterdir() if p.name.startswith(PREFIX)]
    except OSError:
        return removed
    for folder in entries:
        try:
            st = folder.lstat()
            if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.getuid():
                continue
            fd = os.open(folder / LOCK_NAME, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
        except OSError:
            continue
        try:
            if _try_lock(fd):
                shutil.rmtree(folder, ignore_errors=True)
                removed.append(folder)
        finally:
            os.close(fd)
    return removed


@contextmanager
def private_copy(map_path: Path) -> Iterator[Path]:
    """A whole copy of ``map_path`` (write-ahead log included, the map only read) in a new private-copy folder,
    locked while the block runs and removed when it ends."""
    folder = Path(tempfile.mkdtemp(prefix=PREFIX))
    fd = -1
    try:
        if fcntl is not None:
            pending = folder / LOCK_PENDING
            fd = os.open(pending, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
            if not _try_lock(fd):
                raise MapError(f"{folder}: cannot lock the private map copy's folder")
            os.rename(pending, folder / LOCK_NAME)  # visible to the cleaner only once locked
        copy = folder / map_path.name
        copy_map_read_only(map_path, copy)
        yield copy
    finally:
        shutil.rmtree(folder, ignore_errors=True)
        if fd >= 0:
            os.close(fd)
