"""Per-stage wall-clock accounting for benchmarks (cheap enough to stay on in production)."""

from __future__ import annotations

import threading
import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager


class StageTimer:
    """Accumulates seconds per named stage: ``with timer("features"): ...``. Safe to share between
    threads: a stage timed on several threads at once sums their seconds."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self._lock = threading.Lock()

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            elapsed = time.perf_counter() - t0
            with self._lock:
                self.seconds[stage] += elapsed

    def reset(self) -> None:
        with self._lock:
            self.seconds.clear()
