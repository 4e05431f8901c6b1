"""Damage detection for maps: per-vertex checksums, checks of what a taught path must be, the full check.

**Checksums** (an additive table, in this module alone, so the map format stays version 3 and maps
without it still open): ``vertex_checksums(id, row_sum, data_sum)`` holds, for every vertex written
by a map created with it, an 8-byte BLAKE2b of the vertex row (id, run, index, time, both poses,
counts, frame index) and one of its ``vertex_data`` blob (features, descriptors, landmarks) keyed by
the vertex id. They are written in the vertex's own transaction and verified whenever the row or
the blob is read (poses, times, the taught path, a vertex), so a flipped byte is a ``MapError``
naming the vertex instead of a NaN pose or different inliers. A map created before checksums
existed has no such table (``meta`` has no ``checksums`` key) and is read as before; appending to it
adds none (its files stay readable by the vtr that wrote them). The metadata is checked too
(:func:`checksummed`): the key without the table, the table without the key or an unknown value is
damage, so one renamed key does not turn verification off.

**A taught path** must be finite poses with orthonormal rotations (right-handed, last row 0 0 0 1),
times strictly increasing within each run, and vertices only of runs the runs table holds
(:func:`check_taught_path`, :func:`check_vertex_runs`).

**The full check** (:func:`check_map`, ``vtr map check MAP``): SQLite's own integrity check, the
runs table, every vertex's checksums and blob, the taught path, and every temporal edge against the
poses it joins (catches a moved vertex in a map without checksums too).
"""

from __future__ import annotations

import hashlib
import struct
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..errors import MapError
from .database import Connection

if TYPE_CHECKING:
    from .path import TaughtPath

TABLE = "vertex_checksums"
META_KEY = "checksums"               # meta value on maps created with checksums
META_VALUE = "blake2b-8 v1"
SUM_BYTES = 8
ROTATION_TOL = 1e-6                  # |R'R - I| and |det R - 1| allowed (float64 poses composed many times)
EDGE_TOL_M = 1e-6                    # a temporal edge agrees with its poses to this (metres / unit rotation)

SCHEMA = f"""
CREATE TABLE {TABLE} (
    id INTEGER PRIMARY KEY REFERENCES vertices(id),
    row_sum BLOB NOT NULL CHECK (length(row_sum) = {SUM_BYTES}),
    data_sum BLOB NOT NULL CHECK (length(data_sum) = {SUM_BYTES})
);
CREATE TRIGGER {TABLE}_append_only_update BEFORE UPDATE ON {TABLE}
BEGIN SELECT RAISE(ABORT, 'map checksums are immutable'); END;
CREATE TRIGGER {TABLE}_append_only_delete BEFORE DELETE ON {TABLE}
BEGIN SELECT RAISE(ABORT, 'map checksums are immutable'); END;
"""

ROW_COLUMNS = "v.id, v.run, v.idx, v.t_ns, v.T_world_vertex, v.T_vehicle_sensor, v.n_features, v.n_landmarks, " \
              "v.frame_index"


def _int(v: object) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise TypeError(f"not an integer: {type(v).__name__}")
    return v


def row_sum(vid: object, run: object, idx: object, t_ns: object, T_wv: object, T_vs: object, n_features: object,
            n_landmarks: object, frame_index: object) -> bytes:
    """The checksum of a vertex row (``TypeError`` when a field is not of its stored type)."""
    h = hashlib.blake2b(digest_size=SUM_BYTES, person=b"vtr-vertex-row")
    h.update(struct.pack("<7q", _int(vid), _int(run), _int(idx), _int(t_ns), _int(n_features), _int(n_landmarks),
                         _int(frame_index)))
    if not isinstance(T_wv, bytes) or not isinstance(T_vs, bytes):
        raise TypeError("poses are not blobs")
    h.update(T_wv)
    h.update(T_vs)
    return h.digest()


def data_sum(vid: int, blob: object) -> bytes:
    if not isinstance(blob, bytes):
        raise TypeError("vertex data is not a blob")
    h = hashlib.blake2b(digest_size=SUM_BYTES, person=b"vtr-vertex-data")
    h.update(struct.pack("<q", int(vid)))
    h.update(blob)
    return h.digest()


def checksummed(conn: Connection, where: str) -> bool:
    """Whether the map's vertices carry checksums (then every vertex must have them): its ``meta`` says so and
    the table is there. Neither is a map made before checksums existed; one without the other, or a ``meta``
    value this vtr does not write, is damage (``MapError``): a renamed key must not turn verification off."""
    row = conn.execute("SELECT value FROM meta WHERE key = ?", (META_KEY,)).fetchone()
    table = conn.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = ?", (TABLE,)).fetchone()
    if row is None and table is None:
        return False
    if row is None:
        problem = f"the meta table has no {META_KEY!r} key but the {TABLE} table is present"
    elif table is None:
        problem = f"the meta table says {META_KEY} {row[0]!r} but the {TABLE} table is missing"
    elif row[0] != META_VALUE:
        problem = f"meta {META_KEY!r} is {row[0]!r}, this vtr writes {META_VALUE!r}"
    else:
        return True
    raise MapError(f"{where}: the map's checksum metadata is damaged ({problem}); the map file was changed after "
                   "vtr wrote it")


