"""ROS bags (ROS 1 .bag, ROS 2 sqlite3 and MCAP) written with rosbags and read back through open_source."""

from __future__ import annotations

import sqlite3
import tracemalloc
from pathlib import Path

import cv2
import numpy as np
import pytest

from vtr.camera import StereoCamera
from vtr.errors import CalibrationError, DataError, OutputError
from vtr.io import EurocSource, open_source
from vtr.io.ros_messages import CameraInfoData, decode_image
from vtr.io.rosbag import RosbagSource, _pick_image_topic
from vtr.io.rosbag_writer import BagTopics, RosbagWriter, write_bag

DATA = Path(__file__).resolve().parents[2] / "datasets"
KITTI = DATA / "kitti06_clip"
EUROC = DATA / "euroc_v101_micro"
N_KITTI = 4  # a few KITTI frames per bag keep the suite fast
T0_NS = 1_600_000_000_123_456_789  # Unix-ns stamps that float seconds cannot represent exactly
DT_NS = 66_666_667
SMALL = StereoCamera(fx=100.0, fy=100.0, cx=32.0, cy=24.0, baseline=0.12, width=64, height=48)
JPEG_MAX_MEAN_ERROR = 3.0  # grey levels
MEMORY_FLAT_FRACTION = 0.5  # streaming peak (traced) must stay well under the bag's image payload
MEMORY_GROWTH_LIMIT = 1.3  # peak traced memory over a whole pass vs over its first frames


def kitti_frames(n: int = N_KITTI):
    src = open_source(KITTI)
    frames = [src[i] for i in range(n)]
    # re-stamp with large Unix-ns times to check exact ns through header stamps
    return src.camera, [type(f)(T0_NS + i * DT_NS, i, f.left, f.right) for i, f in enumerate(frames)]


def assert_same_frames(got, want):
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        assert g.t_ns == w.t_ns and isinstance(g.t_ns, int)
        assert g.left.dtype == np.uint8 and g.left.shape == w.left.shape
        assert g.left.flags.writeable and g.right.flags.c_contiguous  # like images read from files
        assert np.array_equal(g.left, w.left) and np.array_equal(g.right, w.right)


# (kind, path written, path opened)
LAYOUTS = [
    ("rosbag1", "clip.bag", "clip.bag"),
    ("rosbag2", "clip2", "clip2"),
    ("rosbag2", "clip2", "clip2/clip2.db3"),
    ("mcap", "clipm", "clipm"),
    ("mcap", "clipm", "clipm/clipm.mcap"),
]


@pytest.mark.parametrize(("kind", "written", "opened"), LAYOUTS)
def test_kitti_round_trip_every_bag_kind(tmp_path, kind, written, opened):
    camera, frames = kitti_frames()
    assert write_bag(tmp_path / written, frames, camera, kind=kind) == N_KITTI
    with open_source(tmp_path / opened) as src:
        assert isinstance(src, RosbagSource) and src.format_name == "rosbag"
        assert src.camera.matches(camera, rtol=1e-12)
        np.testing.assert_array_equal(src.camera.T_vehicle_sensor, np.eye(4))
        assert src.timestamps().dtype == np.int64
        assert src.timestamps().tolist() == [f.t_ns for f in frames]
        assert_same_frames(list(src), frames)  # streaming pass
        assert_same_frames([src[i] for i in (3, 0, 2, 1)][::-1][::-1], [frames[i] for i in (3, 0, 2, 1)])
        assert_same_frames(list(src.iter_frames([1, 3])), [frames[1], frames[3]])
        assert src.left_topic == BagTopics().left and src.right_info_topic == BagTopics().right_info
        assert src.unpaired == (0, 0) and not src.rectified_on_load


def test_lone_storage_files_open(tmp_path):
    camera, frames = kitti_frames(2)
    write_bag(tmp_path / "a", frames, camera, kind="rosbag2")
    write_bag(tmp_path / "b", frames, camera, kind="mcap")
    lone = tmp_path / "lone"
    lone.mkdir()
    (tmp_path / "a" / "a.db3").rename(lone / "x.db3")
    (tmp_path / "b" / "b.mcap").rename(lone / "y.mcap")
    for f in ("x.db3", "y.mcap"):
        with open_source(lone / f) as src:
            assert_same_frames(list(src), frames)


