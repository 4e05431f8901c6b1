"""The `vtr` command when the environment is against it: outputs that cannot be written, a full
disk, damaged or odd inputs. Each ends with exit code 1 and a single line on stderr, never a
traceback; an impossible --out is refused before any work (teach writes no map)."""

from __future__ import annotations

import os
import re
import shutil
import struct
from pathlib import Path

import pytest
from click.testing import CliRunner

from vtr.cli import main
from vtr.cli.common import error_line
from vtr.errors import MapError
from vtr.io import open_source
from vtr.io.rosbag_writer import BagTopics, write_bag

DATA = Path(__file__).resolve().parents[2] / "datasets"
KITTI = DATA / "kitti06_clip"
EUROC = DATA / "euroc_v101_micro"
FULL = Path("/dev/full")  # every write fails with ENOSPC: a full disk on demand
needs_dev_full = pytest.mark.skipif(not FULL.exists(), reason="no /dev/full on this system")


PROGRESS_LINE = re.compile(r"^[\w ]+: \d+(/\d+)? \w+s\b")


def run(*args) -> tuple[int, str, str]:
    r = CliRunner().invoke(main, [str(a) for a in args])
    return r.exit_code, r.stdout, r.stderr


def assert_one_line(args, *named: str) -> str:
    code, out, err = run(*args)
    assert code == 1, (code, out, err)
    assert "Traceback" not in out + err
    # without a terminal, progress comes as `DESC: k/N frames` lines (no carriage returns): not errors
    lines = [ln for ln in err.strip().splitlines() if not PROGRESS_LINE.match(ln)]
    assert "\r" not in err
    assert len(lines) == 1 and lines[0].startswith("vtr: error: "), err
    for n in named:
        assert n in lines[0], lines[0]
    return lines[0]


# ------------------------------------------------------------------------------ --out


def test_out_is_an_existing_file(tmp_path):
    f = tmp_path / "taken"
    f.write_text("keep me")
    assert_one_line(["odometry", KITTI, "--out", f], f"--out {f}: exists and is not a folder")
    assert_one_line(["repeat", KITTI, "--map", tmp_path / "none.vtrmap", "--out", f], "exists and is not a folder")
    assert f.read_text() == "keep me"


def test_teach_refuses_out_before_writing_the_map(tmp_path):
    f = tmp_path / "taken"
    f.write_text("x")
    m = tmp_path / "route.vtrmap"
    assert_one_line(["teach", KITTI, "--map", m, "--frames", "0:6:2", "--out", f], "exists and is not a folder")
    assert not m.exists() and not list(tmp_path.glob("route.vtrmap*"))  # was: refused after the whole teach