def create(conn: Connection) -> None:
    """Add the checksum table to a new map (inside its creation transaction)."""
    conn.executescript(SCHEMA)
    conn.execute("INSERT INTO meta(key, value) VALUES (?, ?)", (META_KEY, META_VALUE))


def write(conn: Connection, vid: int, run: int, idx: int, t_ns: int, T_wv: bytes, T_vs: bytes,
          n_features: int, n_landmarks: int, frame_index: int, blob: bytes) -> None:
    """The checksums of a vertex being inserted (same transaction)."""
    conn.execute(f"INSERT INTO {TABLE}(id, row_sum, data_sum) VALUES (?, ?, ?)",
                 (vid, row_sum(vid, run, idx, t_ns, T_wv, T_vs, n_features, n_landmarks, frame_index),
                  data_sum(vid, blob)))


def _damaged(where: str, vid: object, what: str) -> MapError:
    from .records import split_vertex_id

    try:
        run, index = split_vertex_id(int(vid))  # type: ignore[call-overload]
        name = f"vertex {vid} (run {run}, index {index})"
    except (TypeError, ValueError):
        name = f"vertex {vid!r}"
    return MapError(f"{where}: {name} is damaged ({what}); the map file was changed after vtr wrote it "
                    "(`vtr map check` lists what else is)")


def verify_rows(conn: Connection, where: str, lo: int, hi: int, data: bool = False) -> int:
    """Check the checksums of the vertices with ids in ``[lo, hi]`` (and their blobs when ``data``); returns
    how many were checked. ``MapError`` naming the first damaged vertex."""
    cols = ROW_COLUMNS + ", c.row_sum, c.data_sum" + (", d.data" if data else "")
    join = " LEFT JOIN vertex_data d ON d.id = v.id" if data else ""
    rows = conn.execute(f"SELECT {cols} FROM vertices v LEFT JOIN {TABLE} c ON c.id = v.id{join} "
                        "WHERE v.id BETWEEN ? AND ? ORDER BY v.id", (lo, hi)).fetchall()
    for r in rows:
        check_row(where, r, data)
    return len(rows)


def check_row(where: str, r: tuple, data: bool) -> None:
    vid = r[0]
    if r[9] is None:
        raise _damaged(where, vid, "no checksum")
    try:
        ok = row_sum(*r[:9]) == r[9]
    except (TypeError, struct.error):
        ok = False
    if not ok:
        raise _damaged(where, vid, "its pose, time or counts do not match their checksum")
    if data:
        try:
            ok = r[11] is not None and data_sum(int(vid), r[11]) == r[10]
        except TypeError:
            ok = False
        if not ok:
            raise _damaged(where, vid, "its features or landmarks do not match their checksum")


