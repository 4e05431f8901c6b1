"""Readers refuse what they cannot read correctly, when the source opens, with one line naming the
file (and line): unsorted or duplicated EuRoC stamps, malformed optional ground truth, calibrations
OpenCV cannot rectify, damaged MCAP files; the shared source options reach every reader."""

from __future__ import annotations

import shutil
import struct
from pathlib import Path

import numpy as np
import pytest

from vtr.camera import StereoCamera
from vtr.errors import CalibrationError, DataError
from vtr.io import SourceOptions, open_source
from vtr.io.rosbag_writer import BagTopics, write_bag
from vtr.types import StereoImages

DATA = Path(__file__).resolve().parents[2] / "datasets"
EUROC = DATA / "euroc_v101_micro"
KITTI = DATA / "kitti06_clip"
PAIRS = DATA / "euroc_revisit_pairs"
SMALL = StereoCamera(fx=100.0, fy=100.0, cx=32.0, cy=24.0, baseline=0.12, width=64, height=48)
GT_HEADER = "#timestamp, p_x, p_y, p_z, q_w, q_x, q_y, q_z"


def _one_line(err: pytest.ExceptionInfo, *named: str) -> None:
    msg = str(err.value)
    assert "\n" not in msg, msg
    for n in named:
        assert n in msg, msg


@pytest.fixture()
def euroc(tmp_path: Path) -> Path:
    shutil.copytree(EUROC, tmp_path / "euroc")
    return tmp_path / "euroc" / "mav0"


def _rows(csv: Path) -> tuple[list[str], list[str]]:
    lines = csv.read_text().splitlines()
    head = [x for x in lines if x.startswith("#")]
    return head, [x for x in lines if x and not x.startswith("#")]


def _write(csv: Path, head: list[str], rows: list[str]) -> None:
    csv.write_text("\n".join(head + rows) + "\n")


@pytest.mark.parametrize("cam", ["cam0", "cam1"])
def test_euroc_unsorted_stamps_refused(euroc, cam):
    csv = euroc / cam / "data.csv"
    head, rows = _rows(csv)
    rows[2], rows[5] = rows[5], rows[2]  # was: half the frames silently dropped
    _write(csv, head, rows)
    with pytest.raises(DataError) as err:
        open_source(euroc.parent)
    _one_line(err, f"{cam}/data.csv:{len(head) + 4}", "is earlier than", "strictly increasing")


def test_euroc_duplicated_row_refused(euroc):
    csv = euroc / "cam0" / "data.csv"
    head, rows = _rows(csv)
    rows.insert(4, rows[3])  # was: two poses with one time
    _write(csv, head, rows)
    with pytest.raises(DataError) as err:
        open_source(euroc.parent)
    _one_line(err, f"cam0/data.csv:{len(head) + 5}", "repeats")


def _ground_truth(euroc: Path, rows: list[str]) -> Path:
    gt = euroc / "state_groundtruth_estimate0" / "data.csv"
    gt.parent.mkdir(exist_ok=True)
    gt.write_text("\n".join([GT_HEADER, *rows]) + "\n")
    return gt


def _gt_rows(euroc: Path) -> list[str]:
    t = [int(r.split(",")[0]) for r in _rows(euroc / "cam0" / "data.csv")[1]]
    return [f"{s},{0.1 * i},0,0,1,0,0,0" for i, s in enumerate(t)]


def test_euroc_valid_ground_truth_is_read_at_open(euroc):
    _ground_truth(euroc, _gt_rows(euroc))
    with open_source(euroc.parent) as src:
        gt = src.ground_truth()
        assert len(gt.t_ns) == len(src) and np.all(np.diff(gt.t_ns) > 0)


@pytest.mark.parametrize(
    ("damage", "named"),
    [
        (lambda r: r[:3] + ["12,abc,0,0,1,0,0,0"] + r[3:], "malformed"),
        (lambda r: r[:3] + [r[2]] + r[3:], "data.csv:5: timestamp"),  # duplicated time
        (lambda r: [r[1], r[0], *r[2:]], "data.csv:3: timestamp"),  # unsorted
        (lambda r: [*r[:2], r[2].rsplit(",", 4)[0] + ",0,0,0,0", *r[3:]], "data.csv:4: quaternion norm 0"),
        (lambda r: [x.rsplit(",", 2)[0] for x in r], "6 columns"),
        (lambda r: [*r[:1], r[1].replace(",0,0,1,", ",nan,0,1,"), *r[2:]], "data.csv:3: NaN"),
    ],
)
def test_euroc_malformed_ground_truth_refused_at_open(euroc, damage, named):
    gt = _ground_truth(euroc, damage(_gt_rows(euroc)))
    with pytest.raises(DataError) as err:
        open_source(euroc.parent)  # not after the whole run
    _one_line(err, str(gt.relative_to(euroc.parent.parent)), named)


def test_euroc_binary_ground_truth_refused(euroc):
    gt = euroc / "state_groundtruth_estimate0" / "data.csv"
    gt.parent.mkdir()
    gt.write_bytes(bytes(range(256)) * 8)
    with pytest.raises(DataError) as err:
        open_source(euroc.parent)
    _one_line(err, "state_groundtruth_estimate0/data.csv")


def test_euroc_identical_camera_poses_refused(euroc):
    shutil.copy(euroc / "cam0" / "sensor.yaml", euroc / "cam1" / "sensor.yaml")  # was a cv2 traceback
    with pytest.raises(CalibrationError) as err:
        open_source(euroc.parent)
    _one_line(err, "cam0/sensor.yaml", "cam1/sensor.yaml", "no stereo baseline")


