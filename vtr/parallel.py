"""Threads inside one run: how many to use, working ahead in the background, and at what priority.

``threads`` (``features.threads`` in the configuration, ``--threads`` on the command line) is the
number of threads a run's per-frame work may use; 0 means every core this process may run on.
Everything done in threads here gives results bit-identical to the single-threaded run: the
threads only overlap independent work (left and right images; later frames' decoding, features and
stereo while the caller tracks this one, see ``StereoProcessor.frames``).
"""

from __future__ import annotations

import os
import queue
import sys
import threading
from collections.abc import Generator, Iterable
from typing import TypeVar

from .errors import ConfigError

T = TypeVar("T")

MAX_THREADS = 1024  # upper bound of the ``threads`` setting (0 = every available core)
MAX_NICENESS = 19  # the lowest priority Linux gives a thread
LOOKAHEAD_PER_THREAD = 1  # frames queued ahead of the consumer beyond one per worker (a pair is ~1 MB at KITTI size)


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity, not the machine's total)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # no affinity call on this platform
        return max(1, os.cpu_count() or 1)


def resolve_threads(threads: int, where: str = "features.threads") -> int:
    """The thread count meant by a ``threads`` setting: 0 = every available core, else itself."""
    if not 0 <= threads <= MAX_THREADS:
        raise ConfigError(f"{where}={threads}: must be in 0..{MAX_THREADS} (0 = every core)")
    return available_cores() if threads == 0 else threads


def lookahead_frames(threads: int) -> int:
    """Frames decoded and processed ahead of the consumer with ``threads`` workers: enough that every
    worker has a frame while the consumer works on one."""
    return threads + LOOKAHEAD_PER_THREAD


def background_thread(niceness: int) -> None:
    """Lower the calling thread's scheduling priority by ``niceness`` (0..19, relative to its current
    niceness, at most 19): called by a background thread as it starts, so the thread the others feed
    runs first when the cores are all busy. Linux only (elsewhere a thread has no niceness of its own);
    priority is an optimisation, so a system that refuses it is ignored."""
    if niceness <= 0 or sys.platform != "linux":
        return
    tid = threading.get_native_id()
    try:
        os.setpriority(os.PRIO_PROCESS, tid, min(os.getpriority(os.PRIO_PROCESS, tid) + niceness, MAX_NICENESS))
    except OSError:
        pass


class _End:
    """Marks the end of a prefetched stream (or carries the producer's exception)."""

    def __init__(self, error: BaseException | None = None):
        self.error = error


def prefetch(items: Iterable[T], depth: int) -> Generator[T, None, None]:
    """Iterate ``items`` produced by a background thread that runs up to ``depth`` items ahead.

    With ``depth <= 0`` it is ``iter(items)`` unchanged. Items come out in the same order; an
    exception raised while producing is raised here, at the item where it happened. Closing the
    returned generator early (``break``, an error in the consumer) stops the producer.
    """
    if depth <= 0:
        yield from items
        return
    q: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(item) -> bool:
        while not stop.is_set():
            try:
                q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        try:
            for item in items:
                if not put(item):
                    return
        except BaseException as err:  # noqa: BLE001 - handed to the consumer, raised there
            put(_End(err))
            return
        put(_End())

    worker = threading.Thread(target=produce, name="vtr-prefetch", daemon=True)
    worker.start()
    try:
        while True:
            item = q.get()
            if isinstance(item, _End):
                if item.error is not None:
                    raise item.error
                return
            yield item
    finally:
        stop.set()
        worker.join()
