"""How much of the second core a benchmark on this shared machine can have right now."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np


def second_core_available() -> float:
    """Speed-up of two threads over one on a fixed OpenCV workload (releases the GIL) right now: ~2 on an
    idle 2-core machine, ~1 when other processes take the second core."""
    img = np.random.default_rng(0).integers(0, 255, (1500, 1500), dtype=np.uint8)
    before = cv2.getNumThreads()
    cv2.setNumThreads(1)  # one thread per call: the two calls are the only parallelism

    def work() -> None:
        for _ in range(15):
            cv2.GaussianBlur(img, (31, 31), 5)

    t0 = time.perf_counter()
    work()
    work()
    serial = time.perf_counter() - t0
    with ThreadPoolExecutor(2) as pool:
        t0 = time.perf_counter()
        list(pool.map(lambda _: work(), range(2)))
        parallel = time.perf_counter() - t0
    cv2.setNumThreads(before)
    return serial / parallel