def test_euroc_rectified_bag_keeps_camera_and_extrinsics(tmp_path):
    euroc = EurocSource(EUROC)
    frames = list(euroc)
    write_bag(tmp_path / "e", frames, euroc.camera, kind="mcap")
    with open_source(tmp_path / "e") as src:
        assert src.camera.matches(euroc.camera, rtol=1e-12)
        np.testing.assert_allclose(src.camera.T_vehicle_sensor, euroc.camera.T_vehicle_sensor, atol=1e-12)
        assert src.timestamps().tolist() == euroc.timestamps().tolist()
        assert_same_frames(list(src), frames)


def _euroc_raw_infos(euroc: EurocSource):
    """CameraInfos of the raw EuRoC cameras (K, D, R, P as ROS camera_calibration writes them)."""
    from vtr.io.euroc import read_sensor_yaml

    left = read_sensor_yaml(euroc.root / "cam0" / "sensor.yaml")
    right = read_sensor_yaml(euroc.root / "cam1" / "sensor.yaml")
    T_rl = np.linalg.inv(right.T_body_cam) @ left.T_body_cam
    R1, R2, P1, P2, *_ = cv2.stereoRectify(
        left.K,
        left.dist,
        right.K,
        right.dist,
        (left.width, left.height),
        T_rl[:3, :3].copy(),
        T_rl[:3, 3].reshape(3, 1).copy(),
        flags=cv2.CALIB_ZERO_DISPARITY,
        alpha=0.0,
    )
    infos = tuple(
        CameraInfoData(width=c.width, height=c.height, K=c.K, D=c.dist, R=R, P=P, frame_id=name)
        for c, R, P, name in ((left, R1, P1, "cam0"), (right, R2, P2, "cam1"))
    )
    return infos, left.T_body_cam


def test_euroc_raw_bag_is_rectified_from_camera_info(tmp_path):
    euroc = EurocSource(EUROC)
    infos, T_body_cam0 = _euroc_raw_infos(euroc)
    topics = BagTopics("/cam0/image_raw", "/cam1/image_raw", "/cam0/camera_info", "/cam1/camera_info")
    with RosbagWriter(tmp_path / "raw.bag", euroc.camera, topics=topics, infos=infos, T_base_left=T_body_cam0) as w:
        for i, t in enumerate(euroc.timestamps()[:4]):
            w.add(t, *(cv2.imread(str(f[i]), cv2.IMREAD_GRAYSCALE) for f in (euroc._left, euroc._right)))
    with open_source(tmp_path / "raw.bag") as src:  # cam0/cam1 topics detected
        assert src.rectified_on_load and src.left_topic == "/cam0/image_raw"
        assert src.camera.matches(euroc.camera, rtol=1e-9)
        # tf_static places the raw cam0; the source composes the rectifying rotation
        np.testing.assert_allclose(src.camera.T_vehicle_sensor, euroc.camera.T_vehicle_sensor, atol=1e-9)
        assert_same_frames(list(src), [euroc[i] for i in range(4)])


@pytest.mark.parametrize(
    "D",
    [
        [-50.0, 0.0, 0.0, 0.0, 0.0],
        [0.0, -40.0, 0.0, 0.0, 0.0],
        [0.3, 0.1, 0.0, 0.0, 1e9],
        [-0.28, 0.07, 0.0, 0.0, float("nan")],
        [-0.28, 0.07, 0.0],
    ],
)
def test_absurd_camera_info_distortion_is_refused(tmp_path, D):
    """Coefficients that fold the image over (or a wrong count, NaN) are a CalibrationError when the bag is opened
    (were: accepted, and the 'rectified' images were garbage)."""
    from dataclasses import replace

    from vtr.errors import CalibrationError

    euroc = EurocSource(EUROC)
    infos, T_body_cam0 = _euroc_raw_infos(euroc)
    infos = (replace(infos[0], D=np.array(D)), infos[1])
    topics = BagTopics("/cam0/image_raw", "/cam1/image_raw", "/cam0/camera_info", "/cam1/camera_info")
    with RosbagWriter(tmp_path / "raw.bag", euroc.camera, topics=topics, infos=infos, T_base_left=T_body_cam0) as w:
        for i, t in enumerate(euroc.timestamps()[:2]):
            w.add(t, *(cv2.imread(str(f[i]), cv2.IMREAD_GRAYSCALE) for f in (euroc._left, euroc._right)))
    with pytest.raises(CalibrationError, match="distortion|not finite"):
        with open_source(tmp_path / "raw.bag") as src:
            list(src)


