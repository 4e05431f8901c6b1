"""The single-writer lock of a map file: an advisory BSD ``flock`` on the map file itself.

A session that writes a map (``Map.create`` / ``Map.open(..., "a")``) holds an exclusive ``flock``
on the file for as long as it is open; the kernel drops it when the process ends, however it ends
(SIGKILL included). So a second writer is refused at once with one clear line, and a run still
marked ``running`` while nobody holds the lock was left by a killed process (``interrupted``).

``flock`` locks are separate from the POSIX byte-range locks SQLite uses on the same file (Linux,
BSD, macOS), so they do not disturb its locking. But closing *any* descriptor of a file drops
every POSIX lock the process holds on it, SQLite's included (in WAL mode each connection keeps a
shared lock on the file so that no other process folds or deletes the log under it). So the
descriptor lives as long as the ``Map`` and is released after its SQLite connection closed; while
another ``Map`` of this process still has the same file open, releasing only unlocks the ``flock``
and the close waits until the last of them is released (as SQLite does with its own descriptors).
Where ``fcntl`` is missing (Windows) there is no lock and every running run is shown as running.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

from ..errors import MapError

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None  # type: ignore[assignment]


_users: dict[tuple[int, int], int] = {}  # (device, inode) -> MapLocks of this process on it
_deferred: dict[tuple[int, int], list[int]] = {}  # descriptors whose close waits for the last user
_registry = threading.Lock()


def _track(fd: int) -> tuple[int, int]:
    st = os.fstat(fd)
    key = (st.st_dev, st.st_ino)
    with _registry:
        _users[key] = _users.get(key, 0) + 1
    return key


def _close(fd: int, key: tuple[int, int]) -> None:
    """Close ``fd`` now if no other MapLock of this process uses the file, else when the last one goes."""
    with _registry:
        _users[key] -= 1
        if _users[key] > 0:
            _deferred.setdefault(key, []).append(fd)
            return
        del _users[key]
        fds = [*_deferred.pop(key, []), fd]
    for f in fds:
        os.close(f)


class MapLock:
    """An open descriptor on a map file that holds (writer) or probes (reader) its lock."""

    def __init__(self, fd: int, exclusive: bool, key: tuple[int, int]) -> None:
        self._fd: int | None = fd
        self._key = key
        self.exclusive = exclusive

    @classmethod
    def writer(cls, path: Path, fd: int | None = None) -> MapLock:
        """Take the exclusive writer lock of ``path`` (or of the open descriptor ``fd``, which the lock
        then owns); ``MapError`` "another process is writing this map" when someone holds it."""
        if fd is None:
            try:
                fd = os.open(path, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
            except OSError as err:
                raise MapError(f"{path}: cannot open the map ({err.strerror})") from err
        key = _track(fd)
        if fcntl is not None:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                _close(fd, key)
                raise MapError(
                    f"{path}: another process is writing this map (one writer at a time; wait for it to finish)"
                ) from None
            except OSError:
                pass  # a file system without flock: no lock, as on Windows
        return cls(fd, exclusive=True, key=key)

    @classmethod
    def reader(cls, path: Path) -> MapLock:
        """A descriptor to probe the writer lock of ``path`` with (``MapError`` if it cannot be opened)."""
        try:
            fd = os.open(path, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
        except OSError as err:
            raise MapError(f"{path}: cannot read map ({err.strerror})") from err
        return cls(fd, exclusive=False, key=_track(fd))

    def read_head(self, n: int) -> bytes:
        """The first ``n`` bytes of the file, read through this descriptor (opening and closing another
        one would drop the POSIX locks SQLite holds on the file in this process)."""
        assert self._fd is not None
        return os.pread(self._fd, n, 0)

    def writer_alive(self) -> bool:
        """Whether a session (this one when it is the writer) holds the writer lock right now."""
        if self.exclusive:
            return True
        if fcntl is None or self._fd is None:
            return True
        try:
            fcntl.flock(self._fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        except OSError:
            return False  # no flock on this file system (read-only media): nobody can be writing
        fcntl.flock(self._fd, fcntl.LOCK_UN)
        return False

    def release(self) -> None:
        """Close the descriptor (drops the lock). Call after SQLite's connection is closed. Idempotent."""
        if self._fd is None:
            return
        if self.exclusive and fcntl is not None:
            try:
                fcntl.flock(self._fd, fcntl.LOCK_UN)  # the writer lock goes now, even if the close waits
            except OSError:
                pass
        _close(self._fd, self._key)
        self._fd = None
