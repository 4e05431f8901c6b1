"""One batch at a time writes an output folder: ``OUT/.vtr-batch.lock``, an ``flock`` the kernel releases when the
process ends, however. See the README's "Batches" section and ``docs/outputs.md``.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path
from typing import Any

from ...errors import OutputError
from .layout import LOCK_NAME


class BatchLock:
    """``OUT/.vtr-batch.lock`` held (``flock``, exclusive) while a batch writes ``OUT``; a second batch on the
    same folder gets ``OutputError`` at once. The kernel releases it when the process ends, however."""

    def __init__(self, out: Path) -> None:
        self.path = Path(out) / LOCK_NAME
        self.fd: int | None = None

    def __enter__(self) -> BatchLock:
        try:
            self.fd = os.open(
                self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0), 0o644
            )
        except OSError as err:
            raise OutputError(f"{self.path}: cannot open the batch lock ({err.strerror or err})") from None
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(self.fd)
            self.fd = None
            raise OutputError(
                f"--out {self.path.parent}: another vtr batch is writing this folder (it holds "
                f"{LOCK_NAME}); wait for it or choose another --out"
            ) from None
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None
