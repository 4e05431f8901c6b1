"""`vtr teach` / `vtr repeat` record their runs truthfully, on the shipped KITTI clip through the real
command: an error, Ctrl-C (SIGINT) or SIGTERM mid-teach writes the keyframes still in the odometry
window and records the run aborted with the reason; a teach that wrote nothing leaves no file; a
SIGKILLed teach reads as interrupted; `vtr repeat` refuses a teach that did not finish unless
--allow-partial; a failed repeat is aborted; a one-vertex route is refused."""

from __future__ import annotations

import csv
import re
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from vtr.app.pipeline import teach_command
from vtr.cli import main
from vtr.config import Config
from vtr.errors import MapError, Terminated
from vtr.map import Map

BAD_FRAME = 6  # frame whose left image is corrupted in the damaged clip
SIGNAL_AFTER_VERTICES = 2  # the signal is sent once the map holds this many vertices
SUBPROCESS_TIMEOUT_S = 120
WINDOW = Config().odometry.window_keyframes


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def one_line_error(stderr: str, *needles: str) -> str:
    assert "Traceback" not in stderr
    line = stderr.strip().replace("\r", "\n").splitlines()[-1]
    assert line.startswith("vtr: error:"), line
    for n in needles:
        assert n in line, line
    return line


def rows(path: Path) -> str:
    """Every row of the map (its content; the SQLite header may change when a session opens it)."""
    con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        return "\n".join(con.iterdump())
    finally:
        con.close()


def taught(path: Path) -> tuple[list, np.ndarray]:
    """(run infos, t_ns of the teach run's vertices)."""
    with Map.open(path) as m:
        return m.runs(), m.timestamps(0)[1]


@pytest.fixture(scope="module")
def reference(kitti_clip, tmp_path_factory):
    """t_ns of the vertices of complete teaches over the first k frames of the clip, by k."""
    cache: dict[int, np.ndarray] = {}

    def vertices_of_first(k: int) -> np.ndarray:
        if k not in cache:
            path = tmp_path_factory.mktemp("ref") / "ref.vtrmap"
            teach_command(kitti_clip, path, f"0:{k}", Config())
            cache[k] = taught(path)[1]
        return cache[k]

    return vertices_of_first


@pytest.fixture(scope="module")
def damaged_clip(kitti_clip, tmp_path_factory):
    """The first 12 frames of the clip with the left image of frame BAD_FRAME unreadable."""
    clip = tmp_path_factory.mktemp("damaged") / "clip"
    shutil.copytree(kitti_clip, clip)
    (clip / "image_0" / f"{BAD_FRAME:06d}.png").write_bytes(b"not a png")
    return clip


def test_teach_error_mid_run_writes_window_and_aborts(damaged_clip, reference, tmp_path):
    path = tmp_path / "route.vtrmap"
    r = invoke("teach", damaged_clip, "--map", path, "--frames", "0:12")
    assert r.exit_code == 1
    one_line_error(r.stderr, f"{BAD_FRAME:06d}.png", "cannot decode image")
    [run], t_ns = taught(path)
    assert (run.kind, run.state) == ("teach", "aborted")
    assert re.fullmatch(rf"DataError: .*image_0/{BAD_FRAME:06d}\.png: cannot decode image.*", run.reason)
    # every keyframe of the frames processed before the error is in the map, the window included:
    # exactly the vertices of a complete teach over those frames
    expected = reference(BAD_FRAME)
    assert len(expected) > WINDOW
    np.testing.assert_array_equal(t_ns, expected)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["route.vtrmap"]  # no -wal/-shm left
    # `map info` shows it; `repeat` refuses it in one line and writes nothing ...
    info = invoke("map", "info", path)
    assert info.exit_code == 0 and re.search(r"0\s+teach\s+yes\s+aborted\s+" + str(len(expected)), info.stdout)
    assert f"run 0 aborted: DataError: {damaged_clip}" in info.stdout and "--allow-partial" in info.stdout
    before = rows(path)
    r = invoke("repeat", damaged_clip, "--map", path, "--out", tmp_path / "rep", "--frames", "1:5")
    assert r.exit_code == 1
    one_line_error(r.stderr, "teach run 0 is aborted", "not finished", "--allow-partial")
    assert rows(path) == before
    # ... unless --allow-partial: then it runs and only its own run is added
    r = invoke("repeat", damaged_clip, "--map", path, "--out", tmp_path / "rep", "--frames", "1:5", "--allow-partial")
    assert r.exit_code == 0, r.output
    runs, t_after = taught(path)
    assert [(x.kind, x.state) for x in runs] == [("teach", "aborted"), ("repeat", "finished")]
    np.testing.assert_array_equal(t_after, t_ns)


