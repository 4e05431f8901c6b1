"""Damaged maps are refused, not served: real byte flips in a closed map file (a pose, descriptors, compressed
landmarks, the runs table), edits no vtr makes (a moved vertex, times out of order, a vertex of a run that does
not exist), `vtr map check` for a full check, one line everywhere; maps without checksums still open."""

from __future__ import annotations

import sqlite3
import struct
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "cli"))
from test_map_cli import CAMERA, frame, translation  # noqa: E402

from vtr.cli import main  # noqa: E402
from vtr.errors import MapError  # noqa: E402
from vtr.map import Map, vertex_id  # noqa: E402
from vtr.map.checksums import META_KEY, TABLE  # noqa: E402
from vtr.map.codec import BLOB_MAGIC, decode_frame  # noqa: E402
from vtr.types import Keyframe  # noqa: E402

N = 6


def make_map(path: Path) -> Path:
    rng = np.random.default_rng(1)
    with Map.create(path, CAMERA) as m:
        run = m.begin_run("teach", source="synthetic")
        for i in range(N):
            m.add_keyframe(run, Keyframe(i, frame(rng, i), translation(float(i)), np.eye(6) * 1e-4, 50))
    return path


def without_checksums(path: Path) -> Path:
    """The map as a vtr from before checksums wrote it (no table, no meta key)."""
    with sqlite3.connect(path) as c:
        c.executescript(
            f"DROP TRIGGER {TABLE}_append_only_update; DROP TRIGGER {TABLE}_append_only_delete; DROP TABLE {TABLE};"
        )
        c.execute("DELETE FROM meta WHERE key = ?", (META_KEY,))
    return path


def column(path: Path, sql: str, *args):
    with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as c:
        return c.execute(sql, args).fetchone()[0]


def flip(path: Path, needle: bytes, at: int, mask: int = 0x10) -> None:
    """XOR one byte of the only occurrence of ``needle`` in the closed file (a real byte flip on disk)."""
    data = bytearray(path.read_bytes())
    i = data.find(needle)
    assert i >= 0 and data.find(needle, i + 1) < 0, "needle must occur once"
    data[i + at] ^= mask
    path.write_bytes(bytes(data))


def edit(path: Path, sql: str, *args, drop: str = "vertices_append_only_update") -> None:
    """An edit no vtr makes (its immutability trigger dropped first)."""
    with sqlite3.connect(path) as c:
        c.execute("PRAGMA ignore_check_constraints = ON")
        c.execute(f"DROP TRIGGER IF EXISTS {drop}")
        c.execute(sql, args)


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def one_line(r, *needles) -> str:
    assert r.exit_code == 1 and "Traceback" not in r.output, r.output
    assert r.stderr.count("\n") == 1 and r.stderr.startswith("vtr: error:"), r.stderr
    for n in needles:
        assert n in r.stderr, r.stderr
    return r.stderr


V2 = vertex_id(0, 2)


def test_an_intact_map_checks_ok(tmp_path):
    path = make_map(tmp_path / "m.vtrmap")
    r = invoke("map", "check", path)
    assert r.exit_code == 0 and "ok (1 runs, 6 vertices, 5 edges checked; checksums verified)" in r.output


@pytest.mark.parametrize("byte", [0, 7, 3 * 8 + 6, 11 * 8 + 7])  # mantissa, sign/exponent of R, of t_x
def test_a_flipped_byte_in_a_taught_pose(tmp_path, byte):
    path = make_map(tmp_path / "m.vtrmap")
    flip(path, column(path, "SELECT T_world_vertex FROM vertices WHERE id = ?", V2), byte)
    with Map.open(path) as m, pytest.raises(MapError, match=f"vertex {V2} .* damaged"):
        m.taught_path()
    with Map.open(path) as m, pytest.raises(MapError, match="damaged"):
        m.poses(0)
    one_line(invoke("map", "check", path), f"vertex {V2}", "damaged")


@pytest.mark.parametrize("where", ["descriptors", "landmarks"])
def test_a_flipped_byte_in_vertex_data(tmp_path, where):
    path = make_map(tmp_path / "m.vtrmap")
    blob = column(path, "SELECT data FROM vertex_data WHERE id = ?", V2)
    n = struct.unpack_from("<I", blob, len(BLOB_MAGIC))[0]
    head = len(BLOB_MAGIC) + 4
    at = head + 5 if where == "descriptors" else head + n * 32 + 20  # raw descriptors / zlib stream
    lo = max(at - 16, len(BLOB_MAGIC))
    flip(path, blob[lo : lo + 32], at - lo, 0x01)
    with Map.open(path) as m:
        assert len(m.taught_path()) == N  # the pose index is intact
        with pytest.raises(MapError, match=f"vertex {V2}"):
            m.vertex(V2)
        m.vertex(vertex_id(0, 1))  # the others still read
    one_line(invoke("map", "check", path), f"vertex {V2}")


