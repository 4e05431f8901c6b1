"""Messages that say what a source is: a forced --format that cannot fit, a ROS 2 folder without metadata.yaml."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from vtr.errors import DataError
from vtr.io import open_source

KITTI = Path(__file__).resolve().parents[2] / "datasets" / "kitti06_clip"


def test_a_folder_format_forced_on_a_file(tmp_path):
    bag = tmp_path / "run.bag"
    bag.write_bytes(b"#ROSBAG V2.0\n" + b"\0" * 64)
    for fmt in ("kitti", "euroc", "stereo-pairs"):
        with pytest.raises(DataError, match=f"is a file, but --format {fmt} reads a folder"):  # was: no such folder
            open_source(bag, fmt)


def test_another_format_forced_on_a_kitti_folder():
    with pytest.raises(DataError, match="not a euroc source; it looks like a kitti source"):
        open_source(KITTI, "euroc")


def test_a_ros2_folder_without_metadata(tmp_path):
    folder = tmp_path / "ros2"
    folder.mkdir()
    (folder / "run_0.db3").write_bytes(b"SQLite format 3\0")
    with pytest.raises(DataError, match=r"holds run_0\.db3 but no metadata\.yaml"):  # was: unknown layout only
        open_source(folder)


def test_the_right_format_still_opens(tmp_path):
    clip = tmp_path / "clip"
    shutil.copytree(KITTI, clip)
    with open_source(clip, "kitti") as s:
        assert len(s) == 51
