"""Run lifecycle on disk (running / finished / aborted with reason / interrupted), the single-writer
lock, and a closed map being one self-contained file that opens read-only.

Synthetic keyframes from numpy (no images); the killed writer is a real process.
"""

from __future__ import annotations

import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from test_map import CAMERA, cov, make_frame, pose

from vtr.cli import main
from vtr.errors import MapError, Terminated
from vtr.map import Map
from vtr.map.database import connect
from vtr.map.placement import landmarks_in_map_frame
from vtr.map.records import REASON_MAX_CHARS
from vtr.map.store import INTERRUPTED_REASON
from vtr.types import Keyframe

SUBPROCESS_TIMEOUT_S = 60


def add_vertices(m: Map, run: int, n: int, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    for i in range(n):
        frame = make_frame(rng, 20, index=i)
        m.add_keyframe(run, Keyframe(i, frame, pose(float(i)), cov(), 30))


def states(path) -> list[tuple[str, str, int, str]]:
    with Map.open(path) as m:
        return [(r.kind, r.state, r.n_vertices, r.reason) for r in m.runs()]


def test_orderly_close_finishes_and_exception_aborts_with_reason(tmp_path):
    path = tmp_path / "route.vtrmap"
    with Map.create(path, CAMERA) as m:
        add_vertices(m, m.begin_run("teach", source="t"), 3)
        assert m.runs()[0].state == "running"
    with pytest.raises(RuntimeError), Map.open(path, "a") as m:
        add_vertices(m, m.begin_run("repeat", source="r"), 2)
        raise RuntimeError("camera unplugged\nsecond line")
    with pytest.raises(KeyboardInterrupt), Map.open(path, "a") as m:
        add_vertices(m, m.begin_run("repeat"), 1)
        raise KeyboardInterrupt
    with pytest.raises(Terminated), Map.open(path, "a") as m:
        m.begin_run("repeat")
        raise Terminated
    assert states(path) == [
        ("teach", "finished", 3, ""),
        ("repeat", "aborted", 2, "RuntimeError: camera unplugged second line"),
        ("repeat", "aborted", 1, "interrupted by Ctrl-C (SIGINT)"),
        ("repeat", "aborted", 0, "terminated by SIGTERM"),
    ]
    with Map.open(path, "a") as m:  # an aborted run is final
        with pytest.raises(MapError, match="no open run"):
            add_vertices(m, 1, 1)
        with pytest.raises(sqlite3.IntegrityError, match="cannot be reopened"):
            m.file.conn.execute("UPDATE runs SET state = 'finished', reason = '' WHERE id = 1")
        with pytest.raises(sqlite3.IntegrityError, match="finished or aborted run"):
            m.file.conn.execute(
                "INSERT INTO vertices VALUES ((1 << 32) | 9, 1, 9, 0, zeroblob(128), zeroblob(128), 0, 0, 0)"
            )
        with pytest.raises(sqlite3.IntegrityError):  # aborted needs a reason, finished has none
            m.file.conn.execute(
                "INSERT INTO runs(id, kind, privileged, source, created, state) "
                "VALUES (9, 'teach', 1, '', '', 'aborted')"
            )
        m.abort_run("x" * 2000)  # no open run: nothing happens
    assert len(states(path)) == 4


def test_abort_run_reason_is_one_bounded_line(tmp_path):
    path = tmp_path / "route.vtrmap"
    with Map.create(path, CAMERA) as m:
        add_vertices(m, m.begin_run("teach"), 2)
        m.abort_run("first\n\nsecond " + "y" * 2000)
        assert m.open_run is None
    [(_k, state, n, reason)] = states(path)
    assert (state, n) == ("aborted", 2)
    assert reason.startswith("first second yyy") and len(reason) == REASON_MAX_CHARS and "\n" not in reason


def test_created_map_without_vertex_is_removed_on_abort_only(tmp_path):
    aborted = tmp_path / "aborted.vtrmap"
    with pytest.raises(ValueError), Map.create(aborted, CAMERA) as m:
        m.begin_run("teach")
        raise ValueError("first frame unreadable")
    assert list(tmp_path.iterdir()) == []  # no map, no -wal/-shm, no temporary file
    Map.create(tmp_path / "empty.vtrmap", CAMERA).close()  # an explicitly empty map stays
    assert [p.name for p in tmp_path.iterdir()] == ["empty.vtrmap"]
    # a map this process did not create is never removed, even with nothing in it
    with pytest.raises(ValueError), Map.open(tmp_path / "empty.vtrmap", "a") as m:
        m.begin_run("teach")
        raise ValueError("boom")
    assert states(tmp_path / "empty.vtrmap") == [("teach", "aborted", 0, "ValueError: boom")]


KILLED_WRITER = textwrap.dedent("""
    import sys
    import numpy as np
    sys.path.insert(0, sys.argv[2])
    from test_map import CAMERA, make_frame, pose, cov
    from vtr.map import Map
    from vtr.types import Keyframe
    rng = np.random.default_rng(0)
    m = Map.create(sys.argv[1], CAMERA)
    run = m.begin_run("teach", source="killed")
    for i in range(100000):
        frame = make_frame(rng, 50, index=i)
        v = m.add_keyframe(run, Keyframe(i, frame, pose(0.5 * i), cov(), 50))
        print(v.id, flush=True)
        if i == 4:
            print("writing", flush=True)
            sys.stdin.readline()   # hold the lock until the test says so
""")


def _start_writer(path):
    proc = subprocess.Popen(
        [sys.executable, "-c", KILLED_WRITER, str(path), os.path.dirname(__file__)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + SUBPROCESS_TIMEOUT_S
    while (line := proc.stdout.readline()) != "writing\n":
        assert line, f"writer died: {proc.stderr.read()}"
        assert time.monotonic() < deadline
    return proc


def test_live_writer_is_running_killed_writer_is_interrupted_and_never_finished(tmp_path, kitti_clip):
    path = tmp_path / "killed.vtrmap"
    proc = _start_writer(path)
    try:
        with Map.open(path) as m:  # a reader while the writer holds the lock
            [info] = m.runs()
            assert (info.state, info.n_vertices) == ("running", 5)
        with pytest.raises(MapError, match=r"killed.vtrmap: another process is writing this map"):
            Map.open(path, "a")
        # the same through the command: one line, nothing written
        r = CliRunner().invoke(main, ["repeat", str(kitti_clip), "--map", str(path), "--out", str(tmp_path / "o")])
        assert r.exit_code == 1 and r.stderr.count("\n") == 1
        assert r.stderr.startswith(f"vtr: error: {path}: another process is writing this map")
    finally:
        proc.kill()
        proc.wait()
        proc.stdin.close()
        proc.stdout.close()
        proc.stderr.close()
    with Map.open(path) as m:
        [info] = m.runs()
        assert (info.state, info.finished, info.n_vertices) == ("interrupted", False, 5)
        with pytest.raises(MapError, match="teach run 0 is interrupted, not finished.*allow_partial=True"):
            m.check_taught_route()
        m.check_taught_route(allow_partial=True)
    # a writer that opens the map (e.g. a repeat) never marks the interrupted teach finished
    with Map.open(path, "a") as m:
        assert m.run(0).state == "interrupted"
        rep = m.begin_run("repeat", source="after the kill")
        add_vertices(m, rep, 2, seed=4)
    assert states(path) == [("teach", "aborted", 5, INTERRUPTED_REASON), ("repeat", "finished", 2, "")]
    # ... nor does merely opening and closing it
    path2 = tmp_path / "killed2.vtrmap"
    proc = _start_writer(path2)
    proc.kill()
    proc.wait()
    for f in (proc.stdin, proc.stdout, proc.stderr):
        f.close()
    with Map.open(path2, "a") as m:
        assert m.open_run == 0
    assert states(path2) == [("teach", "interrupted", 5, "")]


def test_second_writer_gets_one_clear_line(tmp_path):
    path = tmp_path / "route.vtrmap"
    with Map.create(path, CAMERA) as m:
        add_vertices(m, m.begin_run("teach"), 2)
        with pytest.raises(MapError, match=r"^\S*route.vtrmap: another process is writing this map"):
            Map.open(path, "a")
        with Map.open(path) as reader:  # readers are welcome
            assert reader.runs()[0].state == "running" and reader.runs()[0].n_vertices == 2
    with Map.open(path, "a") as m:  # the lock went with the first writer
        add_vertices(m, m.begin_run("repeat"), 1)
    assert [s[:3] for s in states(path)] == [("teach", "finished", 2), ("repeat", "finished", 1)]


def test_closed_map_is_one_self_contained_file(tmp_path):
    path = tmp_path / "route.vtrmap"
    umask = os.umask(0o022)
    os.umask(umask)
    with Map.create(path, CAMERA) as m:
        assert path.stat().st_mode & 0o777 == 0o666 & ~umask  # an ordinary file, not a private temporary
        add_vertices(m, m.begin_run("teach"), 4)
        assert os.path.exists(f"{path}-wal")  # written through the write-ahead log ...
    assert sorted(p.name for p in tmp_path.iterdir()) == ["route.vtrmap"]  # ... folded back on close
    with Map.open(path, "a") as m:
        add_vertices(m, m.begin_run("repeat"), 3, seed=2)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["route.vtrmap"]
    copy_dir = tmp_path / "copy"
    copy_dir.mkdir()
    shutil.copyfile(path, copy_dir / "alone.vtrmap")  # the file alone, no side files
    assert [s[:3] for s in states(copy_dir / "alone.vtrmap")] == [("teach", "finished", 4), ("repeat", "finished", 3)]
    con = sqlite3.connect(path)
    assert con.execute("PRAGMA journal_mode").fetchone()[0] == "delete"
    assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    con.close()


def test_opens_read_only_from_read_only_folder_and_media(tmp_path):
    folder = tmp_path / "ro"
    folder.mkdir()
    path = folder / "route.vtrmap"
    with Map.create(path, CAMERA) as m:
        add_vertices(m, m.begin_run("teach"), 3)
    # a WAL-mode map (as a killed writer leaves it, log folded) on read-only media has no -shm and
    # cannot make one: mode=ro cannot read it, immutable=1 can (the store falls back to it)
    wal_mode = tmp_path / "walmode.vtrmap"
    shutil.copyfile(path, wal_mode)
    con = sqlite3.connect(wal_mode)
    assert con.execute("PRAGMA journal_mode = WAL").fetchone()[0] == "wal"
    con.close()
    assert not os.path.exists(f"{wal_mode}-wal")
    con = connect(wal_mode, readonly=True, immutable=True)
    assert con.execute("SELECT COUNT(*) FROM vertices").fetchone()[0] == 3
    con.close()
    assert not os.path.exists(f"{wal_mode}-shm") and not os.path.exists(f"{wal_mode}-wal")
    folder.chmod(0o555)
    path.chmod(0o444)
    try:
        with Map.open(path) as m:
            assert [(r.state, r.n_vertices) for r in m.runs()] == [("finished", 3)]
            assert len(landmarks_in_map_frame(m)[0]) > 0
        assert sorted(p.name for p in folder.iterdir()) == ["route.vtrmap"]
    finally:
        folder.chmod(0o755)
        path.chmod(0o644)


def test_read_only_folder_refuses_writing_but_reads(tmp_path, permissions_bind):
    """A map in a read-only folder: opening it to append is refused naming the map, reading it works, and nothing
    is created beside it (run in a process where permissions bind, root included)."""
    path = tmp_path / "route.vtrmap"
    with Map.create(path, CAMERA) as m:
        add_vertices(m, m.begin_run("teach"), 2)
    code = textwrap.dedent(
        """
        import sys
        from vtr.errors import MapError
        from vtr.map import Map
        try:
            Map.open(sys.argv[1], "a").close()
            sys.exit("opened for appending")
        except MapError as err:
            assert "route.vtrmap" in str(err), err
        with Map.open(sys.argv[1]) as m:
            print(m.runs()[0].n_vertices)
        """
    )
    pristine = path.read_bytes()
    tmp_path.chmod(0o555)
    path.chmod(0o444)
    try:
        r = subprocess.run(
            permissions_bind([sys.executable, "-c", code, str(path)]), capture_output=True, text=True, timeout=120
        )
        assert r.returncode == 0 and r.stdout.strip() == "2", r.stderr
        assert sorted(p.name for p in tmp_path.iterdir()) == ["route.vtrmap"]
        assert path.read_bytes() == pristine
    finally:
        tmp_path.chmod(0o755)
        path.chmod(0o644)


def test_unfolded_log_on_read_only_media_is_a_clear_error(tmp_path, monkeypatch):
    """When mode=ro cannot open and a -wal with data lies beside the map, immutable=1 would silently
    drop its data: refuse with one line instead."""
    import vtr.map.database as database

    path = tmp_path / "route.vtrmap"
    with Map.create(path, CAMERA) as m:
        add_vertices(m, m.begin_run("teach"), 2)
    (tmp_path / "route.vtrmap-wal").write_bytes(b"\0" * 4096)
    real = database.connect

    def ro_fails(p, readonly, immutable=False):
        conn = real(p, readonly, immutable)
        if readonly and not immutable:
            conn.close()
            conn = sqlite3.connect(":memory:")
            conn.execute("PRAGMA query_only = ON")
            return _Failing(conn)
        return conn

    monkeypatch.setattr(database, "connect", ro_fails)
    with pytest.raises(MapError, match=r"route.vtrmap: cannot open read-only .* route.vtrmap-wal holds data"):
        Map.open(path)


class _Failing:
    """A connection whose first query fails as mode=ro does on read-only media without -shm."""

    def __init__(self, conn: sqlite3.Connection) -> None:
        self._conn = conn

    def execute(self, *args):
        raise sqlite3.OperationalError("unable to open database file")

    def close(self) -> None:
        self._conn.close()


def _kill_writer(proc) -> None:
    """SIGKILL a writer started by ``_start_writer`` (its run left running, its log unfolded) and reap it."""
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    for f in (proc.stdin, proc.stdout, proc.stderr):
        f.close()


def test_sigkill_writer_left_running_then_reader_sees_interrupted_in_new_process(tmp_path):
    path = tmp_path / "killed.vtrmap"
    _kill_writer(_start_writer(path))
    code = "import sys; from vtr.map import Map; m = Map.open(sys.argv[1]); print(m.runs()[0].state); m.close()"
    r = subprocess.run(
        [sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=SUBPROCESS_TIMEOUT_S
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "interrupted"


JOURNAL_PROBE = (
    "import sqlite3, sys; c = sqlite3.connect(sys.argv[1], timeout=0); "
    "print(c.execute('PRAGMA journal_mode = DELETE').fetchone()[0])"
)


def test_reader_in_the_same_process_keeps_the_writers_sqlite_locks(tmp_path):
    """Closing any descriptor of a file drops all the process's POSIX locks on it, SQLite's shared
    lock included, after which another process could take the map out of WAL mode under the
    writer. Readers opened and closed beside a writer must not do that."""
    path = tmp_path / "route.vtrmap"

    def other_process_switches_journal() -> bool:
        r = subprocess.run(
            [sys.executable, "-c", JOURNAL_PROBE, str(path)],
            capture_output=True,
            text=True,
            timeout=SUBPROCESS_TIMEOUT_S,
        )
        assert r.returncode == 0 or "database is locked" in r.stderr, r.stderr
        return r.returncode == 0

    with Map.create(path, CAMERA) as m:
        add_vertices(m, m.begin_run("teach"), 1)
        assert not other_process_switches_journal()
        for _ in range(2):
            with Map.open(path) as reader:
                reader.runs()
            with pytest.raises(MapError, match="another process"):
                Map.open(path, "a")
        assert not other_process_switches_journal()
        add_vertices(m, 0, 1, seed=1)
    assert [s[:3] for s in states(path)] == [("teach", "finished", 2)]


def test_an_unfinished_route_error_names_its_way_out_and_survives_pickling():
    """The library names allow_partial, the command line its option; a batch worker's error crosses processes."""
    import pickle

    from vtr.errors import UnfinishedRouteError

    err = UnfinishedRouteError("route.vtrmap: teach run 0 is aborted, not finished", 12)
    assert "allow_partial=True to use its 12 vertices" in str(err) and "--" not in str(err)
    back = pickle.loads(pickle.dumps(err))
    assert type(back) is UnfinishedRouteError and str(back) == str(err) and back.vertices == 12
    assert "(--allow-partial to use its 12 vertices anyway)" in str(err.allowed_by("--allow-partial"))


def test_killed_writers_log_is_reported_by_readers_and_folded_by_a_writer(tmp_path):
    """After a SIGKILLed writer its vertices live only in the -wal: readers say the map is not closed (map info
    warns, map check fails naming --repair), a copy of the file alone lacks them; a writer or --repair folds them."""
    path = tmp_path / "killed.vtrmap"
    _kill_writer(_start_writer(path))
    assert os.path.getsize(f"{path}-wal") > 0
    alone = tmp_path / "alone"
    alone.mkdir()
    shutil.copyfile(path, alone / "copy.vtrmap")
    assert states(alone / "copy.vtrmap") == []  # the file alone: the run is only in the log
    info = CliRunner().invoke(main, ["map", "info", str(path)])
    assert info.exit_code == 0, info.output
    assert "warning: not closed:" in info.output and "vtr map check --repair" in info.output
    check = CliRunner().invoke(main, ["map", "check", str(path)])
    assert check.exit_code == 1 and "not closed" in check.output and "--repair" in check.output, check.output
    repaired = CliRunner().invoke(main, ["map", "check", "--repair", str(path)])
    assert repaired.exit_code == 0, repaired.output
    assert "folded" in repaired.output and ": ok (" in repaired.output
    shutil.copyfile(path, alone / "after.vtrmap")
    [(kind, state, n, _)] = states(alone / "after.vtrmap")  # now the file alone holds the killed run
    assert (kind, state) == ("teach", "interrupted") and n >= 5
    assert "not closed" not in CliRunner().invoke(main, ["map", "info", str(path)]).output


def test_a_writer_folds_a_killed_writers_log_on_open(tmp_path):
    path = tmp_path / "killed.vtrmap"
    _kill_writer(_start_writer(path))
    with Map.open(path) as m:
        assert m.not_closed() is not None and m.file.unfolded_pages() > 0
    with Map.open(path, "a") as m:
        assert m.file.unfolded_pages() == 0  # folded before anything else happens
        copy = tmp_path / "copy.vtrmap"
        shutil.copyfile(path, copy)  # while the writer holds it: the file alone is whole
    assert [s[:2] for s in states(copy)] == [("teach", "interrupted")]
    with Map.open(path) as m:
        assert m.not_closed() is None


def test_not_closed_reads_the_log_as_sqlite_does(tmp_path):
    """A live writer's log is not reported; a log whose header has a flipped byte is ignored by SQLite (the file
    alone is the map) and not reported either; a flipped byte in the last frame drops only the last commit."""
    path = tmp_path / "live.vtrmap"
    proc = _start_writer(path)
    try:
        with Map.open(path) as m:
            assert m.runs()[0].state == "running" and m.not_closed() is None  # its writer holds it
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        for f in (proc.stdin, proc.stdout, proc.stderr):
            f.close()
    wal = Path(f"{path}-wal")
    with Map.open(path) as m:
        pages = m.file.unfolded_pages()
        assert pages > 0
    data = bytearray(wal.read_bytes())
    data[-1] ^= 0x01  # the last frame's page: its commit is not valid
    wal.write_bytes(bytes(data))
    Path(f"{path}-shm").unlink()  # SQLite rebuilds its index of the log from the log
    with Map.open(path) as m:
        fewer = m.file.unfolded_pages()
        assert 0 < fewer < pages and m.runs()[0].n_vertices == 4  # the fifth vertex's commit dropped
    data[16] ^= 0x01  # salt-1 in the header: SQLite ignores the whole log
    wal.write_bytes(bytes(data))
    Path(f"{path}-shm").unlink()
    with Map.open(path) as m:
        assert m.not_closed() is None and m.runs() == []


@pytest.mark.parametrize("suffix", ["-wal", "-shm"])
def test_a_side_file_link_is_named_not_blamed_on_the_map(tmp_path, suffix):
    """A symbolic link where SQLite keeps the map's log: one line naming that file, for readers and writers; the
    target is never written (it used to be 'not a readable vtr map', blaming the map)."""
    from vtr.errors import MapError
    from vtr.map import Map
    from vtr.sim import synthetic as syn

    path = tmp_path / "m.vtrmap"
    with Map.create(path, syn.zed_camera()) as m:
        m.begin_run("teach")
    target = tmp_path / "elsewhere"
    target.write_bytes(b"mine")
    link = tmp_path / f"m.vtrmap{suffix}"
    link.symlink_to(target)
    for mode in ("r", "a"):
        with pytest.raises(MapError) as err:
            Map.open(path, mode)
        assert str(link) in str(err.value) and "symbolic link" in str(err.value) and "\n" not in str(err.value)
    assert target.read_bytes() == b"mine"
    fresh = tmp_path / "new.vtrmap"
    Path(f"{fresh}{suffix}").symlink_to(tmp_path / "dangling")
    with pytest.raises(MapError, match="symbolic link"):
        Map.create(fresh, syn.zed_camera())
    assert not fresh.exists() and not (tmp_path / "dangling").exists()
