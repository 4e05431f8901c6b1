"""``vtr convert`` and vtr.app.convert: lossless folder -> bag -> folder round trips, summary, errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from vtr.app.convert import convert
from vtr.cli import main
from vtr.cli.summaries import convert_line
from vtr.errors import DataError, OutputError
from vtr.io import KittiSource, open_source
from vtr.io.rosbag_writer import BagTopics, write_bag
from vtr.types import StereoImages

DATA = Path(__file__).resolve().parents[2] / "datasets"
KITTI = DATA / "kitti06_clip"
EUROC = DATA / "euroc_v101_micro"
FRAMES = "10:16:2"  # three KITTI frames
SELECTED = [10, 12, 14]


def assert_identical(a, b, idx_a, idx_b=None):
    """Same pixels and the same ns stamps, frame by frame."""
    idx_b = idx_a if idx_b is None else idx_b
    for i, j in zip(idx_a, idx_b, strict=True):
        fa, fb = a[i], b[j]
        assert fa.t_ns == fb.t_ns
        assert np.array_equal(fa.left, fb.left) and np.array_equal(fa.right, fb.right)


@pytest.mark.parametrize("target", ["rosbag1", "rosbag2", "mcap"])
def test_cli_round_trip_folder_bag_folder(tmp_path, target):
    bag = tmp_path / ("clip.bag" if target == "rosbag1" else "clip")
    runner = CliRunner()
    r = runner.invoke(main, ["convert", str(KITTI), str(bag), "--to", target, "--frames", FRAMES])
    assert r.exit_code == 0, r.output
    assert f"converted 3 frames (0.400 s of data) kitti -> {target}: {bag}" in r.output
    r = runner.invoke(main, ["convert", str(bag), str(tmp_path / "back"), "--no-progress"])
    assert r.exit_code == 0, r.output
    assert r.output.strip().startswith("converted 3 frames") and "rosbag -> kitti" in r.output
    src, back = open_source(KITTI), open_source(tmp_path / "back")
    assert isinstance(back, KittiSource) and len(back) == 3
    assert back.camera.matches(src.camera, rtol=1e-12)
    assert back.timestamps().tolist() == src.timestamps()[SELECTED].tolist()
    assert_identical(src, back, SELECTED, range(3))
    # the bag itself yields the same frames and camera as the folder
    with open_source(bag) as b:
        assert b.camera.matches(src.camera, rtol=1e-12)
        assert_identical(src, b, SELECTED, range(3))
    assert not list(tmp_path.glob("*.partial*"))


def test_euroc_to_bag_to_kitti_keeps_unix_ns(tmp_path):
    euroc = open_source(EUROC)
    s1 = convert(euroc, tmp_path / "e.bag")
    assert s1.target == "rosbag1" and s1.frames == 12 and s1.source_format == "euroc"
    assert s1.first_t_ns == 1403715273262142976
    with open_source(tmp_path / "e.bag") as bag:
        np.testing.assert_allclose(bag.camera.T_vehicle_sensor, euroc.camera.T_vehicle_sensor, atol=1e-12)
        s2 = convert(bag, tmp_path / "k", to="kitti", indices=[0, 5, 11])
    assert s2.frames == 3 and not s2.wrote_poses
    k = open_source(tmp_path / "k")
    assert k.timestamps().tolist() == euroc.timestamps()[[0, 5, 11]].tolist()
    assert_identical(euroc, k, [0, 5, 11], range(3))


def test_kitti_to_kitti_keeps_poses(tmp_path):
    src = open_source(KITTI)
    s = convert(src, tmp_path / "k", to="kitti", indices=SELECTED)
    assert s.wrote_poses and "with poses.txt" in convert_line(s)
    gt = open_source(tmp_path / "k").ground_truth()
    np.testing.assert_allclose(gt.T_world_cam, src.ground_truth().T_world_cam[SELECTED], atol=1e-8)


def test_progress_callback_and_empty_target_folder(tmp_path):
    seen = []
    (tmp_path / "empty").mkdir()
    convert(open_source(KITTI), tmp_path / "empty", indices=[0, 1], progress=seen.append)
    assert seen == [1, 2] and len(open_source(tmp_path / "empty")) == 2


class _Failing(KittiSource):
    """Breaks on a given frame, like a source whose file is truncated half-way."""

    def _load(self, index: int) -> StereoImages:
        if index == 2:
            raise DataError(f"{self.path}: frame {index} unreadable")
        return super()._load(index)


@pytest.mark.parametrize(("target", "name"), [("kitti", "k"), ("rosbag1", "b.bag"), ("mcap", "m")])
def test_failed_conversion_leaves_no_output(tmp_path, target, name):
    with pytest.raises(DataError, match="frame 2 unreadable"):
        convert(_Failing(KITTI), tmp_path / name, to=target, indices=[0, 1, 2, 3])
    assert list(tmp_path.iterdir()) == []


def test_bad_arguments(tmp_path):
    src = open_source(KITTI)
    (tmp_path / "x.bag").write_bytes(b"")
    with pytest.raises(OutputError, match="already exists"):
        convert(src, tmp_path / "x.bag")
    with pytest.raises(DataError, match=r"must end in \.bag"):
        convert(src, tmp_path / "y", to="rosbag1")
    with pytest.raises(DataError, match="unknown target"):
        convert(src, tmp_path / "z", to="tiff")
    with pytest.raises(DataError, match="no such folder"):
        convert(src, tmp_path / "a" / "b" / "c", to="kitti")
    runner = CliRunner()
    r = runner.invoke(main, ["convert", str(KITTI), str(tmp_path / "o"), "--frames", "60:70"])
    assert r.exit_code == 1 and "vtr: error: frames '60:70': START 60 outside" in r.output
    r = runner.invoke(main, ["convert", str(tmp_path / "missing"), str(tmp_path / "o")])
    assert r.exit_code == 1 and "no such file or folder" in r.output
    r = runner.invoke(main, ["convert", str(KITTI), str(tmp_path / "o"), "--left-topic", "/x"])
    assert r.exit_code == 1 and "--left-topic apply to ROS bag sources only" in r.output


def test_cli_refuses_cloud_run(tmp_path):
    run = tmp_path / "run"
    (run / "images").mkdir(parents=True)
    (run / "attitude.txt").write_text("0,0,0,0,1\n")
    r = CliRunner().invoke(main, ["convert", str(run), str(tmp_path / "o")])
    assert r.exit_code == 1 and "CLOUD runs are monocular" in r.output and "stereo source" in r.output


def test_cli_topic_options(tmp_path):
    src = open_source(KITTI)
    frames = [src[i] for i in range(3)]
    topics = BagTopics("/a/image", "/b/image", "/a/camera_info", "/b/camera_info")
    write_bag(tmp_path / "t.bag", frames, src.camera, topics=topics)
    runner = CliRunner()
    r = runner.invoke(main, ["convert", str(tmp_path / "t.bag"), str(tmp_path / "o1")])
    assert r.exit_code == 1 and "pass left_topic (CLI --left-topic)" in r.output
    r = runner.invoke(
        main,
        [
            "convert",
            str(tmp_path / "t.bag"),
            str(tmp_path / "o2"),
            "--left-topic",
            "/a/image",
            "--right-topic",
            "/b/image",
            "--no-progress",
        ],
    )
    assert r.exit_code == 0, r.output
    assert_identical(src, open_source(tmp_path / "o2"), range(3))