def _synthetic_pair(seed: int = 0):
    rng = np.random.default_rng(seed)
    bgr = rng.integers(0, 256, (SMALL.height, SMALL.width, 3), dtype=np.uint8)
    return bgr, np.roll(bgr, 3, axis=1)


@pytest.mark.parametrize("encoding", ["mono16", "bgr8", "rgb8", "png", "jpeg"])
def test_image_encodings_become_grey(tmp_path, encoding):
    bgr_l, bgr_r = _synthetic_pair()
    if encoding == "mono16":
        imgs = [cv2.cvtColor(b, cv2.COLOR_BGR2GRAY).astype(np.uint16) * 257 + 3 for b in (bgr_l, bgr_r)]
        want = [(i >> 8).astype(np.uint8) for i in imgs]  # high byte (documented mono16 scaling)
    elif encoding == "rgb8":
        imgs = [b[:, :, ::-1].copy() for b in (bgr_l, bgr_r)]
        want = [cv2.cvtColor(b, cv2.COLOR_BGR2GRAY) for b in (bgr_l, bgr_r)]
    else:
        imgs = [bgr_l, bgr_r]
        want = [cv2.cvtColor(b, cv2.COLOR_BGR2GRAY) for b in (bgr_l, bgr_r)]
    kind = {"mono16": "rosbag1", "bgr8": "rosbag2", "rgb8": "mcap", "png": "rosbag1", "jpeg": "mcap"}[encoding]
    out = tmp_path / ("b.bag" if kind == "rosbag1" else "b")
    with RosbagWriter(out, SMALL, kind=kind, encoding=encoding) as w:
        w.add(T0_NS, *imgs)
    with open_source(out) as src:
        f = src[0]
        assert f.left.dtype == np.uint8 and f.left.shape == (SMALL.height, SMALL.width)
        for got, exp in ((f.left, want[0]), (f.right, want[1])):
            if encoding == "jpeg":
                assert np.mean(np.abs(got.astype(int) - exp)) < JPEG_MAX_MEAN_ERROR
            else:
                assert np.array_equal(got, exp)


def test_mono16_shift_and_big_endian():
    class Msg:
        height, width, step, encoding, is_bigendian = 2, 2, 4, "mono16", 1
        data = np.array([[0x0F, 0xF0, 0x01, 0x00], [0xFF, 0xFF, 0x00, 0x10]], np.uint8).ravel()

    img = decode_image(Msg, "sensor_msgs/msg/Image", "t", mono16_shift=8)
    assert img.tolist() == [[0x0F, 0x01], [0xFF, 0x00]]
    img4 = decode_image(Msg, "sensor_msgs/msg/Image", "t", mono16_shift=4)
    assert img4.tolist() == [[255, 16], [255, 1]]  # 12-bit scaling saturates above 255
    Msg.encoding = "yuv422"
    with pytest.raises(DataError, match="encoding 'yuv422' not supported"):
        decode_image(Msg, "sensor_msgs/msg/Image", "/cam0/image_raw")


def test_topic_detection_and_explicit_topics(tmp_path):
    camera, frames = kitti_frames(2)
    topics = BagTopics("/a/image", "/b/image", "/a/camera_info", "/b/camera_info")
    write_bag(tmp_path / "x.bag", frames, camera, topics=topics)
    with pytest.raises(DataError, match=r"no left image topic.*/a/image, /b/image.*left_topic"):
        open_source(tmp_path / "x.bag")
    with RosbagSource(tmp_path / "x.bag", left_topic="/a/image", right_topic="/b/image") as src:
        assert src.left_info_topic == "/a/camera_info" and src.right_info_topic == "/b/camera_info"
        assert_same_frames(list(src), frames)
    with pytest.raises(DataError, match=r"no topic '/c/image'"):
        RosbagSource(tmp_path / "x.bag", left_topic="/c/image", right_topic="/b/image")
    # image_transport's compressed twin is not a second candidate
    t = {"/l/image_raw": "sensor_msgs/msg/Image", "/l/image_raw/compressed": "sensor_msgs/msg/CompressedImage"}
    assert _pick_image_topic(t, ("l/",), "left", "bag") == "/l/image_raw"


def test_truncated_bags_fail_naming_the_file(tmp_path):
    camera, frames = kitti_frames(3)
    for kind, name, storage in (("rosbag1", "t.bag", "t.bag"), ("mcap", "m", "m/m.mcap"), ("rosbag2", "s", "s/s.db3")):
        write_bag(tmp_path / name, frames, camera, kind=kind)
        f = tmp_path / storage
        f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
        with pytest.raises(DataError, match=f"{tmp_path / name}"):
            open_source(tmp_path / name)


