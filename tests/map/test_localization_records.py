"""A repeat keyframe and its localization in one transaction (Map.add_leaf): the vertex, its edges, its experience
use and its localization record are written together or not at all; the records read back as written, are
append-only, go with their run when it is pruned, and the writer thread commits them in order."""

from __future__ import annotations

import dataclasses
import sqlite3

import numpy as np
import pytest

from vtr.camera import StereoCamera
from vtr.errors import MapError
from vtr.map import Map
from vtr.map.experiences import prune
from vtr.map.localizations import Leaf, LocalizationRecord, SpatialEdge
from vtr.map.writer import LeafWriter
from vtr.types import Features, Keyframe, StereoFrame

CAMERA = StereoCamera(fx=718.856, fy=718.856, cx=607.19, cy=185.22, baseline=0.537, width=1226, height=370)


def make_frame(rng: np.random.Generator, n: int, index: int) -> StereoFrame:
    uv = np.column_stack([rng.uniform(0, CAMERA.width, n), rng.uniform(0, CAMERA.height, n)])
    disparity = rng.uniform(1.0, 60.0, n)
    feats = Features(
        uv, rng.integers(0, 8, n).astype(np.int32), rng.random(n), rng.integers(0, 256, (n, 32), dtype=np.uint8)
    )
    return StereoFrame(
        t_ns=index * 100_000_000,
        index=index,
        features=feats,
        u_right=uv[:, 0] - disparity,
        points=CAMERA.triangulate(uv[:, 0], uv[:, 1], disparity),
    )


def pose(x: float, yaw: float = 0.0) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T[0, 3] = x
    return T


def cov(scale: float = 1e-3) -> np.ndarray:
    A = np.random.default_rng(1).normal(size=(6, 6))
    return scale * (A @ A.T + np.eye(6))


def write_teach(path, n: int = 6) -> None:
    """A map with one finished teach run of ``n`` keyframes along x."""
    rng = np.random.default_rng(0)
    with Map.create(path, CAMERA) as m:
        run = m.begin_run("teach", source="synthetic")
        for i in range(n):
            frame = make_frame(rng, 40, 2 * i)
            m.add_keyframe(run, Keyframe(i, frame, pose(float(i), 0.05 * i), cov(1e-4), 30))


def _keyframe(i: int) -> Keyframe:
    frame = make_frame(np.random.default_rng(100 + i), 30, index=2 * i + 1)
    return Keyframe(i, frame, pose(i + 0.1), cov(1e-4), 40)


def _record(leaf_id: int, trunk_id: int, success: bool, i: int) -> LocalizationRecord:
    C = cov(1e-4) if success else np.full((6, 6), np.inf)  # a failure's covariance may be infinite
    return LocalizationRecord(
        t_ns=1000 + i,
        leaf_id=leaf_id,
        trunk_id=trunk_id,
        twig_id=-1 if i == 0 else trunk_id,
        branch_id=-1,
        success=success,
        matches=50 + i,
        inliers=40 + i if success else 3,
        T_leaf_trunk=pose(0.1 * i, 0.01),
        covariance=C,
        consecutive_failures=0 if success else 1,
        distance_since_success_m=0.25 * i,
        status="localized" if success else "too_few_inliers",
        direction=1,
        experiences=(3, 5) if success else (),
    )


def _leaf(m: Map, run: int, i: int, success: bool = True, trunk: int | None = None) -> Leaf:
    trunk_id = int(m.taught_path().ids[i]) if trunk is None else trunk
    record = _record(m.next_vertex_id(run), trunk_id, success, i)
    spatial = SpatialEdge(trunk_id, record.T_leaf_trunk, cov(1e-4), record.inliers) if success else None
    return Leaf(record, spatial, (3,) if success else ())


def _count(m: Map, table: str) -> int:
    with m.file.connection() as conn:
        return int(conn.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0])


