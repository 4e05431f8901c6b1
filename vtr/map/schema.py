"""SQLite schema of the map file (format version 3, ``vtr.map.store.MAP_FORMAT_VERSION``): the tables ``meta``, ``runs``
(with their lifecycle ``state``), ``vertices`` (the pose index), ``vertex_data`` (the vertex codec's blobs), ``edges``
and ``derived`` (rebuildable data such as ``place_index/<run>``), and the triggers that make vertices, vertex data and
edges append-only and a run's state leave ``running`` once and for all. The contents: docs/map.md, "Contents", "Run
lifecycle" and "Derived data"."""

from __future__ import annotations

MATRIX4_BYTES = 16 * 8
MATRIX6_BYTES = 36 * 8

#: how often each experience (an earlier repeat) gave a later repeat's keyframes inliers (vtr.map.experiences)
USE_TABLE = (
    "CREATE TABLE IF NOT EXISTS experience_use (experience INTEGER NOT NULL, repeat INTEGER NOT NULL, "
    "keyframes INTEGER NOT NULL CHECK (keyframes >= 0), PRIMARY KEY (experience, repeat)) WITHOUT ROWID"
)
USE_SQL = (
    "INSERT INTO experience_use(experience, repeat, keyframes) VALUES (?, ?, ?) "
    "ON CONFLICT(experience, repeat) DO UPDATE SET keyframes = keyframes + excluded.keyframes"
)
DERIVED_TABLE = "CREATE TABLE IF NOT EXISTS derived (key TEXT PRIMARY KEY, data BLOB NOT NULL) WITHOUT ROWID"

SCHEMA = f"""
CREATE TABLE meta (
    key TEXT PRIMARY KEY,
    value TEXT NOT NULL
) WITHOUT ROWID;

CREATE TABLE runs (
    id INTEGER PRIMARY KEY,
    kind TEXT NOT NULL CHECK (kind IN ('teach', 'repeat')),
    privileged INTEGER NOT NULL CHECK (privileged IN (0, 1)),
    source TEXT NOT NULL,
    created TEXT NOT NULL,
    state TEXT NOT NULL DEFAULT 'running' CHECK (state IN ('running', 'finished', 'aborted')),
    reason TEXT NOT NULL DEFAULT '',
    CHECK ((state = 'aborted') = (reason <> ''))
);

CREATE TABLE vertices (
    id INTEGER PRIMARY KEY,
    run INTEGER NOT NULL REFERENCES runs(id),
    idx INTEGER NOT NULL,
    t_ns INTEGER NOT NULL,
    T_world_vertex BLOB NOT NULL CHECK (length(T_world_vertex) = {MATRIX4_BYTES}),
    T_vehicle_sensor BLOB NOT NULL CHECK (length(T_vehicle_sensor) = {MATRIX4_BYTES}),
    n_features INTEGER NOT NULL,
    n_landmarks INTEGER NOT NULL,
    frame_index INTEGER NOT NULL,
    CHECK (id = ((run << 32) | idx) AND idx >= 0 AND idx <= 4294967295)
);

CREATE TABLE vertex_data (
    id INTEGER PRIMARY KEY REFERENCES vertices(id),
    data BLOB NOT NULL
);

CREATE TABLE edges (
    from_id INTEGER NOT NULL REFERENCES vertices(id),
    to_id INTEGER NOT NULL REFERENCES vertices(id),
    kind TEXT NOT NULL CHECK (kind IN ('temporal', 'spatial')),
    T_from_to BLOB NOT NULL CHECK (length(T_from_to) = {MATRIX4_BYTES}),
    covariance BLOB NOT NULL CHECK (length(covariance) = {MATRIX6_BYTES}),
    inliers INTEGER NOT NULL CHECK (inliers >= 0),
    PRIMARY KEY (from_id, to_id, kind),
    CHECK (from_id <> to_id)
) WITHOUT ROWID;

CREATE INDEX edges_by_to ON edges(to_id);

CREATE TRIGGER vertices_append_only_update BEFORE UPDATE ON vertices
BEGIN SELECT RAISE(ABORT, 'map vertices are immutable'); END;
CREATE TRIGGER vertices_append_only_delete BEFORE DELETE ON vertices
BEGIN SELECT RAISE(ABORT, 'map vertices are immutable'); END;
CREATE TRIGGER vertex_data_append_only_update BEFORE UPDATE ON vertex_data
BEGIN SELECT RAISE(ABORT, 'map vertex data is immutable'); END;
CREATE TRIGGER vertex_data_append_only_delete BEFORE DELETE ON vertex_data
BEGIN SELECT RAISE(ABORT, 'map vertex data is immutable'); END;
CREATE TRIGGER edges_append_only_update BEFORE UPDATE ON edges
BEGIN SELECT RAISE(ABORT, 'map edges are immutable'); END;
CREATE TRIGGER edges_append_only_delete BEFORE DELETE ON edges
BEGIN SELECT RAISE(ABORT, 'map edges are immutable'); END;

CREATE TRIGGER runs_fixed BEFORE UPDATE OF id, kind, privileged, source, created ON runs
BEGIN SELECT RAISE(ABORT, 'map runs are immutable (only their state may change)'); END;
CREATE TRIGGER runs_state_final BEFORE UPDATE OF state, reason ON runs WHEN OLD.state <> 'running'
BEGIN SELECT RAISE(ABORT, 'a finished or aborted run cannot be reopened'); END;
CREATE TRIGGER runs_no_delete BEFORE DELETE ON runs
BEGIN SELECT RAISE(ABORT, 'map runs are immutable'); END;

CREATE TRIGGER vertices_only_in_open_run BEFORE INSERT ON vertices
WHEN (SELECT state FROM runs WHERE id = NEW.run) <> 'running'
BEGIN SELECT RAISE(ABORT, 'cannot add a vertex to a finished or aborted run'); END;
CREATE TRIGGER temporal_edges_only_in_open_run BEFORE INSERT ON edges
WHEN NEW.kind = 'temporal' AND (SELECT state FROM runs WHERE id = (NEW.from_id >> 32)) <> 'running'
BEGIN SELECT RAISE(ABORT, 'cannot add a temporal edge to a finished or aborted run'); END;
CREATE TRIGGER spatial_edges_touch_open_run BEFORE INSERT ON edges
WHEN NEW.kind = 'spatial'
    AND (SELECT state FROM runs WHERE id = (NEW.from_id >> 32)) <> 'running'
    AND (SELECT state FROM runs WHERE id = (NEW.to_id >> 32)) <> 'running'
BEGIN SELECT RAISE(ABORT, 'a spatial edge must touch an open run'); END;
"""