def test_partial_db3_is_not_reported_complete(tmp_path):
    camera, frames = kitti_frames(3)
    write_bag(tmp_path / "p", frames, camera, kind="rosbag2")
    with sqlite3.connect(tmp_path / "p" / "p.db3") as db:
        tid = db.execute("SELECT id FROM topics WHERE name = ?", (BagTopics().right,)).fetchone()[0]
        db.execute("DELETE FROM messages WHERE id = (SELECT MAX(id) FROM messages WHERE topic_id = ?)", (tid,))
    db.close()
    with pytest.raises(DataError, match=r"/stereo/right/image_raw: the bag index lists 3 messages but 2"):
        open_source(tmp_path / "p")


def test_bag_without_image_topic(tmp_path):
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    with Writer(tmp_path / "s.bag") as w:
        c = w.add_connection("/chatter", "std_msgs/msg/String", typestore=ts)
        w.write(c, 1, ts.serialize_ros1(ts.types["std_msgs/msg/String"](data="hi"), "std_msgs/msg/String"))
    with pytest.raises(DataError, match=r"s.bag: no image topic .*/chatter \(std_msgs/msg/String\)"):
        open_source(tmp_path / "s.bag")


def test_missing_camera_info(tmp_path):
    camera, frames = kitti_frames(2)
    write_bag(tmp_path / "n.bag", frames, camera, write_info=False)
    with pytest.raises(CalibrationError, match=r"n.bag: no unique CameraInfo topic for left.*CameraInfo topics: none"):
        open_source(tmp_path / "n.bag")


def test_mismatched_left_right_counts(tmp_path):
    camera, frames = kitti_frames(3)
    with RosbagWriter(tmp_path / "m.bag", camera) as w:
        for f in frames:
            w.add(f.t_ns, f.left, f.right)
        w.add_image("left", frames[-1].t_ns + DT_NS, frames[0].left)  # a left image without partner
    with pytest.raises(
        DataError,
        match=r"left topic /stereo/left/image_raw has 4 images and right topic "
        r"/stereo/right/image_raw has 3; only 3 pairs",
    ):
        open_source(tmp_path / "m.bag")
    with RosbagSource(tmp_path / "m.bag", allow_unpaired=True) as src:
        assert src.unpaired == (1, 0)
        assert_same_frames(list(src), frames)


def test_pairing_tolerates_small_stamp_offsets(tmp_path):
    camera, frames = kitti_frames(3)
    with RosbagWriter(tmp_path / "o.bag", camera) as w:
        for f in frames:
            w.add_image("right", f.t_ns + 1_000_000, f.right)  # right stamped 1 ms late, written first
            w.add_image("left", f.t_ns, f.left)
    with open_source(tmp_path / "o.bag") as src:
        assert_same_frames(list(src), frames)
        assert_same_frames([src[2]], [frames[2]])
    with pytest.raises(DataError, match="only 0 pairs|no left image"):
        RosbagSource(tmp_path / "o.bag", pair_tolerance_ns=500_000)


@pytest.mark.parametrize(("kind", "name"), [("rosbag1", "big.bag"), ("mcap", "big")])
def test_streaming_memory_stays_flat(tmp_path, kind, name):
    n, early, w, h = 60, 10, 320, 240
    cam = StereoCamera(fx=300.0, fy=300.0, cx=160.0, cy=120.0, baseline=0.1, width=w, height=h)
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, (h, w), dtype=np.uint8)
    with RosbagWriter(tmp_path / name, cam, kind=kind) as bag:
        for i in range(n):
            bag.add(T0_NS + i * DT_NS, np.roll(img, i, axis=1), np.roll(img, i + 5, axis=1))
    with open_source(tmp_path / name) as src:
        tracemalloc.start()
        for f in src:
            assert f.left[0, 0] == np.roll(img, f.index, axis=1)[0, 0]
            if f.index == early:
                _, peak_early = tracemalloc.get_traced_memory()
        current, peak_all = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    assert f.index == n - 1
    # the peak after n frames is that after the first few: nothing accumulates
    assert peak_all < MEMORY_GROWTH_LIMIT * peak_early, (peak_early, peak_all)
    assert peak_all < MEMORY_FLAT_FRACTION * n * 2 * w * h


