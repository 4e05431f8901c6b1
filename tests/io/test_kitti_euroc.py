"""KITTI and EuRoC readers: normal reads, bad input (clear errors naming the file), EuRoC rectification."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from vtr.errors import CalibrationError, DataError
from vtr.io import EurocSource, KittiSource, open_source, parse_frame_range
from vtr.io.kitti_writer import KittiWriter

DATA = Path(__file__).resolve().parents[2] / "datasets"
KITTI = DATA / "kitti06_clip"
EUROC = DATA / "euroc_v101_micro"
KITTI_SIZE = (1226, 370)
EUROC_SIZE = (752, 480)
MAX_ROW_ERROR_PX = 1.0  # rectified stereo rows must agree to better than a pixel
ORB_FEATURES = 2000
ORB_MAX_HAMMING = 40  # accept only close descriptor matches
MAX_DISPARITY_PX = 200
MAX_ROW_OFFSET_PX = 20  # gross-outlier gate before measuring the row error


def small_kitti(tmp_path: Path, n: int = 3) -> Path:
    """A KITTI-layout copy of the first ``n`` frames of the shipped clip."""
    out = tmp_path / "kitti"
    for cam in ("image_0", "image_1"):
        (out / cam).mkdir(parents=True)
        for f in sorted((KITTI / cam).iterdir())[:n]:
            shutil.copy(f, out / cam / f.name)
    shutil.copy(KITTI / "calib.txt", out / "calib.txt")
    (out / "times.txt").write_text("\n".join((KITTI / "times.txt").read_text().split()[:n]) + "\n")
    return out


def test_kitti_clip_reads():
    src = open_source(KITTI)
    assert isinstance(src, KittiSource) and src.format_name == "kitti"
    assert len(src) == 51
    assert src.camera.size == KITTI_SIZE
    t = src.timestamps()
    assert t.dtype == np.int64 and np.all(np.diff(t) > 0)
    f = src[-1]
    assert f.index == 50 and f.left.shape == (370, 1226) and f.left.dtype == np.uint8
    gt = src.ground_truth()
    assert gt is not None and gt.T_world_cam.shape == (51, 4, 4)
    np.testing.assert_allclose(gt.T_world_cam[0], np.eye(4), atol=1e-6)
    with pytest.raises(IndexError):
        src[51]


def test_kitti_missing_calib(tmp_path):
    d = small_kitti(tmp_path)
    (d / "calib.txt").unlink()
    with pytest.raises(CalibrationError, match="calib.txt"):
        open_source(d)


def test_kitti_malformed_calib(tmp_path):
    d = small_kitti(tmp_path)
    (d / "calib.txt").write_text("P0: 1 2 3\nP1: " + " ".join(["0"] * 12) + "\n")
    with pytest.raises(CalibrationError, match=r"calib.txt:1: P0"):
        open_source(d)


def test_kitti_mismatched_image_sizes(tmp_path):
    d = small_kitti(tmp_path)
    bad = d / "image_1" / "000001.png"
    cv2.imwrite(str(bad), np.zeros((100, 200), np.uint8))
    src = open_source(d)
    src[0]
    with pytest.raises(DataError, match=r"image_1/000001.png: image is 200x100"):
        src[1]


def test_kitti_left_right_counts_differ(tmp_path):
    d = small_kitti(tmp_path)
    (d / "image_1" / "000002.png").unlink()
    with pytest.raises(DataError, match="3 left images but 2 right images"):
        open_source(d)


def test_kitti_corrupt_png(tmp_path):
    d = small_kitti(tmp_path)
    bad = d / "image_0" / "000002.png"
    bad.write_bytes(bad.read_bytes()[:200])
    src = open_source(d)
    with pytest.raises(DataError, match=r"image_0/000002.png: cannot decode"):
        src[2]
    first = d / "image_0" / "000000.png"
    first.write_bytes(b"not a png")
    with pytest.raises(DataError, match=r"image_0/000000.png: cannot decode"):
        open_source(d)


def test_kitti_bad_times(tmp_path):
    d = small_kitti(tmp_path)
    (d / "times.txt").write_text("0.0\n0.1\n")
    with pytest.raises(DataError, match=r"times.txt: 2 times for 3 images"):
        open_source(d)
    (d / "times.txt").write_text("0.0\n0.2\n0.1\n")
    with pytest.raises(DataError, match=r"times.txt: timestamps are not strictly increasing"):
        open_source(d)


def test_empty_and_unknown_layouts(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DataError, match="empty folder"):
        open_source(empty)
    other = tmp_path / "other"
    other.mkdir()
    (other / "readme.txt").write_text("hello")
    with pytest.raises(DataError, match="unknown layout"):
        open_source(other)
    with pytest.raises(DataError, match="no such file"):
        open_source(tmp_path / "nope")
    with pytest.raises(DataError, match="unknown format"):
        open_source(KITTI, format="tiff")
    (empty / "image_0").mkdir()
    (empty / "image_1").mkdir()
    with pytest.raises(DataError, match="image_0: no images"):
        open_source(empty)


def test_kitti_writer_round_trip_exact_ns(tmp_path):
    src = open_source(KITTI)
    out = tmp_path / "copy"
    w = KittiWriter(out, src.camera)
    t0 = 1_403_715_273_262_142_976  # a Unix-ns stamp that float seconds cannot hold exactly
    for i in range(3):
        f = src[i]
        w.add(t0 + i * 50_000_001, f.left, f.right)
    w.close()
    back = open_source(out)
    assert back.camera.matches(src.camera)
    assert back.timestamps().tolist() == [t0 + i * 50_000_001 for i in range(3)]
    for i in range(3):
        assert np.array_equal(back[i].left, src[i].left) and np.array_equal(back[i].right, src[i].right)


def test_parse_frame_range():
    assert parse_frame_range(None, 5) == [0, 1, 2, 3, 4]
    assert parse_frame_range("1:5:2", 10) == [1, 3]
    assert parse_frame_range("::3", 7) == [0, 3, 6]
    for bad in ("a:b", "0:5:0", "9:", "1:2:3:4", "3:3"):
        with pytest.raises(DataError):
            parse_frame_range(bad, 5)


# ---------------------------------------------------------------------------------------------
# EuRoC


def test_euroc_micro_reads():
    src = open_source(EUROC)
    assert isinstance(src, EurocSource) and src.format_name == "euroc"
    assert len(src) == 12 and src.camera.size == EUROC_SIZE
    t = src.timestamps()
    assert t[0] == 1403715273262142976 and np.all(np.diff(t) > 0)
    # rectified left camera on the body: a proper rigid transform
    T = src.camera.T_vehicle_sensor
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
    assert 0.10 < src.camera.baseline < 0.12  # EuRoC's ~11 cm stereo baseline


def _row_errors(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    orb = cv2.ORB_create(ORB_FEATURES)
    kl, dl = orb.detectAndCompute(left, None)
    kr, dr = orb.detectAndCompute(right, None)
    matches = [
        m for m in cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(dl, dr) if m.distance < ORB_MAX_HAMMING
    ]
    pl = np.array([kl[m.queryIdx].pt for m in matches])
    pr = np.array([kr[m.trainIdx].pt for m in matches])
    disparity, dv = pl[:, 0] - pr[:, 0], np.abs(pl[:, 1] - pr[:, 1])
    ok = (disparity > 0) & (disparity < MAX_DISPARITY_PX) & (dv < MAX_ROW_OFFSET_PX)
    return dv[ok]


def test_euroc_rectification_aligns_rows():
    src = open_source(EUROC)
    for i in (0, 6, 11):
        f = src[i]
        dv = _row_errors(f.left, f.right)
        assert len(dv) > 200
        assert np.median(dv) < MAX_ROW_ERROR_PX
        assert np.mean(dv < MAX_ROW_ERROR_PX) > 0.75
    # the raw pair is far from row-aligned: rectification does the work
    raw_l = cv2.imread(str(src._left[0]), cv2.IMREAD_GRAYSCALE)
    raw_r = cv2.imread(str(src._right[0]), cv2.IMREAD_GRAYSCALE)
    assert np.median(_row_errors(raw_l, raw_r)) > 5 * MAX_ROW_ERROR_PX


def _euroc_copy(tmp_path: Path) -> Path:
    out = tmp_path / "euroc"
    shutil.copytree(EUROC, out)
    return out / "mav0"


def test_euroc_missing_sensor_yaml(tmp_path):
    root = _euroc_copy(tmp_path)
    (root / "cam1" / "sensor.yaml").unlink()
    with pytest.raises(CalibrationError, match=r"cam1/sensor.yaml: missing camera calibration"):
        open_source(root.parent)


def test_euroc_malformed_rows(tmp_path):
    root = _euroc_copy(tmp_path)
    csv = root / "cam0" / "data.csv"
    lines = csv.read_text().splitlines()
    lines[3] = "notanumber,foo.png"
    csv.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"cam0/data.csv:4: malformed row"):
        open_source(root.parent)


def test_euroc_image_size_mismatch(tmp_path):
    root = _euroc_copy(tmp_path)
    first = sorted((root / "cam1" / "data").iterdir())[0]
    cv2.imwrite(str(first), np.zeros((240, 376), np.uint8))
    src = open_source(root.parent)
    with pytest.raises(DataError, match=rf"{first.name}: image is 376x240"):
        src[0]


def test_euroc_unpaired_right(tmp_path):
    root = _euroc_copy(tmp_path)
    csv = root / "cam1" / "data.csv"
    rows = csv.read_text().splitlines()
    shifted = [rows[0]] + [f"{int(r.split(',')[0]) + 10_000_000},{r.split(',')[1]}" for r in rows[1:]]
    csv.write_text("\n".join(shifted) + "\n")
    with pytest.raises(DataError, match="no left image has a right image"):
        open_source(root.parent)