def test_teach_failing_before_any_vertex_leaves_no_file(kitti_clip, tmp_path):
    clip = tmp_path / "clip"
    shutil.copytree(kitti_clip, clip)
    (clip / "image_1" / "000000.png").write_bytes(b"")  # the first frame's right image
    path = tmp_path / "maps" / "route.vtrmap"
    r = invoke("teach", clip, "--map", path, "--frames", "0:4")
    assert r.exit_code == 1
    one_line_error(r.stderr, "image_1/000000.png")
    assert list((tmp_path / "maps").iterdir()) == []  # no map, no side or temporary file
    r = invoke("teach", kitti_clip, "--map", path, "--frames", "0:3")  # so teaching again just works
    assert r.exit_code == 0, r.output
    assert [(x.state, x.n_vertices) for x in taught(path)[0]] == [("finished", 3)]


def _teach_process(clip: Path, path: Path) -> subprocess.Popen:
    """`vtr teach` over the whole clip in a new process (SIGINT restored to Python's default)."""
    return subprocess.Popen(
        [sys.executable, "-m", "vtr", "teach", str(clip), "--map", str(path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


def _wait_for_vertices(proc: subprocess.Popen, path: Path, n: int) -> int:
    """Poll the map (read-only, as another process) until it holds ``n`` vertices; returns the count seen."""
    deadline = time.monotonic() + SUBPROCESS_TIMEOUT_S
    while True:
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "teach too slow"
        if path.exists():
            try:
                with Map.open(path) as m:
                    if m.runs() and m.runs()[0].n_vertices >= n:
                        return m.runs()[0].n_vertices
            except MapError:
                pass
        time.sleep(0.05)


@pytest.mark.parametrize(
    ("sig", "code", "message", "reason"),
    [
        (signal.SIGTERM, 143, "vtr: terminated (SIGTERM)", "terminated by SIGTERM"),
        (signal.SIGINT, 130, "vtr: interrupted (Ctrl-C)", "interrupted by Ctrl-C (SIGINT)"),
    ],
)
def test_signal_mid_teach_writes_window_and_aborts(kitti_clip, reference, tmp_path, sig, code, message, reason):
    path = tmp_path / "route.vtrmap"
    proc = _teach_process(kitti_clip, path)
    seen = _wait_for_vertices(proc, path, SIGNAL_AFTER_VERTICES)
    proc.send_signal(sig)
    _out, err = proc.communicate(timeout=SUBPROCESS_TIMEOUT_S)
    assert proc.returncode == code, err
    assert "Traceback" not in err and err.replace("\r", "\n").strip().splitlines()[-1] == message
    [run], t_ns = taught(path)
    assert (run.state, run.reason) == ("aborted", reason)
    # a vertex is written when it leaves the odometry window, so when the map held `seen` vertices the
    # process had made at least seen + WINDOW keyframes: all of them are stored (the window was
    # written, not dropped) ...
    assert len(t_ns) >= seen + WINDOW
    # ... and nothing else than the keyframes of a complete teach up to the last stored one
    with Map.open(path) as m:
        last_frame = m.vertex(int(m.vertex_ids(0)[-1])).frame.index
    np.testing.assert_array_equal(t_ns, reference(last_frame + 1))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["route.vtrmap"]


@pytest.mark.parametrize(
    ("signal_exc", "code", "message", "reason"),
    [
        (Terminated, 143, "vtr: terminated (SIGTERM)", "terminated by SIGTERM"),
        (KeyboardInterrupt, 130, "vtr: interrupted (Ctrl-C)", "interrupted by Ctrl-C (SIGINT)"),
    ],
)
def test_signal_surfacing_from_a_compiled_kernel_still_aborts_in_order(
    kitti_clip, tmp_path, monkeypatch, signal_exc, code, message, reason
):
    """A signal handler that raises while a numba kernel returns surfaces as a SystemError caused by the
    signal's exception (seen in the process test above): still an orderly Ctrl-C / SIGTERM exit."""
    from vtr.navigation.teach import Teach

    real, calls = Teach.process_frame, []

    def process_frame(self, frame):
        calls.append(1)
        if len(calls) == SIGNAL_AFTER_VERTICES + WINDOW:
            try:
                raise signal_exc()
            except signal_exc as err:
                raise SystemError("CPUDispatcher(<function schur>) returned a result with an exception set") from err
        return real(self, frame)

    monkeypatch.setattr(Teach, "process_frame", process_frame)
    path = tmp_path / "route.vtrmap"
    r = invoke("teach", kitti_clip, "--map", path)
    assert r.exit_code == code, r.output
    assert "Traceback" not in r.stderr and r.stderr.strip().splitlines()[-1] == message
    [run], t_ns = taught(path)
    assert (run.state, run.reason) == ("aborted", reason) and len(t_ns) > 0


@pytest.mark.parametrize(
    ("sig", "code", "reason"),
    [
        (signal.SIGTERM, 143, "terminated by SIGTERM"),
        (signal.SIGINT, 130, "interrupted by Ctrl-C (SIGINT)"),
    ],
)
def test_signal_during_a_keyframe_write_loses_no_keyframe(
    kitti_clip, reference, tmp_path, monkeypatch, sig, code, reason
):
    """The signal arrives while a finalized keyframe is being written: it is delivered once the frame is
    done, so the map holds exactly the keyframes of a complete teach up to the last one (none skipped)."""
    import os

    real, calls = Map.add_keyframe, []

    def add_keyframe(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == SIGNAL_AFTER_VERTICES + 1:
            os.kill(os.getpid(), sig)  # Python runs the handler at its next instruction
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Map, "add_keyframe", add_keyframe)
    path = tmp_path / "route.vtrmap"
    r = invoke("teach", kitti_clip, "--map", path)
    assert r.exit_code == code, r.output
    [run], t_ns = taught(path)
    assert (run.state, run.reason) == ("aborted", reason)
    assert len(t_ns) >= SIGNAL_AFTER_VERTICES + 1 + WINDOW - 1
    with Map.open(path) as m:
        last_frame = m.vertex(int(m.vertex_ids(0)[-1])).frame.index
    np.testing.assert_array_equal(t_ns, reference(last_frame + 1))


def test_sigkilled_teach_reads_interrupted_and_repeat_refuses(kitti_clip, tmp_path):
    path = tmp_path / "route.vtrmap"
    proc = _teach_process(kitti_clip, path)
    _wait_for_vertices(proc, path, SIGNAL_AFTER_VERTICES)
    proc.kill()
    proc.communicate(timeout=SUBPROCESS_TIMEOUT_S)
    [run], t_ns = taught(path)
    assert (run.state, run.reason, run.finished) == ("interrupted", "", False) and len(t_ns) >= 2
    before = rows(path)
    info = invoke("map", "info", path)
    assert info.exit_code == 0 and re.search(r"0\s+teach\s+yes\s+interrupted\s+\d+", info.stdout)
    r = invoke("repeat", kitti_clip, "--map", path, "--out", tmp_path / "rep", "--frames", "1:4")
    assert r.exit_code == 1
    one_line_error(r.stderr, "teach run 0 is interrupted", "--allow-partial")
    assert [(x.kind, x.state) for x in taught(path)[0]] == [("teach", "interrupted")]
    assert rows(path) == before


def test_failed_repeat_is_aborted_not_finished(kitti_clip, damaged_clip, tmp_path):
    path = tmp_path / "route.vtrmap"
    teach_command(kitti_clip, path, "0:12:2", Config())
    r = invoke("repeat", damaged_clip, "--map", path, "--out", tmp_path / "rep", "--frames", "1:12")
    assert r.exit_code == 1
    one_line_error(r.stderr, f"{BAD_FRAME:06d}.png")
    runs, _ = taught(path)
    assert [(x.kind, x.state) for x in runs] == [("teach", "finished"), ("repeat", "aborted")]
    assert runs[1].reason.startswith("DataError:") and runs[1].n_vertices >= 1


def test_one_vertex_route_is_refused_in_one_line(kitti_clip, tmp_path):
    path = tmp_path / "route.vtrmap"
    r = invoke("teach", kitti_clip, "--map", path, "--frames", "0:1")
    assert r.exit_code == 0, r.output
    assert [(x.state, x.n_vertices) for x in taught(path)[0]] == [("finished", 1)]
    r = invoke("repeat", kitti_clip, "--map", path, "--out", tmp_path / "rep", "--frames", "1:6")
    assert r.exit_code == 1
    one_line_error(r.stderr, "the taught path has 1 vertex", "no segment")
    assert [x.kind for x in taught(path)[0]] == ["teach"]


FILE_SIZE_LIMIT_BYTES = 600_000  # the map's log outgrows this within the clip: a full disk for SQLite


def _full_disk() -> None:
    """In the child: files cannot grow past FILE_SIZE_LIMIT_BYTES (writes fail as on a full disk)."""
    import resource

    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (FILE_SIZE_LIMIT_BYTES, FILE_SIZE_LIMIT_BYTES))


@pytest.mark.skipif(not hasattr(signal, "SIGXFSZ"), reason="needs POSIX file size limits")
def test_full_disk_mid_teach_is_one_line_and_never_finished(kitti_clip, reference, tmp_path):
    path = tmp_path / "route.vtrmap"
    r = subprocess.run(
        [sys.executable, "-m", "vtr", "teach", str(kitti_clip), "--map", str(path)],
        capture_output=True,
        text=True,
        timeout=SUBPROCESS_TIMEOUT_S,
        preexec_fn=_full_disk,
    )
    assert r.returncode == 1
    one_line_error(r.stderr, str(path))
    [run], t_ns = taught(path)  # the map opens with what was committed
    assert not run.finished and run.state in ("aborted", "interrupted")  # aborted when the reason still fit
    assert 0 < len(t_ns) < 51
    with Map.open(path) as m:
        last_frame = m.vertex(int(m.vertex_ids(0)[-1])).frame.index
    np.testing.assert_array_equal(t_ns, reference(last_frame + 1))
    r = invoke("repeat", kitti_clip, "--map", path, "--out", tmp_path / "rep", "--frames", "1:4")
    one_line_error(r.stderr, "not finished", "--allow-partial")


def _localized_in_map(path: Path) -> list[int]:
    with Map.open(path) as m:
        repeat = [r for r in m.runs() if r.kind == "repeat"][-1]
        return sorted(e.from_id for e in m.edges(repeat.id, "spatial"))


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_an_interrupted_repeat_leaves_map_and_reports_in_agreement(kitti_clip, tmp_path, sig):
    """A repeat stopped by a signal mid-run (a real process, localizing on its own thread while odometry runs
    ahead): every localized vertex in the map has its localization.csv row and its landmarks.csv rows."""
    path = tmp_path / "route.vtrmap"
    assert invoke("teach", kitti_clip, "--map", path, "--frames", "0::2").exit_code == 0
    out = tmp_path / "repeat"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "vtr",
            "repeat",
            str(kitti_clip),
            "--map",
            str(path),
            "--out",
            str(out),
            "--threads",
            "2",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.monotonic() + SUBPROCESS_TIMEOUT_S
    while True:  # until the run has localized a few leaves
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "repeat too slow"
        csv_path = out / "localization.csv"
        if csv_path.exists() and len(csv_path.read_text().splitlines()) > 3:
            break
        time.sleep(0.02)
    proc.send_signal(sig)
    _out, err = proc.communicate(timeout=SUBPROCESS_TIMEOUT_S)
    assert proc.returncode in (130, 143), err
    rows = list(csv.DictReader(open(out / "localization.csv")))
    reported = sorted(int(r["leaf_id"]) for r in rows if r["success"] == "1")
    assert reported == _localized_in_map(path)
    with Map.open(path) as m:
        repeat = [r for r in m.runs() if r.kind == "repeat"][-1]
        assert repeat.state == "aborted"
        assert len(rows) == repeat.n_vertices  # one row per written vertex
    landmark_leaves = {int(r["leaf_id"]) for r in csv.DictReader(open(out / "landmarks.csv"))}
    assert landmark_leaves == set(reported)


def test_a_teach_whose_odometry_fails_on_most_frames_fails(kitti_clip, tmp_path):
    """Odometry failing on 9 of 10 frames (real featureless images) ends `vtr teach` failed: one line naming the
    count and the setting, exit 1, the run aborted with that reason, never finished; the threshold is a setting."""
    import cv2

    clip = tmp_path / "clip"
    shutil.copytree(kitti_clip, clip)
    for i in range(1, 10):  # frames 1..9: a uniform grey image, nothing to track
        for side in ("image_0", "image_1"):
            png = clip / side / f"{i:06d}.png"
            grey = np.full_like(cv2.imread(str(png), cv2.IMREAD_GRAYSCALE), 128)
            assert cv2.imwrite(str(png), grey)
    path = tmp_path / "route.vtrmap"
    r = invoke("teach", clip, "--map", path, "--frames", "0:10")
    assert r.exit_code == 1, r.output
    line = one_line_error(r.stderr, "teach failed", "of 10 frames", "odometry.teach_max_failed_fraction")
    failed = int(re.search(r"failed on (\d+) of 10", line).group(1))
    assert failed >= 9
    [run] = taught(path)[0]
    assert run.state == "aborted" and not run.finished
    assert run.reason.startswith("TeachFailedError: teach failed: odometry failed on")
    r = invoke("map", "info", path)
    assert "aborted" in r.output and "teach failed" in r.output
    # the same frames with the bound raised to 1 (never fail) finish: the threshold is what decides
    config = tmp_path / "lenient.yaml"
    config.write_text("odometry:\n  teach_max_failed_fraction: 1.0\n")
    lenient = tmp_path / "lenient.vtrmap"
    r = invoke("teach", clip, "--map", lenient, "--frames", "0:10", "--config", config)
    assert r.exit_code == 0, r.output
    assert [x.state for x in taught(lenient)[0]] == ["finished"]


def test_a_killed_read_only_map_repeat_leaves_no_copy_behind(kitti_clip, tmp_path, monkeypatch):
    """`vtr repeat --read-only-map` SIGKILLed mid-run leaves its private copy of the map in the temporary folder;
    the next such repeat removes it (its lock is free), never a copy whose process still runs, and its own copy
    is gone when it ends."""
    import os
    import tempfile

    from vtr.app.private_copy import PREFIX, private_copy

    path = tmp_path / "route.vtrmap"
    teach_command(kitti_clip, path, "0:40:2", Config())
    before = rows(path)
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    env = {**os.environ, "TMPDIR": str(scratch)}
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "vtr",
            "repeat",
            str(kitti_clip),
            "--map",
            str(path),
            "--out",
            str(tmp_path / "killed"),
            "--read-only-map",
            "--frames",
            "1::1",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    deadline = time.monotonic() + SUBPROCESS_TIMEOUT_S
    while not (tmp_path / "killed" / "localization.csv").exists():  # copied, and repeating
        assert proc.poll() is None, proc.stderr.read()
        assert time.monotonic() < deadline
        time.sleep(0.05)
    proc.kill()
    proc.wait()
    proc.stderr.close()
    [left] = list(scratch.iterdir())  # the killed repeat's copy stays ...
    assert left.name.startswith(PREFIX) and (left / path.name).stat().st_size > 0
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    with private_copy(path) as live:  # ... and so does one whose process runs
        r = subprocess.run(
            [
                sys.executable,
                "-m",
                "vtr",
                "repeat",
                str(kitti_clip),
                "--map",
                str(path),
                "--out",
                str(tmp_path / "next"),
                "--read-only-map",
                "--frames",
                "1:8:2",
            ],
            capture_output=True,
            text=True,
            env=env,
            timeout=SUBPROCESS_TIMEOUT_S,
        )
        assert r.returncode == 0, r.stderr
        assert "removed 1 private map copy folder(s) left by killed --read-only-map repeats" in r.stderr
        assert list(scratch.iterdir()) == [live.parent]  # the stale one removed, the live one kept, its own gone
    assert list(scratch.iterdir()) == []
    assert rows(path) == before  # the map itself only read


UNFOLDED_TEACH = (
    "import os, sys; from pathlib import Path; from vtr.map import database; "
    "database.MapFile.fold_wal = lambda self: os._exit(0); "  # dies where the log would be folded
    "from vtr.app.pipeline import teach_command; from vtr.config import Config; "
    "teach_command(Path(sys.argv[1]), Path(sys.argv[2]), '0:20:2', Config())"
)


def test_a_read_only_map_repeat_copies_what_is_still_in_the_log(kitti_clip, tmp_path):
    """A finished teach whose process died before folding its log: the whole route is in the -wal only. A
    `--read-only-map` repeat copies the map whole (log included) and follows it, leaving the map untouched."""
    path = tmp_path / "route.vtrmap"
    r = subprocess.run(
        [sys.executable, "-c", UNFOLDED_TEACH, str(kitti_clip), str(path)],
        capture_output=True,
        text=True,
        timeout=SUBPROCESS_TIMEOUT_S,
    )
    assert r.returncode == 0, r.stderr
    with Map.open(path) as m:
        assert m.not_closed() is not None and [x.state for x in m.runs()] == ["finished"]
    before = (path.read_bytes(), Path(f"{path}-wal").read_bytes())
    r = invoke("repeat", kitti_clip, "--map", path, "--out", tmp_path / "ro", "--read-only-map", "--frames", "1:8:2")
    assert r.exit_code == 0, r.output
    assert (path.read_bytes(), Path(f"{path}-wal").read_bytes()) == before


def test_a_read_only_map_repeat_names_the_users_map_not_its_private_copy(kitti_clip, tmp_path):
    """An error about the map found while opening a `--read-only-map` repeat (here: another camera) names the map
    the user gave, not the temporary copy the repeat works on (it named /tmp/vtr-repeat-map-copy-.../...)."""
    path = tmp_path / "route.vtrmap"
    assert invoke("teach", kitti_clip, "--map", path, "--frames", "0:8:2").exit_code == 0
    clip = tmp_path / "recalibrated"
    shutil.copytree(kitti_clip, clip)
    calib = clip / "calib.txt"
    calib.write_text(calib.read_text().replace("7.070912000000e+02", "6.500000000000e+02"))
    r = invoke("repeat", clip, "--map", path, "--out", tmp_path / "ro", "--read-only-map", "--frames", "1:8:2")
    line = one_line_error(r.stderr, "map was taught with another camera", f"{path} has")
    assert "vtr-repeat-map-copy" not in line