def test_out_below_a_file(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    assert_one_line(["odometry", KITTI, "--out", f / "sub" / "dir"], f"{f} is not a folder")


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write anywhere")
def test_out_in_a_read_only_folder(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        assert_one_line(["odometry", KITTI, "--out", ro / "o"], "not writable")
    finally:
        ro.chmod(0o755)


# ------------------------------------------------------------------------------ full disk


@needs_dev_full
@pytest.mark.parametrize("victim", ["trajectory_tum.txt", "trajectory.png"])
def test_a_link_to_a_full_disk_is_not_written_through(tmp_path, victim):
    """A link planted at an output's name (here to /dev/full) is refused before any work (vtr.app.outputs)."""
    out = tmp_path / "o"
    out.mkdir()
    (out / victim).symlink_to(FULL)
    # the folder holds a file already: --force to write into it, and still never through a planted link
    line = assert_one_line(["odometry", KITTI, "--out", out, "--frames", "0:3", "--force"], "symbolic link")
    assert str(out / victim) in line


@pytest.mark.parametrize("limit", [300, 3000])
def test_no_room_while_writing_outputs(tmp_path, limit):
    """Writes that fail mid-run (a file-size limit: the kernel refuses a write past ``limit`` bytes, as a full
    disk refuses any) are one line naming the output folder; the output that failed is not left half written."""
    import resource
    import signal
    import subprocess
    import sys

    def small_files():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG instead
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    out = tmp_path / "o"
    r = subprocess.run(
        [sys.executable, "-m", "vtr", "odometry", KITTI, "--out", out, "--frames", "0:12"],
        capture_output=True,
        text=True,
        preexec_fn=small_files,
    )
    assert r.returncode == 1, (r.stdout, r.stderr)
    lines = [ln for ln in r.stderr.strip().splitlines() if not PROGRESS_LINE.match(ln)]
    assert len(lines) == 1 and lines[0].startswith("vtr: error: ") and str(out) in lines[0], r.stderr
    assert "File too large" in lines[0] and "Traceback" not in r.stderr
    assert not (out / "run.json").exists() and not list(out.glob(".vtr-tmp-*"))


@needs_dev_full
def test_full_disk_export_trajectory(tmp_path):
    """A link at the output (here to /dev/full) is refused with or without --force (docs/outputs.md); a disk that
    refuses the write (a file-size limit) is one line naming the output, which is then neither there nor half."""
    import resource
    import signal
    import subprocess
    import sys

    tum = tmp_path / "t.txt"
    tum.write_text("0.0 0 0 0 0 0 0 1\n1.0 1 0 0 0 0 0 1\n")
    dest = tmp_path / "full.csv"
    dest.symlink_to(FULL)
    for force in ([], ["--force"]):
        assert_one_line(["export-trajectory", tum, dest, "--to", "euroc", *force], str(dest), "symbolic link")

    def small_files():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG instead
        resource.setrlimit(resource.RLIMIT_FSIZE, (60, 60))

    new = tmp_path / "new.csv"
    r = subprocess.run(
        [sys.executable, "-m", "vtr", "export-trajectory", tum, new, "--to", "euroc"],
        capture_output=True,
        text=True,
        preexec_fn=small_files,
    )
    assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert str(new) in r.stderr and "File too large" in r.stderr
    assert not new.exists() and not list(tmp_path.glob(".vtr-tmp-*"))


def test_the_first_error_of_a_chain_is_reported():
    """A full disk fails the map write (MapError), then closing a CSV fails too: the MapError is the cause."""
    try:
        try:
            raise MapError("route.vtrmap: cannot write vertex 7 (disk full)")
        except MapError:
            raise OSError(28, "No space left on device") from None
    except OSError as err:
        assert error_line(err, ["out"]) == "route.vtrmap: cannot write vertex 7 (disk full)"
    assert error_line(PermissionError(13, "Permission denied", "/x/y")) == "/x/y: Permission denied"
    assert error_line(OSError(28, "No space left on device"), ["a", "b"]) == "writing a, b: No space left on device"


def test_missing_output_folder_names_the_file(tmp_path):
    tum = tmp_path / "t.txt"
    tum.write_text("0.0 0 0 0 0 0 0 1\n")
    assert_one_line(
        ["export-trajectory", tum, tmp_path / "no" / "such" / "dir.csv", "--to", "euroc"],
        "no/such/dir.csv",
        "No such file or directory",
    )


# ------------------------------------------------------------------------------ odd inputs


def test_zero_norm_quaternion_in_export_trajectory(tmp_path):
    tum = tmp_path / "t.txt"
    tum.write_text("0.0 0 0 0 0 0 0 1\n1.0 1 0 0 0 0 0 0\n")
    assert_one_line(["export-trajectory", tum, tmp_path / "o.csv", "--to", "euroc"], f"{tum}:2", "quaternion norm 0")


def test_rate_upper_bound(tmp_path):
    assert_one_line(
        ["repeat", KITTI, "--map", tmp_path / "m.vtrmap", "--out", tmp_path / "o", "--rate", "1e9"],
        "smoothing.rate_hz",
        "(0, 1000]",
    )


@pytest.mark.parametrize(
    ("content", "named"),
    [
        (bytes(range(256)) * 4, "not UTF-8"),
        (b"features:\n  n_levels: 0\n", "features.n_levels must be an integer in [1, 16]"),
        (b"odometry:\n  keyframe_translation_m: .nan\n", "odometry.keyframe_translation_m"),
    ],
)
def test_bad_config_files(tmp_path, content, named):
    cfg = tmp_path / "c.yaml"
    cfg.write_bytes(content)
    assert_one_line(["odometry", KITTI, "--out", tmp_path / "o", "--config", cfg], str(cfg), named)
    assert not (tmp_path / "o").exists()


def test_identical_euroc_camera_poses(tmp_path):
    shutil.copytree(EUROC, tmp_path / "e")
    root = tmp_path / "e" / "mav0"
    shutil.copy(root / "cam0" / "sensor.yaml", root / "cam1" / "sensor.yaml")
    assert_one_line(["odometry", tmp_path / "e", "--out", tmp_path / "o"], "cam1/sensor.yaml", "no stereo baseline")


def _kitti_bag(path: Path, topics: BagTopics, kind: str = "rosbag1") -> None:
    with open_source(KITTI) as src:
        write_bag(path, [src[i] for i in range(4)], src.camera, kind=kind, topics=topics)


def test_damaged_mcap(tmp_path):
    _kitti_bag(tmp_path / "b", BagTopics(), kind="mcap")
    f = tmp_path / "b" / "b.mcap"
    data = bytearray(f.read_bytes())
    data_end = data.rfind(b"\x0f" + (4).to_bytes(8, "little"))
    footer = len(data) - 8 - 29
    data[data_end + 1 : data_end + 9] = (2**62).to_bytes(8, "little")
    struct.pack_into("<Q", data, footer + 9, data_end)
    f.write_bytes(bytes(data))
    assert_one_line(["odometry", tmp_path / "b", "--out", tmp_path / "o"], "cannot open bag", "damaged")


def test_robot_topic_names_through_every_source_command(tmp_path):
    """A bag whose image topics are not named left/cam0: every SOURCE command takes the topic options."""
    bag = tmp_path / "robot.bag"
    _kitti_bag(bag, BagTopics("/front/image", "/rear/image", "/front/camera_info", "/rear/camera_info"))
    assert_one_line(["odometry", bag, "--out", tmp_path / "o"], "--left-topic")
    topics = ["--left-topic", "/front/image", "--right-topic", "/rear/image"]
    code, out, err = run("odometry", bag, "--out", tmp_path / "o", *topics)
    assert code == 0, err
    assert (tmp_path / "o" / "trajectory_tum.txt").is_file()
    code, out, err = run("teach", bag, "--map", tmp_path / "m.vtrmap", *topics)
    assert code == 0, err
    code, out, err = run(
        "repeat",
        bag,
        "--map",
        tmp_path / "m.vtrmap",
        "--out",
        tmp_path / "r",
        *topics,
        "--left-info-topic",
        "/front/camera_info",
        "--allow-unpaired",
    )
    assert code == 0, err
    code, out, err = run("convert", bag, tmp_path / "k", *topics)
    assert code == 0, err
    assert_one_line(
        ["teach", KITTI, "--map", tmp_path / "n.vtrmap", "--left-topic", "/x"],
        "--left-topic apply to ROS bag sources only",
    )
    assert not (tmp_path / "n.vtrmap").exists()


def test_map_with_landmarks_behind_the_camera(tmp_path):
    """A damaged map whose landmarks lie behind their camera: was a ValueError traceback in bundle_adjust."""
    import sqlite3

    from vtr.map.codec import decode_frame, pack_arrays

    m = tmp_path / "route.vtrmap"
    code, _, err = run("teach", KITTI, "--map", m, "--frames", "0:6:2")
    assert code == 0, err
    with sqlite3.connect(m) as db:
        for (trigger,) in db.execute(
            "SELECT name FROM sqlite_master WHERE type = 'trigger' AND tbl_name = 'vertex_data'"
        ).fetchall():
            db.execute(f"DROP TRIGGER {trigger}")  # vertex data is immutable: damage it from outside
        vid, blob = db.execute("SELECT id, data FROM vertex_data ORDER BY id LIMIT 1").fetchone()
        f = decode_frame(blob, 0, 0, "x")
        arrays = {
            "uv": f.features.uv,
            "octave": f.features.octave,
            "descriptors": f.features.descriptors,
            "u_right": f.u_right,
            "points": f.points * [1.0, 1.0, -1.0],
        }
        db.execute("UPDATE vertex_data SET data = ? WHERE id = ?", (pack_arrays(arrays, 3), vid))
    # the vertex's checksum finds the damage first (vtr.map.checksums) ...
    assert_one_line(
        ["repeat", KITTI, "--map", m, "--out", tmp_path / "r", "--frames", "1:6:2"], f"{m}: vertex {vid}", "damaged"
    )
    # ... and in a map made before checksums existed the codec's check does
    from vtr.map.checksums import META_KEY, TABLE

    with sqlite3.connect(m) as db:
        db.executescript(
            f"DROP TRIGGER {TABLE}_append_only_update; DROP TRIGGER {TABLE}_append_only_delete; DROP TABLE {TABLE};"
        )
        db.execute("DELETE FROM meta WHERE key = ?", (META_KEY,))
    assert_one_line(
        ["repeat", KITTI, "--map", m, "--out", tmp_path / "r2", "--frames", "1:6:2"],
        f"{m} vertex {vid}",
        "behind its camera",
    )
