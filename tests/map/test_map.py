"""The on-disk pose-graph map: round trips, durability (SIGKILL), immutability, validation, queries.

Vertices are small synthetic keyframes built from numpy (no images).
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from vtr.camera import StereoCamera
from vtr.config import MapConfig
from vtr.errors import ConfigError, MapError, VtrError
from vtr.geometry import usable_covariance
from vtr.map import MAP_FORMAT_VERSION, EdgeRecord, Map, RunInfo, VertexRecord, split_vertex_id, vertex_id
from vtr.map.placement import landmarks_in_map_frame, poses_in_map_frame
from vtr.types import Features, StereoFrame

CAMERA = StereoCamera(
    fx=718.856,
    fy=718.856,
    cx=607.19,
    cy=185.22,
    baseline=0.537,
    width=1226,
    height=370,
    T_vehicle_sensor=np.array([[0, 0, 1, 0.2], [-1, 0, 0, 0], [0, -1, 0, 1.5], [0, 0, 0, 1.0]]),
)
ARRAYS = ("uv", "octave", "descriptors", "u_right", "points")
KILL_AFTER = 12  # vertices the killed writer must have committed before SIGKILL
SUBPROCESS_TIMEOUT_S = 60


def make_frame(rng: np.random.Generator, n: int, index: int = 0) -> StereoFrame:
    """A keyframe with n features; every third one has no stereo match (NaN u_right and point)."""
    uv = np.column_stack([rng.uniform(0, CAMERA.width, n), rng.uniform(0, CAMERA.height, n)])
    disparity = rng.uniform(1.0, 60.0, n)
    points = CAMERA.triangulate(uv[:, 0], uv[:, 1], disparity)
    u_right = uv[:, 0] - disparity
    u_right[::3] = np.nan
    points[::3] = np.nan
    feats = Features(
        uv, rng.integers(0, 8, n).astype(np.int32), rng.random(n), rng.integers(0, 256, (n, 32), dtype=np.uint8)
    )
    return StereoFrame(t_ns=index * 100_000_000, index=index, features=feats, u_right=u_right, points=points)


def pose(x: float, yaw: float = 0.0, y: float = 0.0) -> np.ndarray:
    """Camera pose: rotation about the camera y axis (down) by yaw, position (x, y, 0)."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T[:3, 3] = [x, y, 0.0]
    return T


def inv(T: np.ndarray) -> np.ndarray:
    return np.linalg.inv(T)


def cov(scale: float = 1e-3) -> np.ndarray:
    A = np.random.default_rng(1).normal(size=(6, 6))
    return scale * (A @ A.T + np.eye(6))


def write_teach(path, n: int = 6, n_features=(40, 0, 25, 40, 40, 40), seed: int = 0):
    """A map with one finished teach run along x; returns the frames and poses written."""
    rng = np.random.default_rng(seed)
    frames, poses = [], []
    with Map.create(path, CAMERA) as m:
        run = m.begin_run("teach", source="synthetic")
        prev = None
        for i in range(n):
            frame = make_frame(rng, n_features[i % len(n_features)], index=2 * i)
            T = pose(float(i), 0.05 * i)
            v = m.add_vertex(run, frame.t_ns, T, frame)
            if prev is not None:
                m.add_edge(prev.id, v.id, inv(prev.T_world_vertex) @ T, cov(), "temporal", inliers=30 + i)
            prev = v
            frames.append(frame)
            poses.append(T)
    return frames, poses


def frame_of(frame: StereoFrame) -> dict[str, np.ndarray]:
    f = frame.features
    return {
        "uv": f.uv,
        "octave": f.octave,
        "descriptors": f.descriptors,
        "u_right": frame.u_right,
        "points": frame.points,
    }


