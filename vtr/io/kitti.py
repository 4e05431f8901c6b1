"""KITTI odometry layout: ``image_0/`` (left), ``image_1/`` (right), ``calib.txt`` (P0, P1),
``times.txt`` (s) and optionally ``poses.txt`` (T_world_cam0 as 3x4 rows, world = first camera).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np

from ..camera import StereoCamera
from ..conventions import NS_PER_S
from ..errors import CalibrationError, DataError
from ..geometry import check_se3
from ..types import StereoImages
from .base import FrameSource, GroundTruth

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pgm", ".bmp")
POSE_TOLERANCE = 1e-3  # KITTI poses are printed with ~6 significant digits: rigid to this


def is_kitti(path: Path) -> bool:
    return (path / "image_0").is_dir() and (path / "image_1").is_dir()


def read_kitti_calib(path: Path, width: int, height: int) -> StereoCamera:
    """Parse ``calib.txt`` (rectified P0/P1) into a ``StereoCamera`` of the given image size."""
    if not path.is_file():
        raise CalibrationError(f"{path}: missing calibration file (KITTI layout needs calib.txt with P0, P1)")
    P: dict[str, np.ndarray] = {}
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        if ":" not in line:
            continue
        key, vals = line.split(":", 1)
        try:
            P[key.strip()] = np.array(vals.split(), float).reshape(3, 4)
        except ValueError as err:
            raise CalibrationError(f"{path}:{lineno}: {key.strip()} is not 12 numbers") from err
    for key in ("P0", "P1"):
        if key not in P:
            raise CalibrationError(f"{path}: no {key} line (need P0 and P1)")
    P0, P1 = P["P0"], P["P1"]
    fx = P0[0, 0]
    if not np.allclose(P0[:, :3], P1[:, :3]):
        raise CalibrationError(f"{path}: P0 and P1 have different intrinsics; images are not rectified")
    return StereoCamera(
        fx=fx, fy=P0[1, 1], cx=P0[0, 2], cy=P0[1, 2], baseline=-(P1[0, 3] - P0[0, 3]) / fx, width=width, height=height
    )


def _list_images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


class KittiSource(FrameSource):
    """Reader of a KITTI-layout stereo folder (rectified greyscale images)."""

    format_name = "kitti"

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.is_dir():
            raise FileNotFoundError(f"{self.path}: no such folder")
        if not is_kitti(self.path):
            raise DataError(f"{self.path}: not a KITTI layout (needs image_0/ and image_1/)")
        self.left_files = _list_images(self.path / "image_0")
        self.right_files = _list_images(self.path / "image_1")
        if not self.left_files:
            raise DataError(f"{self.path / 'image_0'}: no images")
        if len(self.left_files) != len(self.right_files):
            raise DataError(f"{self.path}: {len(self.left_files)} left images but {len(self.right_files)} right images")
        first = cv2.imread(str(self.left_files[0]), cv2.IMREAD_GRAYSCALE)
        if first is None:
            raise DataError(f"{self.left_files[0]}: cannot decode image (missing or corrupt file)")
        self.camera = read_kitti_calib(self.path / "calib.txt", first.shape[1], first.shape[0])
        self._t_ns = self._read_times()
        self._gt = self._read_ground_truth()  # optional; validated now, not after a whole run

    def _read_times(self) -> np.ndarray:
        n = len(self.left_files)
        exact = self.path / "times_ns.txt"
        if exact.is_file():
            # written by KittiWriter: exact int64 ns (times.txt in seconds cannot hold Unix ns)
            try:
                t_ns = np.loadtxt(exact, ndmin=1, dtype=np.int64)
            except ValueError as err:
                raise DataError(f"{exact}: malformed ({err})") from err
            if len(t_ns) != n:
                raise DataError(f"{exact}: {len(t_ns)} times for {n} images")
            return t_ns
        times = self.path / "times.txt"
        if not times.is_file():
            # KITTI's nominal 10 Hz when the clip ships no times.txt
            return np.arange(n, dtype=np.int64) * 100_000_000
        try:
            t = np.loadtxt(times, ndmin=1, dtype=float)
        except ValueError as err:
            raise DataError(f"{times}: malformed ({err})") from err
        if len(t) != n:
            raise DataError(f"{times}: {len(t)} times for {n} images")
        bad = ~np.isfinite(t) | (np.abs(t) >= 2**63 / NS_PER_S)
        if bad.any():
            line = int(np.argmax(bad)) + 1
            raise DataError(
                f"{times}: line {line}: {float(t[line - 1])} is not a time in seconds that fits int64 nanoseconds"
            )
        t_ns = np.round(t * NS_PER_S).astype(np.int64)
        if np.any(np.diff(t_ns) <= 0):
            raise DataError(f"{times}: timestamps are not strictly increasing")
        return t_ns

    def __len__(self) -> int:
        return len(self.left_files)

    def timestamps(self) -> np.ndarray:
        return self._t_ns

    def _load(self, index: int) -> StereoImages:
        lf, rf = self.left_files[index], self.right_files[index]
        left = self.check_image(cv2.imread(str(lf), cv2.IMREAD_GRAYSCALE), lf)
        right = self.check_image(cv2.imread(str(rf), cv2.IMREAD_GRAYSCALE), rf)
        return StereoImages(int(self._t_ns[index]), index, left, right)

    def ground_truth(self) -> GroundTruth | None:
        return self._gt

    def _read_ground_truth(self) -> GroundTruth | None:
        poses = self.path / "poses.txt"
        if not poses.is_file():
            return None
        T = read_kitti_poses(poses)
        if len(T) != len(self):
            raise DataError(f"{poses}: {len(T)} poses for {len(self)} images")
        return GroundTruth(self._t_ns.copy(), T)


def read_kitti_poses(path: Path) -> np.ndarray:
    """KITTI pose file (3x4 row-major per line) -> (N, 4, 4)."""
    try:
        rows = np.loadtxt(path, ndmin=2)
    except ValueError as err:
        raise DataError(f"{path}: malformed pose file ({err})") from err
    if rows.shape[1] != 12:
        raise DataError(f"{path}: expected 12 numbers per line, got {rows.shape[1]}")
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :] = rows.reshape(-1, 3, 4)
    for i, T_i in enumerate(T):
        check_se3(T_i, f"{path}: pose {i + 1}", tol=POSE_TOLERANCE, error=DataError)
    return T


def write_kitti_poses(path: Path, T: np.ndarray) -> None:
    """Write (N, 4, 4) poses in KITTI's 3x4 row-major format."""
    np.savetxt(path, np.asarray(T)[:, :3, :].reshape(-1, 12), fmt="%.9e")


def write_reordered_clip(src: str | Path, dst: str | Path, order: list[int]) -> Path:
    """A KITTI-layout copy of clip ``src`` at ``dst`` with its frames in ``order`` (images linked, not copied;
    times kept increasing, poses with their frames): reversed order is the route travelled backward facing as
    taught (a gimbal's return flight), a gap drops frames mid-route (odometry loses track across it)."""

    src, dst = Path(src), Path(dst)
    (dst / "image_0").mkdir(parents=True)
    (dst / "image_1").mkdir()
    shutil.copy(src / "calib.txt", dst / "calib.txt")
    times = np.loadtxt(src / "times.txt", ndmin=1)
    poses = np.loadtxt(src / "poses.txt", ndmin=2)
    for k, i in enumerate(order):
        for side in ("image_0", "image_1"):
            (dst / side / f"{k:06d}.png").symlink_to((src / side / f"{i:06d}.png").resolve())
    np.savetxt(dst / "times.txt", np.sort(times[order]), fmt="%.6e")
    np.savetxt(dst / "poses.txt", poses[order], fmt="%.9e")
    return dst
