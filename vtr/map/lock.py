"""The single-writer lock of a map file: an advisory BSD ``flock`` on the map file itself.

A session that writes a map (``Map.create`` / ``Map.open(..., "a")``) holds an exclusive ``flock``
on the file for as long as it is open; the kernel drops it when the process ends, however it ends
(SIGKILL included). So a second writer is refused at once with one clear line, and a run still
marked ``running`` while nobody holds the lock was left by a killed process (``interrupted``).

``flock`` locks are separate from the POSIX byte-range locks SQLite uses on the same file (Linux,
BSD, macOS), so they do not disturb its locking. The descriptor is kept open for the lifetime of
the ``Map`` and closed only after SQLite's connection: closing any descriptor of a file drops the
POSIX locks a process holds on it, so probing must not open and close descriptors while SQLite
holds locks. Where ``fcntl`` is missing (Windows) there is no lock and every running run is shown
as running.
"""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import MapError

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None  # type: ignore[assignment]


class MapLock:
    """An open descriptor on a map file that holds (writer) or probes (reader) its lock."""

    def __init__(self, fd: int, exclusive: bool) -> None:
        self._fd: int | None = fd
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
        if fcntl is not None:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                raise MapError(f"{path}: another process is writing this map (one writer at a time; "
                               "wait for it to finish)") from None
            except OSError:
                pass  # a file system without flock: no lock, as on Windows
        return cls(fd, exclusive=True)

    @classmethod
    def reader(cls, path: Path) -> MapLock | None:
        """A descriptor to probe the writer lock of ``path`` with (``None`` if the file cannot be opened)."""
        try:
            return cls(os.open(path, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0)), exclusive=False)
        except OSError:
            return None

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
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