def digest(rec: VertexRecord) -> str:
    h = hashlib.sha256()
    stored = frame_of(rec.frame)
    for name in ARRAYS:
        a = stored[name]
        h.update(f"{name}{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    h.update(rec.T_world_vertex.tobytes())
    return h.hexdigest()


def run_rows_digest(path, run: int) -> str:
    """SHA-256 of every stored row of ``run``: its run row, vertices, vertex data and temporal edges."""
    lo, hi = run << 32, (run << 32) | 0xFFFFFFFF
    con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    h = hashlib.sha256()
    for sql in (
        "SELECT id, kind, privileged, source, created FROM runs WHERE id = ?",
        "SELECT * FROM vertices WHERE run = ? ORDER BY id",
        "SELECT * FROM vertex_data WHERE id >> 32 = ? ORDER BY id",
        "SELECT * FROM edges WHERE kind = 'temporal' AND from_id >> 32 = ? ORDER BY from_id",
    ):
        for row in con.execute(sql, (run,)):
            h.update(repr(row).encode())
    n = con.execute("SELECT COUNT(*) FROM vertices WHERE id BETWEEN ? AND ?", (lo, hi)).fetchone()[0]
    con.close()
    return f"{n}:{h.hexdigest()}"


# ------------------------------------------------------------------ ids


def test_vertex_ids_follow_vtr3():
    assert vertex_id(0, 0) == 0
    assert vertex_id(3, 17) == (3 << 32) | 17
    assert split_vertex_id(vertex_id(5, 4_000_000_000)) == (5, 4_000_000_000)
    for bad in ((-1, 0), (0, -1), (0, 1 << 32), (1 << 31, 0)):
        with pytest.raises(MapError):
            vertex_id(*bad)


# ------------------------------------------------------------------ round trips


def test_round_trip_is_byte_exact(tmp_path):
    path = tmp_path / "teach.vtrmap"
    frames, poses = write_teach(path)
    with Map.open(path) as m:
        assert issubclass(MapError, VtrError)
        assert m.format_version == MAP_FORMAT_VERSION
        assert m.camera.to_dict() == CAMERA.to_dict()
        [info] = m.runs()
        assert info == RunInfo(0, "teach", True, "synthetic", info.created, len(frames), state="finished")
        ids = m.vertex_ids(0)
        assert ids.dtype == np.int64 and ids.tolist() == [vertex_id(0, i) for i in range(len(frames))]
        for i, (vid, frame, T) in enumerate(zip(ids, frames, poses, strict=True)):
            rec = m.vertex(int(vid))
            assert (rec.id, rec.run, rec.index, rec.t_ns, rec.frame.index) == (vid, 0, i, frame.t_ns, frame.index)
            assert rec.T_world_vertex.tobytes() == T.tobytes()
            assert np.array_equal(rec.T_vehicle_sensor, CAMERA.T_vehicle_sensor)
            stored = frame_of(rec.frame)
            assert rec.frame.t_ns == rec.t_ns and not rec.frame.features.response.any()  # responses not stored
            for name, src in frame_of(frame).items():
                got = stored[name]
                assert got.dtype == src.dtype and got.shape == src.shape, name
                assert got.tobytes() == src.tobytes(), name
            assert np.array_equal(rec.landmark_mask, np.isfinite(frame.points).all(axis=1))
            assert not rec.frame.points.flags.writeable  # shared through the cache: read-only
        ids_p, T_p = m.poses(0)
        assert np.array_equal(ids_p, ids) and T_p.tobytes() == np.stack(poses).tobytes()
        edges = m.edges()
        assert len(edges) == len(frames) - 1 and all(isinstance(e, EdgeRecord) for e in edges)
        e = m.edge(int(ids[1]), int(ids[2]), "temporal")
        assert e.T_from_to.tobytes() == (inv(poses[1]) @ poses[2]).tobytes()
        assert e.covariance.tobytes() == cov().tobytes() and e.inliers == 32
        assert m.edges(kind="spatial") == [] and len(m.edges(run=0, kind="temporal")) == len(frames) - 1
        s = m.stats()
        n_feat = sum(len(f.features) for f in frames)
        n_lm = sum(int(np.isfinite(f.points).all(axis=1).sum()) for f in frames)
        assert (s["runs"], s["vertices"], s["edges"], s["features"], s["landmarks"]) == (
            1,
            len(frames),
            len(frames) - 1,
            n_feat,
            n_lm,
        )
        assert s["bytes"] == path.stat().st_size > 0


def test_reopened_in_a_new_process(tmp_path):
    path = tmp_path / "teach.vtrmap"
    write_teach(path)
    with Map.open(path) as m:
        expected = [digest(m.vertex(int(v))) for v in m.taught_path().ids]
    code = textwrap.dedent(f"""
        import hashlib, sys
        sys.path.insert(0, {os.path.dirname(__file__)!r})
        from test_map import digest
        from vtr.map import Map
        with Map.open(sys.argv[1]) as m:
            for v in m.taught_path().ids:
                print(digest(m.vertex(int(v))))
    """)
    r = subprocess.run(
        [sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=SUBPROCESS_TIMEOUT_S
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == expected


WRITER = textwrap.dedent("""
    import sys
    import numpy as np
    sys.path.insert(0, sys.argv[2])
    from test_map import CAMERA, make_frame, pose, cov
    from vtr.map import Map
    rng = np.random.default_rng(0)
    m = Map.create(sys.argv[1], CAMERA)
    run = m.begin_run("teach", source="killed")
    prev = None
    for i in range(100000):
        frame = make_frame(rng, 200, index=i)
        v = m.add_vertex(run, frame.t_ns, pose(0.5 * i), frame)
        if prev is not None:
            m.add_edge(prev.id, v.id, pose(0.5), cov(), "temporal", 50)
        prev = v
        print(v.id, flush=True)
""")


def test_sigkill_mid_teach_keeps_every_committed_vertex(tmp_path):
    path = tmp_path / "killed.vtrmap"
    proc = subprocess.Popen(
        [sys.executable, "-c", WRITER, str(path), os.path.dirname(__file__)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    printed = []
    deadline = time.monotonic() + SUBPROCESS_TIMEOUT_S
    try:
        while len(printed) < KILL_AFTER:
            line = proc.stdout.readline()
            assert line, f"writer died: {proc.stderr.read()}"
            printed.append(int(line))
            assert time.monotonic() < deadline, "writer too slow"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    printed += [int(x) for x in proc.stdout.read().split()]
    proc.stdout.close()
    proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL

    with Map.open(path) as m:  # read-only open recovers the write-ahead log
        stored = m.vertex_ids(0)
        assert set(printed) <= set(stored.tolist())
        assert stored.tolist() == list(range(len(stored)))  # no gap: vertices are atomic
        for vid in stored:
            assert m.vertex(int(vid)).frame.points.shape == (200, 3)
        assert len(m.edges(run=0)) in (len(stored) - 1, len(stored) - 2)
        [info] = m.runs()
        assert info.kind == "teach" and not info.finished
        assert m.taught_path().ids.tolist() == stored.tolist()
    # reopened for appending, the interrupted teach is the open run and continues
    with Map.open(path, "a") as m:
        assert m.open_run == 0
        v = m.add_vertex(0, 10**12, pose(100.0), make_frame(np.random.default_rng(3), 5))
        assert v.index == len(stored)
    with Map.open(path) as m:
        assert m.runs()[0].finished and m.runs()[0].n_vertices == len(stored) + 1


# ------------------------------------------------------------------ refusing bad files


def test_format_version_mismatch_is_refused(tmp_path):
    path = tmp_path / "old.vtrmap"
    write_teach(path, n=2)
    for version in (MAP_FORMAT_VERSION + 1, MAP_FORMAT_VERSION - 1):
        con = sqlite3.connect(path)
        con.execute("UPDATE meta SET value = ? WHERE key = 'format_version'", (str(version),))
        con.commit()
        con.close()
        with pytest.raises(MapError, match=rf"{path.name}.*version {version}.*version {MAP_FORMAT_VERSION}"):
            Map.open(path)
        with pytest.raises(MapError, match="version"):
            Map.open(path, "a")


def test_missing_corrupt_and_foreign_files_are_refused(tmp_path):
    with pytest.raises(MapError, match="no map at .*nothing.vtrmap"):
        Map.open(tmp_path / "nothing.vtrmap")
    with pytest.raises(MapError, match="directory"):
        Map.open(tmp_path)
    junk = tmp_path / "junk.vtrmap"
    junk.write_bytes(b"this is not a database" * 100)
    with pytest.raises(MapError, match="junk.vtrmap is not a vtr map"):
        Map.open(junk)
    (tmp_path / "empty.vtrmap").write_bytes(b"")
    with pytest.raises(MapError, match="empty.vtrmap is not a vtr map"):
        Map.open(tmp_path / "empty.vtrmap")
    other = tmp_path / "other.sqlite"
    con = sqlite3.connect(other)
    con.execute("CREATE TABLE t(x)")
    con.commit()
    con.close()
    with pytest.raises(MapError, match="other.sqlite is not a vtr map"):
        Map.open(other)
    with pytest.raises(MapError, match="mode"):
        Map.open(other, "w")
    # a vtr map whose pages were overwritten: refused on open or on read, naming the file
    bad = tmp_path / "damaged.vtrmap"
    write_teach(bad, n=6)
    data = bytearray(bad.read_bytes())
    data[4096:] = np.random.default_rng(0).integers(0, 256, len(data) - 4096, dtype=np.uint8).tobytes()
    bad.write_bytes(bytes(data))
    with pytest.raises(MapError, match="damaged.vtrmap"), Map.open(bad) as m:
        for v in m.vertex_ids(0):
            m.vertex(int(v))


def test_create_refuses_to_overwrite(tmp_path):
    path = tmp_path / "teach.vtrmap"
    write_teach(path, n=2)
    before = path.read_bytes()
    with pytest.raises(MapError, match="already exists"):
        Map.create(path, CAMERA)
    assert path.read_bytes() == before
    with pytest.raises(ConfigError, match="map.compress_level"):  # an invalid section cannot even be built
        Map.create(tmp_path / "x.vtrmap", CAMERA, MapConfig(compress_level=12))
    assert not (tmp_path / "x.vtrmap").exists()
    with pytest.raises(MapError, match="is a directory: a vtr map is one SQLite file"):
        Map.create(tmp_path, CAMERA)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["teach.vtrmap"]


def test_empty_map_opens_and_has_no_taught_path(tmp_path):
    path = tmp_path / "empty.vtrmap"
    Map.create(path, CAMERA).close()
    with Map.open(path) as m:
        assert m.runs() == [] and m.edges() == []
        assert m.stats()["vertices"] == 0 and landmarks_in_map_frame(m)[0].shape == (0, 3)
        with pytest.raises(MapError, match="map has no taught run"):
            m.taught_path()
    with Map.open(path, "a") as m:
        m.begin_run("repeat")  # a repeat alone is no taught path either
        with pytest.raises(MapError, match="map has no taught run"):
            m.taught_path()


def test_camera_mismatch(tmp_path):
    path = tmp_path / "teach.vtrmap"
    write_teach(path, n=1)
    with Map.open(path) as m:
        m.check_camera(StereoCamera.from_dict(CAMERA.to_dict()))
        other = StereoCamera(fx=700.0, fy=700.0, cx=607.19, cy=185.22, baseline=0.537, width=1226, height=370)
        with pytest.raises(MapError, match="map was taught with another camera: .*fx=718.856.*fx=700"):
            m.check_camera(other)


# ------------------------------------------------------------------ write rules


def test_read_only_refuses_every_write(tmp_path):
    path = tmp_path / "teach.vtrmap"
    frames, _ = write_teach(path, n=3)
    before = path.read_bytes()
    with Map.open(path, "r") as m:
        ids = m.vertex_ids(0)
        for attempt in (
            lambda: m.begin_run("repeat"),
            lambda: m.add_vertex(0, 0, np.eye(4), frames[0]),
            lambda: m.add_edge(int(ids[0]), int(ids[2]), np.eye(4), np.eye(6), "spatial"),
            m.finish_run,
        ):
            with pytest.raises(MapError, match="read-only"):
                attempt()
        with pytest.raises(sqlite3.OperationalError):  # even raw SQL on its connection is refused
            m.file.conn.execute("INSERT INTO runs VALUES (9, 'repeat', 0, '', '', 0)")
    assert path.read_bytes() == before
    m.close()  # closing twice is harmless
    with pytest.raises(MapError, match="closed"):
        m.vertex(0)


def test_bad_edges_and_vertices_write_nothing(tmp_path):
    path = tmp_path / "teach.vtrmap"
    rng = np.random.default_rng(2)
    with Map.create(path, CAMERA) as m:
        run = m.begin_run("teach")
        a = m.add_vertex(run, 0, pose(0.0), make_frame(rng, 10))
        b = m.add_vertex(run, 1, pose(1.0), make_frame(rng, 10))
        c = m.add_vertex(run, 2, pose(2.0), make_frame(rng, 10))
        good_T, good_C = inv(pose(0.0)) @ pose(1.0), cov()
        nan_T = good_T.copy()
        nan_T[0, 3] = np.nan
        scaled_T = good_T.copy()
        scaled_T[:3, :3] *= 1.1
        reflect_T = np.diag([1.0, 1.0, -1.0, 1.0])
        bad_row_T = good_T.copy()
        bad_row_T[3, 0] = 0.5
        non_psd = good_C.copy()
        non_psd[0, 0] = -1.0
        asym = good_C.copy()
        asym[0, 1] += 1e-2
        nan_C = good_C.copy()
        nan_C[2, 2] = np.nan
        cases = [
            ((a.id, b.id, nan_T, good_C, "temporal"), "NaN"),
            ((a.id, b.id, scaled_T, good_C, "temporal"), "orthonormal"),
            ((a.id, b.id, reflect_T, good_C, "temporal"), "orthonormal"),
            ((a.id, b.id, bad_row_T, good_C, "temporal"), "last row"),
            ((a.id, b.id, np.eye(3), good_C, "temporal"), "4x4"),
            ((a.id, b.id, good_T, non_psd, "temporal"), "positive semi-definite"),
            ((a.id, b.id, good_T, asym, "temporal"), "symmetric"),
            ((a.id, b.id, good_T, nan_C, "temporal"), "NaN"),
            ((a.id, b.id, good_T, np.eye(3), "temporal"), "6x6"),
            ((a.id, b.id, good_T, good_C, "loop"), "kind"),
            ((a.id, a.id, good_T, good_C, "spatial"), "itself"),
            ((a.id, c.id, good_T, good_C, "temporal"), "consecutive"),
            ((a.id, vertex_id(0, 99), good_T, good_C, "spatial"), "no vertex"),
        ]
        for args, message in cases:
            with pytest.raises(MapError, match=message):
                m.add_edge(*args)
        with pytest.raises(MapError, match="inliers"):
            m.add_edge(a.id, b.id, good_T, good_C, "temporal", inliers=-1)
        assert m.edges() == []
        m.add_edge(a.id, b.id, good_T, good_C, "temporal", inliers=5)
        with pytest.raises(MapError, match="already exists"):
            m.add_edge(a.id, b.id, good_T, good_C, "temporal", inliers=5)
        assert len(m.edges()) == 1
        # bad vertices
        short = make_frame(rng, 10)
        short = StereoFrame(0, 0, short.features, short.u_right[:5], short.points)
        fractional = make_frame(rng, 4)
        fractional = StereoFrame(
            0,
            0,
            Features(
                fractional.features.uv,
                np.array([0.5, 1, 2, 3]),
                fractional.features.response,
                fractional.features.descriptors,
            ),
            fractional.u_right,
            fractional.points,
        )
        for args, message in [
            ((run, 3, nan_T, make_frame(rng, 3)), "NaN"),
            ((run, 3, scaled_T, make_frame(rng, 3)), "orthonormal"),
            ((run, 3.5, pose(3.0), make_frame(rng, 3)), "t_ns"),
            ((run, 3, pose(3.0), short), "u_right"),
            ((run, 3, pose(3.0), fractional), "octave"),
            ((run, 3, pose(3.0), "not a frame"), "StereoFrame"),
            ((run + 1, 3, pose(3.0), make_frame(rng, 3)), "run"),
        ]:
            with pytest.raises(MapError, match=message):
                m.add_vertex(*args)
        assert m.vertex_ids(run).tolist() == [a.id, b.id, c.id]
        # an int64 octave converts losslessly and is stored as int32
        f = make_frame(rng, 4)
        f64 = StereoFrame(
            5,
            5,
            Features(f.features.uv, f.features.octave.astype(np.int64), f.features.response, f.features.descriptors),
            f.u_right,
            f.points,
        )
        assert m.add_vertex(run, 3, pose(3.0), f64).frame.features.octave.dtype == np.int32
    with Map.open(path) as m:
        assert m.stats()["vertices"] == 4 and m.stats()["edges"] == 1


def test_repeat_never_modifies_the_taught_run(tmp_path):
    path = tmp_path / "teach.vtrmap"
    write_teach(path, n=6)
    before = run_rows_digest(path, 0)
    rng = np.random.default_rng(5)
    with Map.open(path, "a") as m:
        assert m.open_run is None  # the teach session finished its run
        with pytest.raises(MapError, match="no open run"):
            m.add_vertex(0, 0, pose(0.0), make_frame(rng, 5))
        rep = m.begin_run("repeat", source="repeat 1")
        assert rep == 1 and not m.run(rep).privileged
        teach_ids = m.taught_path().ids
        prev = None
        for i in range(4):
            v = m.add_vertex(rep, 10**10 + i, pose(i + 0.1, y=0.3), make_frame(rng, 20, index=i))
            if prev is not None:
                m.add_edge(prev.id, v.id, inv(pose(i - 0.9, y=0.3)) @ pose(i + 0.1, y=0.3), cov(), "temporal", 40)
            m.add_edge(
                v.id, int(teach_ids[i]), inv(pose(i + 0.1, y=0.3)) @ pose(float(i), 0.05 * i), cov(), "spatial", 25
            )
            prev = v
        # the taught run cannot grow or change, by the API ...
        with pytest.raises(MapError, match="run 0 is not the open run"):
            m.add_vertex(0, 0, pose(0.0), make_frame(rng, 5))
        with pytest.raises(MapError, match="finished"):
            m.add_edge(int(teach_ids[0]), int(teach_ids[1]), pose(1.0), cov(), "temporal")
        with pytest.raises(MapError, match="open run"):
            m.add_edge(int(teach_ids[0]), int(teach_ids[3]), pose(3.0), cov(), "spatial")
        assert m.open_run == rep
        # ... nor by raw SQL on the file (triggers)
        for sql in (
            "UPDATE vertices SET t_ns = 0 WHERE run = 0",
            "DELETE FROM vertex_data WHERE id = 0",
            "UPDATE edges SET inliers = 0",
            "UPDATE runs SET state = 'running' WHERE id = 0",
            "INSERT INTO vertices VALUES (7, 0, 7, 0, zeroblob(128), zeroblob(128), 0, 0, 0)",
        ):
            with pytest.raises(sqlite3.IntegrityError):
                m.file.conn.execute(sql)
        assert len(m.edges(run=rep, kind="spatial")) == 4 and len(m.edges(run=0, kind="spatial")) == 4
    assert run_rows_digest(path, 0) == before
    with Map.open(path) as m:
        assert [(r.kind, r.n_vertices, r.finished) for r in m.runs()] == [("teach", 6, True), ("repeat", 4, True)]
        assert m.taught_path().ids.tolist() == [vertex_id(0, i) for i in range(6)]


# ------------------------------------------------------------------ queries


def test_window_nearest_and_poses_without_features(tmp_path):
    path = tmp_path / "route.vtrmap"
    rng = np.random.default_rng(7)
    n = 40
    xs = np.cumsum(rng.uniform(0.3, 1.2, n))
    with Map.create(path, CAMERA) as m:
        run = m.begin_run("teach")
        for i in range(n):
            m.add_vertex(run, i, pose(xs[i], 0.1 * np.sin(i), y=np.sin(xs[i] / 5.0)), make_frame(rng, 8))
        rep = m.begin_run("repeat")
        m.add_vertex(rep, 0, pose(0.0), make_frame(rng, 8))  # not on the privileged path
    with Map.open(path, cache_size=4) as m:
        reads = []

        def authorizer(action, arg1, arg2, dbname, source):
            if action == sqlite3.SQLITE_READ:
                reads.append(arg1)
            return sqlite3.SQLITE_OK

        m.file.conn.set_authorizer(authorizer)
        path_ids = m.taught_path().ids
        assert path_ids.tolist() == [vertex_id(0, i) for i in range(n)]
        taught = m.taught_path()
        ids, T = taught.ids, taught.T_world_vertex
        assert np.allclose(T[:, 0, 3], xs) and taught.t_ns.tolist() == list(range(n))
        assert taught.index(vertex_id(0, 7)) == 7 and taught.window(2, 10, 3) == (0, 6)
        assert taught.segment(3, 5).ids.tolist() == [vertex_id(0, 3), vertex_id(0, 4)]
        assert np.allclose(taught.arc_length_m()[-1], np.sum(np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)))

        def window(center_id, back, forward):
            lo, hi = taught.window(taught.index(center_id), back, forward)
            return taught.ids[lo:hi].tolist()

        assert window(vertex_id(0, 20), 10, 20) == [vertex_id(0, i) for i in range(10, 40)]
        assert window(vertex_id(0, 2), 10, 3) == [vertex_id(0, i) for i in range(0, 6)]
        assert window(vertex_id(0, 38), 1, 20) == [vertex_id(0, i) for i in range(37, 40)]
        assert window(vertex_id(0, 5), 0, 0) == [vertex_id(0, 5)]
        with pytest.raises(MapError, match="not on the privileged path"):
            taught.index(vertex_id(1, 0))
        centres = T[:, :3, 3]
        for q in rng.uniform([-2, -2, -1], [xs[-1] + 2, 2, 1], (25, 3)):
            got = ids[taught.nearest(q, 3)]
            order = np.argsort(np.linalg.norm(centres - q, axis=1), kind="stable")[:3]
            assert got.tolist() == ids[order].tolist()
        assert len(taught.nearest(centres[5], 100)) == n
        assert ids[taught.nearest(centres[5], 1)].tolist() == [vertex_id(0, 5)]
        with pytest.raises(MapError, match="position"):
            taught.nearest([np.nan, 0, 0], 1)
        m.poses(0)
        m.stats()
        m.runs()
        assert "vertex_data" not in reads and "vertices" in reads  # poses come from the pose index
        # the vertex cache stays bounded and serves repeats
        for vid in path_ids:
            m.vertex(int(vid))
        assert len(m._cache) == 4 and "vertex_data" in reads
        assert m.vertex(int(path_ids[-1])) is m.vertex(int(path_ids[-1]))
        with pytest.raises(MapError, match="no vertex"):
            m.vertex(vertex_id(0, n))
        with pytest.raises(MapError, match="no run 5"):
            m.poses(5)


def _two_run_map(path):
    """Teach run; repeat run 1 offset 0.5 m sideways, own world frame = its first camera; unlinked run 2.

    Returns the true world positions of each run's landmarks.
    """
    rng = np.random.default_rng(11)
    truth = {}
    with Map.create(path, CAMERA) as m:
        teach = m.begin_run("teach")
        T_teach = [pose(float(i), 0.03 * i) for i in range(5)]
        pts = []
        for T in T_teach:
            f = make_frame(rng, 12)
            m.add_vertex(teach, f.t_ns, T, f)
            keep = np.isfinite(f.points).all(axis=1)
            pts.append(f.points[keep] @ T[:3, :3].T + T[:3, 3])
        truth[teach] = np.concatenate(pts)
        for linked in (True, False):
            run = m.begin_run("repeat")
            T_true = [pose(float(i) + 0.2, 0.03 * i + 0.02, y=0.5) for i in range(5)]  # in the teach frame
            T_R = [inv(T_true[0]) @ T for T in T_true]  # the repeat's own world frame
            pts = []
            for i, (T, T_own) in enumerate(zip(T_true, T_R, strict=True)):
                f = make_frame(rng, 12)
                v = m.add_vertex(run, f.t_ns, T_own, f)
                keep = np.isfinite(f.points).all(axis=1)
                pts.append(f.points[keep] @ T[:3, :3].T + T[:3, 3])
                if linked and i in (1, 3):
                    m.add_edge(v.id, vertex_id(teach, i), inv(T) @ T_teach[i], cov(), "spatial", 30)
            truth[run] = np.concatenate(pts)
    return truth


def test_landmarks_in_the_teach_frame(tmp_path):
    path = tmp_path / "two.vtrmap"
    truth = _two_run_map(path)
    with Map.open(path) as m:
        assert m.reference_run() == 0
        assert poses_in_map_frame(m, 0)[2] and poses_in_map_frame(m, 1)[2] and not poses_in_map_frame(m, 2)[2]
        for run in (0, 1):
            pts, owner = landmarks_in_map_frame(m, run)
            assert np.allclose(pts, truth[run], atol=1e-9) and np.all(owner == run)
        own, _ = landmarks_in_map_frame(m, 2)
        assert own.shape == truth[2].shape and not np.allclose(own, truth[2], atol=1e-3)
        pts, owner = landmarks_in_map_frame(m)
        assert len(pts) == sum(len(t) for t in truth.values()) == m.stats()["landmarks"]
        assert np.bincount(owner).tolist() == [len(truth[r]) for r in (0, 1, 2)]


def test_ply_export_reopens_in_open3d(tmp_path):
    import open3d as o3d

    from vtr.map.export import export_landmarks_ply

    path = tmp_path / "two.vtrmap"
    truth = _two_run_map(path)
    ply = tmp_path / "out" / "landmarks.ply"
    with Map.open(path) as m:
        summary = export_landmarks_ply(m, ply)
        with pytest.raises(MapError, match=r"\.ply"):
            export_landmarks_ply(m, tmp_path / "landmarks.xyz")
    assert [(s.run, s.points, s.aligned) for s in summary] == [(r, len(truth[r]), r != 2) for r in (0, 1, 2)]
    cloud = o3d.io.read_point_cloud(str(ply))
    pts, cols = np.asarray(cloud.points), np.asarray(cloud.colors)
    assert len(pts) == sum(len(t) for t in truth.values())
    assert np.allclose(pts[: len(truth[0])], truth[0])
    assert len(np.unique(np.round(cols, 2), axis=0)) == 3


def test_add_keyframe_writes_vertex_and_edge_together(tmp_path):
    from vtr.types import Keyframe

    rng = np.random.default_rng(4)
    path = tmp_path / "kf.vtrmap"
    with Map.create(path, CAMERA) as m:
        run = m.begin_run("teach")
        for i in range(3):
            T = pose(0.4 * i, 0.02 * i)
            kf = Keyframe(i, make_frame(rng, 10, index=3 * i), T, cov(), 60 + i)
            v = m.add_keyframe(run, kf)
            assert (v.index, v.frame.index, v.t_ns, v.frame.t_ns) == (i, 3 * i, kf.frame.t_ns, kf.frame.t_ns)
        bad = Keyframe(3, make_frame(rng, 10, index=9), pose(1.2), -cov(), 5)
        with pytest.raises(MapError, match="positive semi-definite"):
            m.add_keyframe(run, bad)  # neither the vertex nor its edge is written
        assert len(m.vertex_ids(run)) == 3
        resumed = Keyframe(0, make_frame(rng, 10, index=12), pose(1.6), np.zeros((6, 6)), 0)
        assert m.add_keyframe(run, resumed, link_previous=False).index == 3
        unknown = Keyframe(4, make_frame(rng, 10, index=15), pose(2.0), np.full((6, 6), np.nan), 0)
        with pytest.raises(MapError, match="NaN"):
            m.add_keyframe(run, unknown)
        usable = dataclasses.replace(unknown, edge_covariance=usable_covariance(unknown.edge_covariance, 100.0))
        assert m.add_keyframe(run, usable).index == 4  # not estimated: odometry makes it unknown
    with Map.open(path) as m:
        edges = m.edges(run=0)
        assert [(e.from_id, e.to_id, e.kind, e.inliers) for e in edges] == [
            (0, 1, "temporal", 61),
            (1, 2, "temporal", 62),
            (3, 4, "temporal", 0),
        ]
        for e in edges:  # the edge is the relative pose of the two stored vertices
            assert np.allclose(m.vertex(e.from_id).T_world_vertex @ e.T_from_to, m.vertex(e.to_id).T_world_vertex)
        assert np.array_equal(edges[2].covariance, np.eye(6) * 100.0)
