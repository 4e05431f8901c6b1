"""A repeat's map writes off the frame's thread: :class:`LeafWriter` commits each leaf (:meth:`vtr.map.Map.add_leaf`:
vertex, edges, experience use and localization record in one transaction) in order on a thread of its own, through a
second connection of the map file, so neither the encoding nor the commit's fsync holds up the odometry or the
localization, and their reads of taught vertices never wait for a commit (WAL readers do not wait for the writer).
Between writes it decodes the taught vertices the caller will read next into the map's vertex cache (``prefetch``).

Ordering and durability are those of :meth:`~vtr.map.Map.add_leaf` called in order: each leaf is one
``synchronous=FULL`` transaction, committed in submission order; after a failed one (a full disk) no later one is
written (their futures raise ``CancelledError``), so the vertices in the map are whole and in order. A caller that
hands out a leaf's result only after its future completed (``vtr.navigation.repeat.Repeat.steps``) has handed out
nothing the map does not hold. The caller bounds the queue (the repeat waits for the oldest leaf once it is
``LOCALIZATION_LOOKAHEAD`` frames behind). While a writer is open no other code writes the map; close it first.
"""

from __future__ import annotations

import threading
from concurrent.futures import CancelledError, Future, ThreadPoolExecutor
from types import TracebackType
from typing import TYPE_CHECKING

import numpy as np

from ..errors import MapError
from ..timing import StageTimer
from .database import Connection
from .localizations import Leaf
from .records import VertexRecord

if TYPE_CHECKING:
    from ..types import Keyframe
    from .store import Map


class LeafWriter:
    """Writes leaves of ``map_``'s open run in submission order on one thread, through a second connection (the time
    each takes goes to ``timer``'s ``map_write``). A context manager: leaving it waits for the leaves submitted."""

    def __init__(self, map_: Map, timer: StageTimer | None = None):
        self._map = map_
        self._timer = timer or StageTimer()  # seconds in "map_write" (on the writer thread)
        self._conn: Connection | None = map_.file.second_connection()
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="vtr-map-write")
        self._failed = threading.Event()

    def submit(
        self, run: int, keyframe: Keyframe, leaf: Leaf, T_vehicle_sensor: np.ndarray | None = None
    ) -> Future[VertexRecord]:
        """Queue ``add_leaf(run, keyframe, leaf)``; the future gives the stored vertex once committed, or raises its
        error (``CancelledError`` when an earlier leaf failed or the writer closed before starting it)."""
        return self._pool.submit(self._write, run, keyframe, leaf, T_vehicle_sensor)

    def prefetch(self, vertex_ids: list[int]) -> None:
        """Decode these vertices into the map's vertex cache on the writer thread, between writes, so that the
        caller's next reads of them (a localization's next taught submap) find them decoded. A vertex that cannot
        be read is left alone: the caller's own read reports it."""
        if vertex_ids:
            self._pool.submit(self._prefetch, list(vertex_ids))

    def _prefetch(self, vertex_ids: list[int]) -> None:
        for vid in vertex_ids:
            try:
                self._map.vertex(vid)
            except MapError:
                return

    def _write(self, run: int, keyframe: Keyframe, leaf: Leaf, T_vehicle_sensor: np.ndarray | None) -> VertexRecord:
        if self._failed.is_set():  # an earlier leaf failed: never write a later one
            raise CancelledError()
        try:
            with self._timer("map_write"):
                return self._map.add_leaf(run, keyframe, leaf, T_vehicle_sensor, connection=self._conn)
        except BaseException:
            self._failed.set()
            raise

    def close(self, cancel_pending: bool = False) -> None:
        """Wait for the leaf being written (and, unless ``cancel_pending``, those queued), then close the
        connection. Idempotent."""
        self._pool.shutdown(wait=True, cancel_futures=cancel_pending)
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def __enter__(self) -> LeafWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close(cancel_pending=exc is not None)


__all__ = ["LeafWriter"]