def test_writer_rejects_bad_input(tmp_path):
    with pytest.raises(DataError, match=r"must end in \.bag"):
        RosbagWriter(tmp_path / "x.db3", SMALL, kind="rosbag1")
    with pytest.raises(DataError, match="unknown bag kind"):
        RosbagWriter(tmp_path / "x", SMALL, kind="rosbag3")
    with RosbagWriter(tmp_path / "y.bag", SMALL) as w:
        with pytest.raises(DataError, match="mono8 needs a uint8 image"):
            w.add(0, np.zeros((48, 64), np.uint16), np.zeros((48, 64), np.uint16))
        with pytest.raises(DataError, match="negative time"):
            w.add(-1, np.zeros((48, 64), np.uint8), np.zeros((48, 64), np.uint8))
    with pytest.raises(OutputError, match="already exists"):
        RosbagWriter(tmp_path / "y.bag", SMALL)


@pytest.mark.parametrize("kind", ["rosbag1", "mcap"])
def test_odometry_on_bag_matches_folder(tmp_path, kind):
    """`vtr odometry` on a bag written from the KITTI folder gives the folder's trajectory."""
    import subprocess
    import sys

    from vtr.io.trajectory import read_tum

    n = 10
    src = open_source(KITTI)
    frames = [src[i] for i in range(n)]
    bag = tmp_path / ("clip.bag" if kind == "rosbag1" else "clipm")
    write_bag(bag, frames, src.camera, kind=kind)
    runs = {}
    for name, source, extra in (("folder", KITTI, ["--frames", f"0:{n}"]), ("bag", bag, [])):
        r = subprocess.run(
            [sys.executable, "-m", "vtr", "odometry", str(source), "--out", str(tmp_path / name), *extra],
            capture_output=True,
            text=True,
        )
        assert r.returncode == 0, r.stderr
        runs[name] = read_tum(tmp_path / name / "trajectory_tum.txt")
    np.testing.assert_array_equal(runs["bag"][0], runs["folder"][0])
    np.testing.assert_allclose(runs["bag"][1], runs["folder"][1], atol=1e-9)


def test_mcap_chunks_carry_crcs_and_a_damaged_one_is_refused(tmp_path):
    """rosbags writes chunk CRC 0 ("no check"): 4 KB zeroed mid-file then gave other images and rc 0. vtr's MCAP
    bags carry a CRC per chunk; a byte flip in a chunk is refused naming the bag; a truncated file gets a hint."""
    import struct

    from vtr.io.rosbag_writer import MCAP_MAGIC

    camera, frames = kitti_frames(3)
    write_bag(tmp_path / "m", frames, camera, kind="mcap")
    f = tmp_path / "m" / "m.mcap"
    data = bytearray(f.read_bytes())
    assert data.startswith(MCAP_MAGIC)
    chunk = data.index(b"\x06", len(MCAP_MAGIC))  # the first record after the header is a chunk here
    pos = len(MCAP_MAGIC)
    crcs = []
    while data[pos] != 0x0F:  # up to DataEnd
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        if data[pos] == 0x06:
            crcs.append(struct.unpack_from("<I", data, pos + 9 + 24)[0])
            chunk = pos
        pos += 9 + length
    assert crcs and all(crcs)
    from binascii import crc32

    # the data section's CRC (leading magic up to DataEnd), as the MCAP libraries check it
    assert struct.unpack_from("<I", data, pos + 9)[0] == crc32(data[:pos]) != 0
    with open_source(tmp_path / "m") as src:  # intact: read whole
        assert len([src[i] for i in range(len(src))]) == 3
    bad = bytearray(data)
    flip = chunk + 9 + 200 + (struct.unpack_from("<Q", data, chunk + 1)[0] - 200) // 2
    bad[flip : flip + 4096] = bytes(4096)  # 4 KB zeroed inside a chunk's image bytes
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "metadata.yaml").write_text(
        (tmp_path / "m" / "metadata.yaml").read_text().replace("m.mcap", "b.mcap")
    )
    (tmp_path / "b" / "b.mcap").write_bytes(bytes(bad))
    with pytest.raises(DataError, match="checksum"), open_source(tmp_path / "b") as src:
        [src[i] for i in range(len(src))]
    f.write_bytes(bytes(data[: len(data) * 2 // 3]))
    with pytest.raises(DataError, match="truncated.*mcap recover"):
        open_source(tmp_path / "m")
