"""Reading a map's vertices and edges (mixed into :class:`vtr.map.Map`): ids, poses and times of a run, a vertex
decoded (through the map's vertex cache, its checksum verified), the edges. The map file and its rules:
:mod:`vtr.map.store`, docs/map.md."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Iterator
from contextlib import AbstractContextManager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..camera import StereoCamera
from ..errors import MapError
from . import checksums
from .codec import decode_frame
from .database import Connection
from .records import EDGE_KINDS, EdgeRecord, VertexRecord, blob_matrix, check_int, run_range, split_vertex_id


class MapReading:
    """The vertex and edge reads of :class:`vtr.map.Map`."""

    if TYPE_CHECKING:  # what Map provides
        path: Path
        camera: StereoCamera
        _cache: OrderedDict[int, VertexRecord]
        _cache_size: int
        _checksums: bool
        _lock: threading.RLock

        def _db(self) -> AbstractContextManager[Connection]: ...
        def _run_row(self, conn: Connection, run: int) -> tuple: ...

    def has_vertex(self, vid: int) -> bool:
        if int(vid) in self._cache:
            return True
        with self._db() as conn:
            return conn.execute("SELECT 1 FROM vertices WHERE id = ?", (int(vid),)).fetchone() is not None

    __contains__ = has_vertex

    def vertex_ids(self, run: int) -> np.ndarray:
        """(N,) int64 vertex ids of ``run`` in index order."""
        lo, hi = run_range(check_int(run, "run", 0))
        with self._db() as conn:
            self._run_row(conn, run)
            ids = [r[0] for r in conn.execute("SELECT id FROM vertices WHERE id BETWEEN ? AND ? ORDER BY id", (lo, hi))]
        return np.array(ids, dtype=np.int64)

    def poses(self, run: int) -> tuple[np.ndarray, np.ndarray]:
        """``(ids (N,) int64, T_world_vertex (N, 4, 4))`` of a run in index order, from the pose index only."""
        lo, hi = run_range(check_int(run, "run", 0))
        with self._db() as conn:
            self._run_row(conn, run)
            rows = conn.execute(
                "SELECT id, T_world_vertex FROM vertices WHERE id BETWEEN ? AND ? ORDER BY id", (lo, hi)
            ).fetchall()
            if self._checksums:
                checksums.verify_rows(conn, str(self.path), lo, hi)
        return self._pose_arrays(rows)

    @staticmethod
    def _pose_arrays(rows: list[Any]) -> tuple[np.ndarray, np.ndarray]:
        ids = np.array([r[0] for r in rows], dtype=np.int64)
        T = np.frombuffer(b"".join(r[1] for r in rows), dtype="<f8").astype(np.float64).reshape(-1, 4, 4)
        return ids, T

    def timestamps(self, run: int) -> tuple[np.ndarray, np.ndarray]:
        """``(ids (N,) int64, t_ns (N,) int64)`` of a run in index order."""
        lo, hi = run_range(check_int(run, "run", 0))
        with self._db() as conn:
            self._run_row(conn, run)
            rows = conn.execute(
                "SELECT id, t_ns FROM vertices WHERE id BETWEEN ? AND ? ORDER BY id", (lo, hi)
            ).fetchall()
            if self._checksums:
                checksums.verify_rows(conn, str(self.path), lo, hi)
        return (np.array([r[0] for r in rows], dtype=np.int64), np.array([r[1] for r in rows], dtype=np.int64))

    def vertex(self, vid: int, cached: bool = True) -> VertexRecord:
        """The keyframe ``vid`` with its features, checksums verified: decoded once, then served from a bounded LRU
        cache; ``cached=False`` reads it from the file and leaves the cache alone (a full check, a stream)."""
        vid = check_int(vid, "vertex id", 0)
        if not cached:
            return self._read_vertex(vid)
        with self._lock:
            record = self._cache.get(vid)
            if record is not None:
                self._cache.move_to_end(vid)
                return record
            record = self._read_vertex(vid)
            self._cache_put(record)
            return record

    def _read_vertex(self, vid: int) -> VertexRecord:
        with self._db() as conn:
            row = conn.execute(
                "SELECT v.t_ns, v.T_world_vertex, v.T_vehicle_sensor, v.frame_index, d.data FROM vertices v "
                "JOIN vertex_data d ON d.id = v.id WHERE v.id = ?",
                (vid,),
            ).fetchone()
        if row is None:
            run, index = split_vertex_id(vid)
            raise MapError(f"{self.path}: no vertex {vid} (run {run}, index {index}) with data")
        return self._decode_vertex(vid, row)

    def _decode_vertex(self, vid: int, row: tuple[Any, ...]) -> VertexRecord:
        if self._checksums:
            with self._db() as conn:
                checksums.verify_rows(conn, str(self.path), vid, vid, data=True)
        t_ns, T_wv, T_vs, frame_index, data = row
        frame = decode_frame(data, t_ns, frame_index, f"{self.path} vertex {vid}")
        return VertexRecord.of(vid, t_ns, blob_matrix(T_wv, (4, 4)), blob_matrix(T_vs, (4, 4)), frame)

    def _cache_put(self, record: VertexRecord) -> None:
        with self._lock:
            self._cache[record.id] = record
            self._cache.move_to_end(record.id)
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)

    def iter_vertices(self, run: int) -> Iterator[VertexRecord]:
        """Every vertex of a run in index order, streamed (bypasses the cache; memory stays flat)."""
        for vid in self.vertex_ids(run):
            with self._db() as conn:
                row = conn.execute(
                    "SELECT v.t_ns, v.T_world_vertex, v.T_vehicle_sensor, v.frame_index, d.data FROM vertices v "
                    "JOIN vertex_data d ON d.id = v.id WHERE v.id = ?",
                    (int(vid),),
                ).fetchone()
            yield self._decode_vertex(int(vid), row)

    def edges(self, run: int | None = None, kind: str | None = None) -> list[EdgeRecord]:
        """Edges touching ``run`` (either end; all runs when ``None``), optionally of one ``kind``."""
        if kind is not None and kind not in EDGE_KINDS:
            raise MapError(f"edge kind must be one of {EDGE_KINDS}, got {kind!r}")
        sql = "SELECT from_id, to_id, kind, T_from_to, covariance, inliers FROM edges"
        where: list[str] = []
        args: list[int | str] = []
        if run is not None:
            lo, hi = run_range(check_int(run, "run", 0))
            where.append("(from_id BETWEEN ? AND ? OR to_id BETWEEN ? AND ?)")
            args += [lo, hi, lo, hi]
        if kind is not None:
            where.append("kind = ?")
            args.append(kind)
        if where:
            sql += " WHERE " + " AND ".join(where)
        with self._db() as conn:
            if run is not None:
                self._run_row(conn, run)
            rows = conn.execute(sql + " ORDER BY from_id, to_id, kind", args).fetchall()
        return [
            EdgeRecord(
                from_id=int(r[0]),
                to_id=int(r[1]),
                kind=r[2],
                T_from_to=blob_matrix(r[3], (4, 4)),
                covariance=blob_matrix(r[4], (6, 6)),
                inliers=int(r[5]),
            )
            for r in rows
        ]

    def edge(self, from_id: int, to_id: int, kind: str) -> EdgeRecord:
        """The edge ``from_id -> to_id`` of ``kind`` (``MapError`` if absent)."""
        with self._db() as conn:
            r = conn.execute(
                "SELECT from_id, to_id, kind, T_from_to, covariance, inliers FROM edges "
                "WHERE from_id = ? AND to_id = ? AND kind = ?",
                (int(from_id), int(to_id), kind),
            ).fetchone()
        if r is None:
            raise MapError(f"{self.path}: no {kind} edge {from_id}->{to_id}")
        return EdgeRecord(int(r[0]), int(r[1]), r[2], blob_matrix(r[3], (4, 4)), blob_matrix(r[4], (6, 6)), int(r[5]))


__all__ = ["MapReading"]