def check_poses(where: str, ids: np.ndarray, T: np.ndarray) -> None:
    """``MapError`` unless every pose is finite, a rotation (orthonormal, det +1) and has last row 0 0 0 1."""
    if len(T) == 0:
        return
    bad = ~np.isfinite(T).all(axis=(1, 2))
    if bad.any():
        raise _damaged(where, int(ids[np.argmax(bad)]), "its pose is not finite")
    R = T[:, :3, :3]
    err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    last = np.abs(T[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1)
    bad = (err > ROTATION_TOL) | (np.abs(det - 1.0) > ROTATION_TOL) | (last > 0)
    if bad.any():
        k = int(np.argmax(bad))
        raise _damaged(where, int(ids[k]), f"its pose is not a rigid transform (|R'R - I| = {err[k]:.3g}, "
                                           f"det R = {det[k]:.6g})")


def check_taught_path(where: str, path: TaughtPath) -> None:
    """What a taught path must be: finite rigid poses, times strictly increasing within each run."""
    from .records import RUN_SHIFT

    check_poses(where, path.ids, path.T_world_vertex)
    run = path.ids >> RUN_SHIFT
    same = run[1:] == run[:-1]
    back = same & (np.diff(path.t_ns) <= 0)
    if back.any():
        k = int(np.argmax(back)) + 1
        raise _damaged(where, int(path.ids[k]), f"its time {int(path.t_ns[k])} ns is not after the previous "
                                                f"vertex's {int(path.t_ns[k - 1])} ns")


def check_path_edges(conn: Connection, where: str, path: TaughtPath) -> None:
    """``MapError`` when a temporal edge between taught vertices disagrees with their poses (``add_vertex``
    computes one from the other: a difference is a moved vertex or a damaged edge, checksums or not)."""
    from ..geometry import inv_T
    from .records import blob_matrix

    if len(path) < 2:
        return
    lo, hi = int(path.ids.min()), int(path.ids.max())
    rows = conn.execute("SELECT from_id, to_id, T_from_to FROM edges WHERE kind = 'temporal' AND from_id BETWEEN ? "
                        "AND ? AND to_id BETWEEN ? AND ?", (lo, hi, lo, hi)).fetchall()
    index = {int(v): i for i, v in enumerate(path.ids)}
    T = path.T_world_vertex
    for a, b, blob in rows:
        i, j = index.get(int(a)), index.get(int(b))
        if i is None or j is None:
            continue
        E = blob_matrix(blob, (4, 4))
        d = np.abs(inv_T(T[i]) @ T[j] - E)
        if not np.isfinite(E).all() or d.max() > EDGE_TOL_M * max(1.0, float(np.abs(E[:3, 3]).max())):
            raise _damaged(where, int(b), f"its pose disagrees with the temporal edge from {a} by "
                                          f"{float(d[:3, 3].max()):.3g} m (a moved vertex or a damaged edge)")


def check_vertex_runs(conn: Connection, where: str) -> None:
    """``MapError`` when a vertex belongs to a run the runs table does not hold, or its id and run disagree."""
    r = conn.execute("SELECT v.id, v.run FROM vertices v LEFT JOIN runs r ON r.id = v.run "
                     "WHERE r.id IS NULL OR v.id <> ((v.run << 32) | v.idx) LIMIT 1").fetchone()
    if r is not None:
        raise _damaged(where, r[0], f"it belongs to run {r[1]!r}, which the runs table does not hold or its id "
                                    "does not encode")


@dataclass(frozen=True)
class CheckReport:
    """What :func:`check_map` looked at."""

    runs: int
    vertices: int
    edges: int
    checksums: bool                    # the map has checksums (created by a vtr with them)


def check_map(m: object) -> CheckReport:
    """The full check of an open map ``m`` (a :class:`vtr.map.Map`); ``MapError`` on the first damage found."""
    from ..geometry import inv_T
    from .records import RUN_SHIFT
    from .store import Map

    assert isinstance(m, Map)
    where = str(m.path)
    with m.file.connection() as conn:
        result = conn.execute("PRAGMA integrity_check").fetchall()
        if [tuple(r) for r in result] != [("ok",)]:
            raise MapError(f"{where}: the SQLite file is damaged ({str(result[0][0]).splitlines()[0]})")
        sums = checksummed(conn, where)
    runs = m.runs()                           # checks the runs table
    check_vertex_runs_of(m)
    n_vertices = 0
    for run in runs:
        ids, T = m.poses(run.id)              # checksums of the rows, when the map has them
        check_poses(where, ids, T)
        _, t = m.timestamps(run.id)
        back = np.diff(t) <= 0
        if back.any():
            raise _damaged(where, int(ids[int(np.argmax(back)) + 1]), "its time is not after the previous vertex's")
        for vid in ids:
            m._read_vertex_uncached(int(vid))  # checksum of the blob, then the codec's checks
        n_vertices += len(ids)
    if any(r.privileged for r in runs):
        check_taught_path(where, m.taught_path())
    edges = m.edges()
    pose: dict[int, np.ndarray] = {}
    for run in runs:
        ids, T = m.poses(run.id)
        pose.update(zip(ids.tolist(), T, strict=True))
    for e in edges:
        if not (np.isfinite(e.T_from_to).all() and np.isfinite(e.covariance).all()):
            raise MapError(f"{where}: {e.kind} edge {e.from_id}->{e.to_id} is damaged (not finite)")
        if e.kind == "temporal":
            if e.from_id >> RUN_SHIFT != e.to_id >> RUN_SHIFT or e.from_id not in pose or e.to_id not in pose:
                raise MapError(f"{where}: temporal edge {e.from_id}->{e.to_id} does not join two vertices of a run")
            d = inv_T(pose[e.from_id]) @ pose[e.to_id] - e.T_from_to
            if np.abs(d).max() > EDGE_TOL_M * max(1.0, float(np.abs(e.T_from_to[:3, 3]).max())):
                raise _damaged(where, e.to_id, f"its pose disagrees with the temporal edge from {e.from_id} by "
                                               f"{float(np.abs(d[:3, 3]).max()):.3g} m (a moved vertex)")
    return CheckReport(len(runs), n_vertices, len(edges), sums)


def check_vertex_runs_of(m: object) -> None:
    from .store import Map

    assert isinstance(m, Map)
    with m.file.connection() as conn:
        check_vertex_runs(conn, str(m.path))