def test_a_damaged_runs_table_is_one_line_in_map_info(tmp_path):
    path = make_map(tmp_path / "m.vtrmap")
    created = column(path, "SELECT created FROM runs WHERE id = 0").encode()
    flip(path, created + b"finished", len(created), 0x01)  # state 'finished' -> 'ginished'
    one_line(invoke("map", "info", path), "runs table is damaged", "state")
    one_line(invoke("map", "check", path), "runs table is damaged")
    path = make_map(tmp_path / "m2.vtrmap")
    flip(path, b"synthetic", 3, 0xC0)  # invalid UTF-8 in the source
    one_line(invoke("map", "info", path), str(path))


@pytest.mark.parametrize("checksums", [True, False])
def test_edits_no_vtr_makes(tmp_path, checksums):
    """A vertex moved 1 km, times out of order, a vertex of a run that does not exist: refused with or without
    checksums (without: the path checks and the temporal edges find them)."""
    cases = [
        (
            "moved",
            "UPDATE vertices SET T_world_vertex = ? WHERE id = ?",
            lambda p: (translation(1000.0).astype("<f8").tobytes(), V2),
            "temporal edge" if not checksums else "damaged",
        ),
        (
            "times",
            "UPDATE vertices SET t_ns = 1 WHERE id = ?",
            lambda p: (V2,),
            "not after" if not checksums else "damaged",
        ),
        ("no run", "UPDATE vertices SET run = 7 WHERE id = ?", lambda p: (V2,), "runs table does not hold"),
    ]
    for name, sql, args, msg in cases:
        path = make_map(tmp_path / f"{name}.vtrmap")
        if not checksums:
            without_checksums(path)
        edit(path, sql, *args(path))
        r = invoke("map", "check", path)
        one_line(r, msg)
        with Map.open(path) as m, pytest.raises(MapError, match=msg):
            m.taught_path()


def test_a_map_without_checksums_still_opens_and_appends(tmp_path):
    path = without_checksums(make_map(tmp_path / "old.vtrmap"))
    with Map.open(path) as m:
        assert len(m.taught_path()) == N and m.vertex(V2).frame.points.shape[1] == 3
    rng = np.random.default_rng(5)
    with Map.open(path, "a") as m:
        run = m.begin_run("repeat", source="rep")
        m.add_keyframe(run, Keyframe(0, frame(rng, 0), translation(0.5), np.eye(6) * 1e-4, 50))
    with sqlite3.connect(path) as c:  # appending adds no checksum table
        assert c.execute("SELECT COUNT(*) FROM sqlite_master WHERE name = ?", (TABLE,)).fetchone()[0] == 0
    r = invoke("map", "check", path)
    assert r.exit_code == 0 and "no checksums" in r.output, r.output


def test_infinite_or_absurd_landmarks_are_refused():
    from vtr.map.codec import pack_arrays

    rng = np.random.default_rng(2)
    f = frame(rng, 0)
    base = {
        "uv": f.features.uv,
        "octave": f.features.octave,
        "descriptors": f.features.descriptors,
        "u_right": f.u_right,
    }
    for bad, msg in ((np.inf, "infinite"), (1e9, "m away")):
        pts = np.array(f.points, float)
        pts[1, 2] = bad
        blob = pack_arrays({**base, "points": pts}, 3)
        with pytest.raises(MapError, match=msg):
            decode_frame(blob, 0, 0, "m.vtrmap vertex 0")


def test_times_past_int64_are_a_map_error(tmp_path):
    rng = np.random.default_rng(3)
    with Map.create(tmp_path / "m.vtrmap", CAMERA) as m:
        run = m.begin_run("teach", source="x")
        kf = Keyframe(0, frame(rng, 0), translation(0.0), np.eye(6) * 1e-4, 50)
        with pytest.raises(MapError, match="t_ns"):
            m.add_vertex(run, 2**63, translation(0.0), kf.frame)


@pytest.mark.parametrize("damage", ["renamed", "value", "flipped"])
def test_damaged_checksum_metadata_is_damage_not_an_old_map(tmp_path, damage):
    """One damaged meta key must not turn verification off: the key renamed (an SQL edit), its value changed, or a
    real byte flip in its name on disk while the checksum table is there is refused, not read as a map made
    before checksums."""
    path = make_map(tmp_path / "m.vtrmap")
    if damage == "renamed":
        edit(path, "UPDATE meta SET key = 'checksumz' WHERE key = ?", META_KEY)
    elif damage == "value":
        edit(path, "UPDATE meta SET value = 'none' WHERE key = ?", META_KEY)
    else:
        flip(path, b"checksumsblake2b", 0, 0x01)  # 'checksums' -> 'bhecksums' in the meta row
    r = invoke("map", "check", path)
    text = one_line(r, "checksum")
    assert "no checksums" not in text
    with pytest.raises(MapError, match="checksum"):
        Map.open(path).close()
    edit(path, f"UPDATE {TABLE} SET row_sum = zeroblob(8)", drop=f"{TABLE}_append_only_update")
    with pytest.raises(MapError, match="checksum"):  # never served without verification
        with Map.open(path) as m:
            m.poses(0)