@pytest.mark.parametrize(
    ("old", "new", "named"),
    [
        ("intrinsics: [", "intrinsics: [.nan, ", "cam1/sensor.yaml: NaN or infinite"),
        ("resolution: [752, 480]", "resolution: [0, 0]", "cam1/sensor.yaml: resolution 0x0 is empty"),
    ],
)
def test_euroc_unusable_intrinsics_refused(euroc, old, new, named):
    y = euroc / "cam1" / "sensor.yaml"
    text = y.read_text()
    assert old in text
    if new.endswith(", "):
        start = text.index(old) + len(old)
        end = text.index("]", start)
        text = text[:start] + ".nan, " + text[start:end].split(",", 1)[1] + text[end:]
    else:
        text = text.replace(old, new)
    y.write_text(text)
    with pytest.raises(CalibrationError) as err:
        open_source(euroc.parent)
    _one_line(err, "sensor.yaml", named)


def test_stereo_pairs_malformed_ground_truth_refused_at_open(tmp_path):
    shutil.copytree(PAIRS, tmp_path / "p")
    gt = tmp_path / "p" / "groundtruth.csv"
    lines = gt.read_text().splitlines()
    rows = [x for x in lines if not x.startswith("#")]
    gt.write_text("\n".join([*(x for x in lines if x.startswith("#")), rows[1], rows[0], *rows[2:]]) + "\n")
    with pytest.raises(DataError) as err:
        open_source(tmp_path / "p")
    _one_line(err, "groundtruth.csv", "strictly increasing")


def test_kitti_malformed_poses_refused_at_open(tmp_path):
    shutil.copytree(KITTI, tmp_path / "k")
    poses = tmp_path / "k" / "poses.txt"
    rows = poses.read_text().splitlines()
    rows[7] = " ".join(["nan"] * 12)
    poses.write_text("\n".join(rows) + "\n")
    with pytest.raises(DataError) as err:
        open_source(tmp_path / "k")
    _one_line(err, "poses.txt: pose 8", "NaN")
    rows[7] = " ".join(["2"] * 12)
    poses.write_text("\n".join(rows) + "\n")
    with pytest.raises(DataError) as err:
        open_source(tmp_path / "k")
    _one_line(err, "poses.txt: pose 8", "orthonormal")


@pytest.mark.parametrize("value", ["nan", "inf", "1e300"])
def test_kitti_time_that_is_not_a_time_is_named_by_line(tmp_path, value):
    """A NaN, infinite or out-of-range time in times.txt used to pass through a numpy cast warning and read as
    "not strictly increasing"; it is named by its line."""
    shutil.copytree(KITTI, tmp_path / "k")
    times = tmp_path / "k" / "times.txt"
    rows = times.read_text().splitlines()
    rows[3] = value
    times.write_text("\n".join(rows) + "\n")
    with pytest.raises(DataError) as err:
        open_source(tmp_path / "k")
    _one_line(err, "times.txt: line 4", "not a time in seconds")


# ------------------------------------------------------------------------------ bags


def _frames(n: int = 3) -> list[StereoImages]:
    rng = np.random.default_rng(0)
    return [
        StereoImages(
            10**9 + i * 10**8,
            i,
            rng.integers(0, 255, (48, 64), dtype=np.uint8),
            rng.integers(0, 255, (48, 64), dtype=np.uint8),
        )
        for i in range(n)
    ]


def test_damaged_mcap_data_end_is_one_line(tmp_path):
    write_bag(tmp_path / "b", _frames(), SMALL, kind="mcap")
    f = tmp_path / "b" / "b.mcap"
    data = bytearray(f.read_bytes())
    data_end = data.rfind(b"\x0f" + (4).to_bytes(8, "little"))  # DataEnd: opcode, length 4, crc
    footer = len(data) - 8 - 29  # Footer record before the end magic
    assert data_end > 0 and data[footer] == 0x02
    data[data_end + 1 : data_end + 9] = (2**62).to_bytes(8, "little")  # absurd record length
    struct.pack_into("<Q", data, footer + 9, data_end)  # summary starts at the damaged record
    f.write_bytes(bytes(data))
    with pytest.raises(DataError) as err:  # was a MemoryError traceback
        open_source(tmp_path / "b")
    _one_line(err, str(tmp_path / "b"), "damaged")


def test_source_options_reach_the_bag_reader(tmp_path):
    """A real robot's topics (not named left/cam0) open through the shared SourceOptions."""
    topics = BagTopics("/front/image", "/rear/image", "/front/camera_info", "/rear/camera_info")
    frames = _frames()
    write_bag(tmp_path / "x.bag", frames, SMALL, topics=topics)
    with pytest.raises(DataError) as err:
        open_source(tmp_path / "x.bag")
    _one_line(err, "--left-topic")
    opts = SourceOptions(left_topic="/front/image", right_topic="/rear/image")
    with open_source(tmp_path / "x.bag", opts) as src:
        assert len(src) == 3 and src.left_info_topic == "/front/camera_info"
        np.testing.assert_array_equal(src[1].left, frames[1].left)
    with open_source(
        tmp_path / "x.bag", SourceOptions(format="rosbag", left_topic="/front/image", right_topic="/rear/image")
    ) as src:
        assert len(src) == 3


def test_bag_options_on_another_format_refused():
    with pytest.raises(DataError) as err:
        open_source(KITTI, SourceOptions(left_topic="/x", allow_unpaired=True))
    _one_line(err, "--left-topic, --allow-unpaired apply to ROS bag sources only", "kitti")