def test_a_leaf_is_written_whole_and_reads_back(tmp_path):
    path = tmp_path / "route.vtrmap"
    write_teach(path)
    with Map.open(path, "a") as m:
        run = m.begin_run("repeat")
        leaves = [_leaf(m, run, 0)]
        m.add_leaf(run, _keyframe(0), leaves[0])
        leaves.append(_leaf(m, run, 1, success=False))
        m.add_leaf(run, _keyframe(1), leaves[1])
        leaves.append(_leaf(m, run, 2))
        m.add_leaf(run, _keyframe(2), leaves[2])
        ids = [int(v) for v in m.vertex_ids(run)]
        records = m.localization_records(run)
        assert [r.leaf_id for r in records] == ids == [leaf.record.leaf_id for leaf in leaves]
        for got, leaf in zip(records, leaves, strict=True):
            want = leaf.record
            assert (
                got.t_ns,
                got.trunk_id,
                got.success,
                got.matches,
                got.inliers,
                got.status,
                got.experiences,
                got.distance_since_success_m,
            ) == (
                want.t_ns,
                want.trunk_id,
                want.success,
                want.matches,
                want.inliers,
                want.status,
                want.experiences,
                want.distance_since_success_m,
            )
            assert np.array_equal(got.T_leaf_trunk, want.T_leaf_trunk)
            assert np.array_equal(got.covariance, want.covariance)  # infinite on the failure too
        assert [(e.from_id, e.to_id) for e in m.edges(run, "temporal")] == list(zip(ids[:-1], ids[1:], strict=True))
        assert [(e.from_id, e.to_id) for e in m.edges(run, "spatial")] == [
            (ids[0], records[0].trunk_id),
            (ids[2], records[2].trunk_id),
        ]
        assert m.localization_count(run) == 3
    with Map.open(path) as m:  # closed and reopened read-only
        assert len(m.localization_records(run)) == 3
        assert m.localization_count(0) == 0  # a teach has none


@pytest.mark.parametrize("problem", ["missing trunk", "wrong leaf id", "covariance shape"])
def test_a_leaf_that_cannot_be_written_leaves_nothing(tmp_path, problem):
    path = tmp_path / "route.vtrmap"
    write_teach(path)
    with Map.open(path, "a") as m:
        run = m.begin_run("repeat")
        m.add_leaf(run, _keyframe(0), _leaf(m, run, 0))
        before = {t: _count(m, t) for t in ("vertices", "vertex_data", "edges", "localizations", "experience_use")}
        leaf = _leaf(m, run, 1)
        if problem == "missing trunk":  # only the insert of the spatial edge, inside the transaction, fails
            leaf = Leaf(leaf.record, SpatialEdge(123456, pose(0.0), cov(), 10), leaf.experience_use)
        elif problem == "wrong leaf id":
            leaf = Leaf(_record(m.next_vertex_id(run) + 1, leaf.record.trunk_id, True, 1), leaf.spatial)
        else:
            leaf = Leaf(dataclasses.replace(leaf.record, covariance=np.eye(3)), leaf.spatial)
        with pytest.raises(MapError):
            m.add_leaf(run, _keyframe(1), leaf)
        assert {t: _count(m, t) for t in before} == before
        m.add_leaf(run, _keyframe(1), _leaf(m, run, 1))  # the next write goes on as if nothing happened
        assert len(m.localization_records(run)) == 2


def test_records_are_append_only_and_pruned_with_their_run(tmp_path):
    path = tmp_path / "route.vtrmap"
    write_teach(path)
    with Map.open(path, "a") as m:
        run = m.begin_run("repeat")
        for i in range(3):
            m.add_leaf(run, _keyframe(i), _leaf(m, run, i))
    con = sqlite3.connect(path)
    with pytest.raises(sqlite3.DatabaseError, match="immutable"):
        con.execute("UPDATE localizations SET inliers = 0")
    with pytest.raises(sqlite3.DatabaseError, match="immutable"):
        con.execute("DELETE FROM localizations")
    con.close()
    with Map.open(path, "a") as m:
        assert prune(m, [run]) == 3
        with m.file.connection() as conn:
            assert conn.execute("SELECT COUNT(*) FROM localizations").fetchone()[0] == 0
            assert (
                conn.execute(
                    "SELECT COUNT(*) FROM sqlite_master WHERE name = 'localizations_append_only_delete'"
                ).fetchone()[0]
                == 1
            )  # the trigger is back after the prune


def test_the_writer_thread_commits_in_order_and_stops_after_a_failure(tmp_path):
    path = tmp_path / "route.vtrmap"
    write_teach(path)
    with Map.open(path, "a") as m:
        run = m.begin_run("repeat")
        first = m.next_vertex_id(run)
        ids = [first + i for i in range(4)]
        taught = m.taught_path().ids
        leaves = [
            Leaf(_record(ids[i], int(taught[i]), True, i), SpatialEdge(int(taught[i]), pose(0.0), cov(), 9))
            for i in range(4)
        ]
        leaves[2] = Leaf(leaves[2].record, SpatialEdge(999999, pose(0.0), cov(), 9))  # fails inside its commit
        with LeafWriter(m) as writer:
            futures = [writer.submit(run, _keyframe(i), leaves[i]) for i in range(4)]
            writer.prefetch([int(t) for t in taught[:2]])
            assert [f.result().id for f in futures[:2]] == ids[:2]
            with pytest.raises(MapError):
                futures[2].result()
            assert futures[3].exception() is not None  # never written after the failure
        assert [int(v) for v in m.vertex_ids(run)] == ids[:2]
        assert [r.leaf_id for r in m.localization_records(run)] == ids[:2]
