"""Writing a map: its runs' lifecycle and the vertices and edges of the open run (mixed into :class:`vtr.map.Map`).

Every write is one transaction (``synchronous=FULL``); a map appends only to its *open run*, and finished and aborted
runs never change (:mod:`vtr.map.store` for the durability and lifecycle rules, docs/map.md "Writing"). A repeat
keyframe goes in with its localization in one transaction (:meth:`MapWriting.add_leaf`,
:mod:`vtr.map.localizations`), from a writer thread when :class:`vtr.map.writer.LeafWriter` commits it.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..camera import StereoCamera
from ..errors import MapError
from ..geometry import inv_T
from . import checksums, localizations
from .codec import encode_frame
from .database import Connection, MapFile, transaction
from .localizations import Leaf
from .records import (
    EDGE_KINDS,
    INDEX_MASK,
    RUN_ABORTED,
    RUN_FINISHED,
    RUN_KINDS,
    RUN_RUNNING,
    RUN_SHIFT,
    VertexRecord,
    blob_matrix,
    check_covariance,
    check_int,
    check_transform,
    matrix_blob,
    one_line_reason,
    run_range,
    split_vertex_id,
    utc_now,
    vertex_id,
)
from .schema import USE_SQL, USE_TABLE

if TYPE_CHECKING:
    from ..types import Keyframe, StereoFrame

INTERRUPTED_REASON = "interrupted: its writing process ended without closing the run (killed?)"


class MapWriting:
    """The writing half of :class:`vtr.map.Map`: runs begun and ended, vertices, keyframes, leaves and edges."""

    if TYPE_CHECKING:  # what Map provides
        path: Path
        camera: StereoCamera
        _file: MapFile
        _compress_level: int
        _checksums: bool
        _generation: int
        _open_run: int | None
        _open_run_privileged: bool
        _open_run_touched: bool
        _aborted: bool

        def _db(self) -> AbstractContextManager[Connection]: ...
        def _tx(self) -> AbstractContextManager[Connection]: ...
        def _check_writable(self) -> None: ...
        def _check_open_run(self, run: int, what: str) -> None: ...
        def _cache_put(self, record: VertexRecord) -> None: ...
        def has_vertex(self, vid: int) -> bool: ...

    def begin_run(self, kind: str, source: str = "", privileged: bool | None = None) -> int:
        """Start a new run (``"teach"`` or ``"repeat"``) and return its id; it becomes the open run.

        Teach runs are privileged (define the path to repeat) unless ``privileged=False``. A run
        this session was writing is finished first; a run left running by a killed process is
        recorded as aborted (interrupted), never as finished.
        """
        self._check_writable()
        if kind not in RUN_KINDS:
            raise MapError(f"run kind must be one of {RUN_KINDS}, got {kind!r}")
        privileged = kind == "teach" if privileged is None else bool(privileged)
        mine = self._open_run if self._open_run_touched else None
        with self._tx() as conn:
            if mine is not None:
                conn.execute("UPDATE runs SET state = ? WHERE id = ? AND state = ?", (RUN_FINISHED, mine, RUN_RUNNING))
            conn.execute(
                "UPDATE runs SET state = ?, reason = ? WHERE state = ?", (RUN_ABORTED, INTERRUPTED_REASON, RUN_RUNNING)
            )
            run = conn.execute("SELECT COALESCE(MAX(id) + 1, 0) FROM runs").fetchone()[0]
            vertex_id(run, 0)  # checks the run id range
            conn.execute(
                "INSERT INTO runs(id, kind, privileged, source, created, state) VALUES (?, ?, ?, ?, ?, ?)",
                (run, kind, int(privileged), str(source), utc_now(), RUN_RUNNING),
            )
        self._open_run, self._open_run_touched = int(run), True
        self._open_run_privileged = privileged
        return int(run)

    def finish_run(self) -> None:
        """Finish the open run now: it is complete and becomes immutable (``close`` does this too)."""
        self._end_open_run(RUN_FINISHED, "")

    def abort_run(self, reason: str) -> None:
        """End the open run as aborted with a one-line ``reason`` (it becomes immutable, and is not a
        complete route: a repeat refuses a taught run that is not finished)."""
        self._end_open_run(RUN_ABORTED, one_line_reason(reason))
        self._aborted = True

    def _end_open_run(self, state: str, reason: str) -> None:
        self._check_writable()
        if self._open_run is None:
            return
        self._set_state(self._open_run, state, reason)

    def _set_state(self, run: int, state: str, reason: str) -> None:
        with self._tx() as conn:
            conn.execute("UPDATE runs SET state = ?, reason = ? WHERE id = ?", (state, reason, run))
        self._open_run = None
        self._open_run_touched = False

    def add_vertex(
        self,
        run: int,
        t_ns: int,
        T_world_vertex: np.ndarray,
        frame: StereoFrame,
        T_vehicle_sensor: np.ndarray | None = None,
    ) -> VertexRecord:
        """Append a stereo frame as the next vertex of the open run ``run`` (no edge); returns the stored record.

        ``T_world_vertex`` (4x4) is the frame's left camera pose in the run's first camera frame;
        ``T_vehicle_sensor`` defaults to the map camera's. The frame is stored through the vertex codec
        (:mod:`vtr.map.codec`: lossless dtype conversion only, else ``MapError``). Odometry keyframes go
        through :meth:`add_keyframe`, which adds their temporal edge in the same transaction.
        """
        return self._add_vertex(run, t_ns, T_world_vertex, frame, T_vehicle_sensor, None)

    def add_keyframe(
        self, run: int, keyframe: Keyframe, T_vehicle_sensor: np.ndarray | None = None, link_previous: bool = True
    ) -> VertexRecord:
        """Append an odometry ``Keyframe`` and its temporal edge from the run's previous vertex, atomically.

        The edge is ``T_prev_vertex = inv(T_world_prev) @ T_world_kf`` from the two stored poses, with the
        keyframe's ``edge_covariance`` and ``edge_inliers``; the covariance must be a valid one (else
        ``MapError``): odometry makes it usable where it produces the keyframe (``vtr.vo``).
        The edge is written when the run already has a vertex and ``link_previous`` is true (pass false
        for the first keyframe of a new odometry session, e.g. after resuming a teach).
        """
        edge = None
        if link_previous:
            edge = (
                check_covariance(keyframe.edge_covariance, "temporal edge covariance"),
                check_int(keyframe.edge_inliers, "temporal edge inliers", 0),
            )
        return self._add_vertex(run, keyframe.frame.t_ns, keyframe.T_world_kf, keyframe.frame, T_vehicle_sensor, edge)

    def add_leaf(
        self,
        run: int,
        keyframe: Keyframe,
        leaf: Leaf,
        T_vehicle_sensor: np.ndarray | None = None,
        *,
        connection: Connection | None = None,
    ) -> VertexRecord:
        """Append a repeat keyframe with its localization, atomically: the vertex and its temporal edge (as
        :meth:`add_keyframe`), the spatial edge of a success (``leaf.spatial``, from this vertex), one keyframe of use
        for each experience it used (``leaf.experience_use``) and its localization record (``leaf.record``), in one
        transaction. A kill at any point leaves all of it or none (:mod:`vtr.map.localizations`).

        The record's ``leaf_id`` is the id the vertex gets (:meth:`next_vertex_id`: the localization runs before the
        write), else ``MapError``. ``connection``: a second connection of this map's file
        (:meth:`vtr.map.database.MapFile.second_connection`) to commit through, from a writer thread
        (:class:`vtr.map.writer.LeafWriter`); by default the map's own."""
        row = leaf.record.row()
        spatial = None
        if leaf.spatial is not None:
            e = leaf.spatial
            to_id = check_int(e.to_id, "spatial edge to_id", 0)
            spatial = (
                to_id,
                matrix_blob(check_transform(e.T_from_to, f"spatial edge ->{to_id} T_from_to")),
                matrix_blob(check_covariance(e.covariance, f"spatial edge ->{to_id} covariance")),
                check_int(e.inliers, "spatial edge inliers", 0),
            )
        use = [(int(x), int(run), 1) for x in leaf.experience_use]

        def extra(conn: Connection, vid: int) -> None:
            if vid != row[0]:
                raise MapError(
                    f"{self.path}: the localization record is for vertex {row[0]}, the keyframe became "
                    f"vertex {vid} (another writer?)"
                )
            if spatial is not None:
                conn.execute(
                    "INSERT INTO edges(from_id, to_id, kind, T_from_to, covariance, inliers) "
                    "VALUES (?, ?, 'spatial', ?, ?, ?)",
                    (vid, *spatial),
                )
            if use:
                conn.execute(USE_TABLE)
                conn.executemany(USE_SQL, use)
            localizations.create(conn)
            localizations.insert(conn, row)

        edge = (
            check_covariance(keyframe.edge_covariance, "temporal edge covariance"),
            check_int(keyframe.edge_inliers, "temporal edge inliers", 0),
        )
        return self._add_vertex(
            run, keyframe.frame.t_ns, keyframe.T_world_kf, keyframe.frame, T_vehicle_sensor, edge, extra, connection
        )

    def _add_vertex(
        self,
        run: int,
        t_ns: int,
        T_world_vertex: np.ndarray,
        frame: StereoFrame,
        T_vehicle_sensor: np.ndarray | None,
        edge: tuple[np.ndarray, int] | None,
        extra: Callable[[Connection, int], None] | None = None,
        connection: Connection | None = None,
    ) -> VertexRecord:
        self._check_writable()
        run = check_int(run, "run", 0)
        self._check_open_run(run, "add_vertex")
        t_ns = check_int(t_ns, "t_ns")
        if not -(2**63) <= t_ns < 2**63:
            raise MapError(
                f"t_ns: {t_ns} does not fit int64 nanoseconds (a time past the year 2262: a damaged "
                "timestamp in the source?)"
            )
        T_wv = check_transform(T_world_vertex, "T_world_vertex")
        T_vs = check_transform(
            self.camera.T_vehicle_sensor if T_vehicle_sensor is None else T_vehicle_sensor, "T_vehicle_sensor"
        )
        encoded = encode_frame(frame, t_ns, self._compress_level)
        lo, hi = run_range(run)
        with self._tx() if connection is None else transaction(connection, self.path) as conn:
            last = conn.execute("SELECT MAX(id) FROM vertices WHERE id BETWEEN ? AND ?", (lo, hi)).fetchone()[0]
            index = 0 if last is None else (int(last) & INDEX_MASK) + 1
            vid = vertex_id(run, index)
            conn.execute(
                "INSERT INTO vertices(id, run, idx, t_ns, T_world_vertex, T_vehicle_sensor, n_features, "
                "n_landmarks, frame_index) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    vid,
                    run,
                    index,
                    t_ns,
                    matrix_blob(T_wv),
                    matrix_blob(T_vs),
                    encoded.n_features,
                    encoded.n_landmarks,
                    encoded.frame.index,
                ),
            )
            conn.execute("INSERT INTO vertex_data(id, data) VALUES (?, ?)", (vid, encoded.blob))
            if self._checksums:
                checksums.write(
                    conn,
                    vid,
                    run,
                    index,
                    t_ns,
                    matrix_blob(T_wv),
                    matrix_blob(T_vs),
                    encoded.n_features,
                    encoded.n_landmarks,
                    encoded.frame.index,
                    encoded.blob,
                )
            if edge is not None and last is not None:
                C, inliers = edge
                T_world_prev = blob_matrix(
                    conn.execute("SELECT T_world_vertex FROM vertices WHERE id = ?", (int(last),)).fetchone()[0], (4, 4)
                )
                T = inv_T(T_world_prev) @ T_wv
                conn.execute(
                    "INSERT INTO edges(from_id, to_id, kind, T_from_to, covariance, inliers) "
                    "VALUES (?, ?, 'temporal', ?, ?, ?)",
                    (int(last), vid, matrix_blob(T), matrix_blob(C), inliers),
                )
            if extra is not None:
                extra(conn, vid)
        self._open_run_touched = True
        if self._open_run_privileged:
            self._generation += 1  # the privileged path grew: drop its caches
        record = VertexRecord.of(vid, t_ns, T_wv, T_vs, encoded.frame)
        self._cache_put(record)
        return record

    def add_edge(
        self, from_id: int, to_id: int, T_from_to: np.ndarray, covariance: np.ndarray, kind: str, inliers: int = 0
    ) -> None:
        """Add an edge; ``T_from_to`` (4x4) maps to-vertex coordinates into the from-vertex frame.

        ``temporal`` edges join consecutive vertices (index i -> i+1) of the open run; ``spatial``
        edges may join any two vertices as long as one of them is in the open run (e.g. a repeat
        vertex to a taught one). Validates SE(3), finiteness and a symmetric PSD 6x6 covariance;
        on any error nothing is written.
        """
        self._check_writable()
        if kind not in EDGE_KINDS:
            raise MapError(f"edge kind must be one of {EDGE_KINDS}, got {kind!r}")
        from_id = check_int(from_id, "from_id", 0)
        to_id = check_int(to_id, "to_id", 0)
        if from_id == to_id:
            raise MapError(f"edge from vertex {from_id} to itself")
        T = check_transform(T_from_to, f"edge {from_id}->{to_id} T_from_to")
        C = check_covariance(covariance, f"edge {from_id}->{to_id} covariance")
        inliers = check_int(inliers, "inliers", 0)
        (run_f, idx_f), (run_t, idx_t) = split_vertex_id(from_id), split_vertex_id(to_id)
        for vid in (from_id, to_id):
            if not self.has_vertex(vid):
                raise MapError(f"{self.path}: no vertex {vid} (run {vid >> RUN_SHIFT}, index {vid & INDEX_MASK})")
        if kind == "temporal":
            if run_f != run_t or idx_t != idx_f + 1:
                raise MapError(
                    f"temporal edge must join consecutive vertices of one run, got "
                    f"({run_f}, {idx_f}) -> ({run_t}, {idx_t})"
                )
            self._check_open_run(run_f, "temporal edge")
        elif self._open_run is None or self._open_run not in (run_f, run_t):
            raise MapError(
                f"{self.path}: spatial edge ({run_f}, {idx_f}) -> ({run_t}, {idx_t}) must touch the "
                f"open run ({self._open_run}); finished runs are immutable"
            )
        with self._db() as conn:
            dup = conn.execute(
                "SELECT 1 FROM edges WHERE from_id = ? AND to_id = ? AND kind = ?", (from_id, to_id, kind)
            ).fetchone()
        if dup:
            raise MapError(f"{self.path}: {kind} edge {from_id}->{to_id} already exists")
        with self._tx() as conn:
            conn.execute(
                "INSERT INTO edges(from_id, to_id, kind, T_from_to, covariance, inliers) VALUES (?, ?, ?, ?, ?, ?)",
                (from_id, to_id, kind, matrix_blob(T), matrix_blob(C), inliers),
            )
        self._open_run_touched = True


__all__ = ["INTERRUPTED_REASON", "MapWriting"]
