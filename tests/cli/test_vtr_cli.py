"""The `vtr` command as a user runs it: outputs on real data, one-line errors on bad input."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from vtr.io.trajectory import read_tum


def vtr(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vtr", *map(str, args)], capture_output=True, text=True)


def test_version_and_dependency_versions():
    r = vtr("versions")
    assert r.returncode == 0, r.stderr
    for name in ("cv2", "gtsam", "open3d", "rosbags"):
        assert name in r.stdout


def test_odometry_writes_outputs(kitti_clip, tmp_path):
    out = tmp_path / "odo"
    r = vtr("odometry", kitti_clip, "--out", out, "--frames", "0:12")
    assert r.returncode == 0, r.stderr
    assert "keyframes" in r.stdout and "t_err" in r.stdout
    t_ns, T = read_tum(out / "trajectory_tum.txt")
    assert len(t_ns) == 12 and np.all(np.diff(t_ns) == 100_000_000)
    assert T[-1, 2, 3] > 10.0  # the car drives ~1.2 m per frame along camera z
    rows = (out / "frames.csv").read_text().splitlines()
    assert rows[0] == "t_ns,result,matches,inliers,keyframe_id" and len(rows) == 13
    run = json.loads((out / "run.json").read_text())
    assert run["summary"]["frames"] == 12 and "gtsam" in run["versions"]
    assert (out / "trajectory.png").stat().st_size > 1000
    assert (out / "config.yaml").is_file()
    # the written config is reusable
    r2 = vtr("odometry", kitti_clip, "--out", tmp_path / "again", "--frames", "0:3", "--config", out / "config.yaml")
    assert r2.returncode == 0, r2.stderr


def test_export_trajectory_formats(kitti_clip, tmp_path):
    out = tmp_path / "odo"
    assert vtr("odometry", kitti_clip, "--out", out, "--frames", "0:4").returncode == 0
    for fmt in ("kitti", "euroc"):
        r = vtr("export-trajectory", out / "trajectory_tum.txt", tmp_path / f"traj.{fmt}", "--to", fmt)
        assert r.returncode == 0, r.stderr
    assert len((tmp_path / "traj.kitti").read_text().splitlines()) == 4
    euroc = (tmp_path / "traj.euroc").read_text().splitlines()
    assert euroc[0].startswith("#timestamp") and len(euroc) == 5


def _copy_clip(src: Path, dst: Path, n: int = 3) -> Path:
    for sub in ("image_0", "image_1"):
        (dst / sub).mkdir(parents=True)
        for f in sorted((src / sub).iterdir())[:n]:
            shutil.copy(f, dst / sub / f.name)
    shutil.copy(src / "calib.txt", dst / "calib.txt")
    return dst


def _assert_one_line_error(r: subprocess.CompletedProcess, *needles: str) -> None:
    assert r.returncode == 1
    assert "Traceback" not in r.stderr
    line = r.stderr.strip().splitlines()[-1]
    assert line.startswith("vtr: error:")
    for n in needles:
        assert n in line


def test_missing_calibration(kitti_clip, tmp_path):
    clip = _copy_clip(kitti_clip, tmp_path / "clip")
    (clip / "calib.txt").unlink()
    _assert_one_line_error(vtr("odometry", clip, "--out", tmp_path / "o"), "calib.txt")


def test_mismatched_image_size(kitti_clip, tmp_path):
    import cv2

    clip = _copy_clip(kitti_clip, tmp_path / "clip")
    bad = clip / "image_1" / "000001.png"
    cv2.imwrite(str(bad), np.zeros((100, 200), np.uint8))
    _assert_one_line_error(vtr("odometry", clip, "--out", tmp_path / "o"), "000001.png", "200x100")


def test_corrupt_png(kitti_clip, tmp_path):
    clip = _copy_clip(kitti_clip, tmp_path / "clip")
    (clip / "image_0" / "000002.png").write_bytes(b"\x89PNG garbage")
    _assert_one_line_error(vtr("odometry", clip, "--out", tmp_path / "o"), "000002.png")


def test_empty_folder_and_unknown_layout(tmp_path):
    (tmp_path / "empty").mkdir()
    _assert_one_line_error(vtr("odometry", tmp_path / "empty", "--out", tmp_path / "o"), "empty")
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "readme.txt").write_text("hello")
    _assert_one_line_error(vtr("odometry", tmp_path / "other", "--out", tmp_path / "o"), "unknown layout")


@pytest.mark.parametrize("spec", ["60:70", "0:5:0", "a:b"])
def test_frames_outside_source(kitti_clip, tmp_path, spec):
    _assert_one_line_error(vtr("odometry", kitti_clip, "--out", tmp_path / "o", "--frames", spec), f"frames '{spec}'")


@pytest.mark.parametrize(
    "text, named",
    [("odometry:\n  no_such_key: 3\n", "no_such_key"), ("features:\n  corner_score: sift\n", "corner_score")],
)
def test_bad_config(kitti_clip, tmp_path, text, named):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(text)
    _assert_one_line_error(vtr("odometry", kitti_clip, "--out", tmp_path / "o", "--config", cfg), named)


def test_euroc_sequence_runs(euroc_micro, tmp_path):
    r = vtr("odometry", euroc_micro, "--out", tmp_path / "e")
    assert r.returncode == 0, r.stderr
    t_ns, T = read_tum(tmp_path / "e" / "trajectory_tum.txt")
    assert len(t_ns) == 12
    # the vehicle is nearly static in this excerpt
    assert np.linalg.norm(T[-1, :3, 3]) < 0.2


def test_demo_is_the_readme_main_command(tmp_path):
    """`vtr demo` (the README's main command) teaches and repeats the shipped clip and reports (its fourth
    step, the synthetic aerial mission, is tested on a tiny route in tests/app/test_mission.py)."""
    r = vtr("demo", "--out", tmp_path / "demo", "--no-aerial")
    assert r.returncode == 0, r.stderr
    assert "localized 24 (96.0 %)" in r.stdout
    assert "T_leaf_trunk error vs ground truth" in r.stdout
    for f in (
        "odometry/trajectory.png",
        "repeat/report.png",
        "repeat/localization.csv",
        "repeat/landmarks.csv",
        "repeat/state.csv",
        "route.vtrmap",
    ):
        assert (tmp_path / "demo" / f).is_file(), f


def test_demo_deletes_only_what_its_record_says_it_made(tmp_path):
    """A user's out/route.vtrmap (a taught map) is refused, never deleted; a rerun replaces the demo's own map and
    keeps the user's out/route.vtrmap.notes; a user's out/aerial/teach/ is refused before anything is rendered."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "route.vtrmap").write_bytes(b"SQLite format 3\0 the user's taught map")
    (out / "route.vtrmap.notes").write_text("the user's notes")
    r = vtr("demo", "--out", out, "--no-aerial")
    assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "route.vtrmap: was not made by vtr here" in r.stderr
    assert (out / "route.vtrmap").read_bytes().endswith(b"the user's taught map")
    (out / "route.vtrmap").unlink()
    for _ in range(2):  # the second run replaces the demo's own outputs
        r = vtr("demo", "--out", out, "--no-aerial")
        assert r.returncode == 0, r.stderr
        assert (out / "route.vtrmap").is_file() and (out / "route.vtrmap.notes").read_text() == "the user's notes"
    (out / "aerial" / "teach").mkdir(parents=True)
    (out / "aerial" / "teach" / "mine.txt").write_text("the user's")
    from vtr.app.mission import run_aerial_mission
    from vtr.config import Config
    from vtr.errors import OutputError

    with pytest.raises(OutputError, match="aerial/teach: was not made by vtr here"):
        run_aerial_mission(out / "aerial", Config(), length_m=9.0, lateral_m=(0.0,), held_out_m=(), ramp_m=2.0)
    assert (out / "aerial" / "teach" / "mine.txt").read_text() == "the user's"
