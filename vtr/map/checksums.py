"""Per-vertex checksums of a map.

An additive table, in this module alone, so the map format stays version 3 and maps
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

"""

from __future__ import annotations

import hashlib
import struct

from ..errors import MapError
from .damage import damaged
from .database import Connection

TABLE = "vertex_checksums"
META_KEY = "checksums"  # meta value on maps created with checksums
META_VALUE = "blake2b-8 v1"
SUM_BYTES = 8

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

ROW_COLUMNS = (
    "v.id, v.run, v.idx, v.t_ns, v.T_world_vertex, v.T_vehicle_sensor, v.n_features, v.n_landmarks, v.frame_index"
)


def _int(v: object) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise TypeError(f"not an integer: {type(v).__name__}")
    return v


def row_sum(
    vid: object,
    run: object,
    idx: object,
    t_ns: object,
    T_wv: object,
    T_vs: object,
    n_features: object,
    n_landmarks: object,
    frame_index: object,
) -> bytes:
    """The checksum of a vertex row (``TypeError`` when a field is not of its stored type)."""
    h = hashlib.blake2b(digest_size=SUM_BYTES, person=b"vtr-vertex-row")
    h.update(
        struct.pack(
            "<7q", _int(vid), _int(run), _int(idx), _int(t_ns), _int(n_features), _int(n_landmarks), _int(frame_index)
        )
    )
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
    raise MapError(
        f"{where}: the map's checksum metadata is damaged ({problem}); the map file was changed after vtr wrote it"
    )


def create(conn: Connection) -> None:
    """Add the checksum table to a new map (inside its creation transaction)."""
    conn.executescript(SCHEMA)
    conn.execute("INSERT INTO meta(key, value) VALUES (?, ?)", (META_KEY, META_VALUE))


def write(
    conn: Connection,
    vid: int,
    run: int,
    idx: int,
    t_ns: int,
    T_wv: bytes,
    T_vs: bytes,
    n_features: int,
    n_landmarks: int,
    frame_index: int,
    blob: bytes,
) -> None:
    """The checksums of a vertex being inserted (same transaction)."""
    conn.execute(
        f"INSERT INTO {TABLE}(id, row_sum, data_sum) VALUES (?, ?, ?)",
        (vid, row_sum(vid, run, idx, t_ns, T_wv, T_vs, n_features, n_landmarks, frame_index), data_sum(vid, blob)),
    )


def verify_rows(conn: Connection, where: str, lo: int, hi: int, data: bool = False) -> int:
    """Check the checksums of the vertices with ids in ``[lo, hi]`` (and their blobs when ``data``); returns
    how many were checked. ``MapError`` naming the first damaged vertex."""
    cols = ROW_COLUMNS + ", c.row_sum, c.data_sum" + (", d.data" if data else "")
    join = " LEFT JOIN vertex_data d ON d.id = v.id" if data else ""
    rows = conn.execute(
        f"SELECT {cols} FROM vertices v LEFT JOIN {TABLE} c ON c.id = v.id{join} "
        "WHERE v.id BETWEEN ? AND ? ORDER BY v.id",
        (lo, hi),
    ).fetchall()
    for r in rows:
        check_row(where, r, data)
    return len(rows)


def check_row(where: str, r: tuple, data: bool) -> None:
    vid = r[0]
    if r[9] is None:
        raise damaged(where, vid, "no checksum")
    try:
        ok = row_sum(*r[:9]) == r[9]
    except (TypeError, struct.error):
        ok = False
    if not ok:
        raise damaged(where, vid, "its pose, time or counts do not match their checksum")
    if data:
        try:
            ok = r[11] is not None and data_sum(int(vid), r[11]) == r[10]
        except TypeError:
            ok = False
        if not ok:
            raise damaged(where, vid, "its features or landmarks do not match their checksum")
