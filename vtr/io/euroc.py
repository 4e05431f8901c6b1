"""EuRoC ASL layout: ``mav0/cam0``, ``mav0/cam1`` (``data.csv`` of ns stamps, ``data/*.png``,
``sensor.yaml`` with intrinsics, radial-tangential distortion and ``T_BS``). Raw images are
rectified on load; the rectified left camera's pose on the body is ``camera.T_vehicle_sensor``.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import yaml

from ..camera import RawCamera, StereoRectifier
from ..conventions import NS_PER_S
from ..errors import CalibrationError, DataError
from ..geometry import QUATERNION_NORM_TOLERANCE
from ..types import StereoImages
from .base import FrameSource, GroundTruth

PAIR_TOLERANCE_NS = 1_000_000  # left/right stamps of one hardware-synchronised pair differ by < 1 ms


def euroc_root(path: Path) -> Path | None:
    """The ``mav0`` folder of an ASL dataset at ``path`` (or ``path`` itself), else None."""
    for cand in (path / "mav0", path):
        if (cand / "cam0" / "data.csv").is_file() and (cand / "cam1").is_dir():
            return cand
    return None


def read_sensor_yaml(path: Path) -> RawCamera:
    """Parse an ASL camera ``sensor.yaml`` (OpenCV's %YAML:1.0 header tolerated)."""
    if not path.is_file():
        raise CalibrationError(f"{path}: missing camera calibration")
    try:
        raw = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        raise CalibrationError(f"{path}: not a text file (expected an ASL sensor.yaml)") from None
    text = "\n".join(line for line in raw.splitlines() if not line.startswith("%YAML"))
    try:
        d = yaml.safe_load(text)
        fu, fv, cu, cv = (float(v) for v in d["intrinsics"])
        w, h = (int(v) for v in d["resolution"])
        dist = np.array(d.get("distortion_coefficients", [0, 0, 0, 0]), float)
        T = np.array(d["T_BS"]["data"], float).reshape(4, 4)
    except (yaml.YAMLError, KeyError, TypeError, ValueError) as err:
        raise CalibrationError(f"{path}: malformed camera calibration ({err!r})") from err
    model = d.get("distortion_model", "radial-tangential")
    if model not in ("radial-tangential", "radtan", "none"):
        raise CalibrationError(f"{path}: distortion model {model!r} not supported (radial-tangential only)")
    if w <= 0 or h <= 0:
        raise CalibrationError(f"{path}: resolution {w}x{h} is empty")
    if not (np.isfinite([fu, fv, cu, cv]).all() and np.isfinite(dist).all() and np.isfinite(T).all()):
        raise CalibrationError(f"{path}: NaN or infinite value in intrinsics, distortion or T_BS")
    if fu <= 0 or fv <= 0:
        raise CalibrationError(f"{path}: focal lengths must be positive, got {fu:g}, {fv:g}")
    K = np.array([[fu, 0, cu], [0, fv, cv], [0, 0, 1.0]])
    return RawCamera(K=K, dist=dist, width=w, height=h, T_body_cam=T)


def read_stamp_csv(path: Path) -> tuple[np.ndarray, list[str]]:
    """``#timestamp [ns],filename`` rows -> (int64 ns, filenames)."""
    if not path.is_file():
        raise DataError(f"{path}: missing image list")
    t, names, linenos = [], [], []
    for lineno, line in enumerate(_text(path).splitlines(), 1):
        if not line.strip() or line.startswith("#"):
            continue
        parts = [p.strip() for p in line.split(",")]
        try:
            t.append(int(parts[0]))
            names.append(parts[1])
        except (ValueError, IndexError) as err:
            raise DataError(f"{path}:{lineno}: malformed row {line!r}") from err
        linenos.append(lineno)
    t_ns = np.array(t, np.int64)
    check_increasing(t_ns, np.array(linenos), path)
    return t_ns, names


def _text(path: Path) -> str:
    try:
        return path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as err:
        raise DataError(f"{path}: not a text file ({err.reason} at byte {err.start})") from None


def check_increasing(t_ns: np.ndarray, linenos: np.ndarray, path: Path) -> None:
    """``DataError`` naming the file and line unless the times are strictly increasing (unique, sorted)."""
    bad = np.flatnonzero(np.diff(t_ns) <= 0)
    if len(bad):
        k = int(bad[0]) + 1
        what = "repeats" if t_ns[k] == t_ns[k - 1] else "is earlier than"
        raise DataError(
            f"{path}:{linenos[k]}: timestamp {t_ns[k]} {what} the previous row's "
            f"({t_ns[k - 1]}, line {linenos[k - 1]}): times must be strictly increasing"
        )


class EurocSource(FrameSource):
    """Reader of an EuRoC ASL stereo sequence, rectified on the fly."""

    format_name = "euroc"
    gravity_aligned_truth = True  # the Vicon / Leica world of state_groundtruth_estimate0 has z up

    def __init__(self, path: str | Path, alpha: float = 0.0):
        self.path = Path(path)
        if not self.path.is_dir():
            raise FileNotFoundError(f"{self.path}: no such folder")
        root = euroc_root(self.path)
        if root is None:
            raise DataError(f"{self.path}: not an EuRoC ASL layout (needs mav0/cam0/data.csv and mav0/cam1)")
        self.root = root
        left = read_sensor_yaml(root / "cam0" / "sensor.yaml")
        right = read_sensor_yaml(root / "cam1" / "sensor.yaml")
        self.rectifier = StereoRectifier.from_raw(
            left, right, alpha=alpha, where=f"{root / 'cam0' / 'sensor.yaml'}, {root / 'cam1' / 'sensor.yaml'}"
        )
        self.camera = self.rectifier.camera
        tl, nl = read_stamp_csv(root / "cam0" / "data.csv")
        tr, nr = read_stamp_csv(root / "cam1" / "data.csv")
        if len(tl) == 0:
            raise DataError(f"{root / 'cam0' / 'data.csv'}: no images")
        # pair left and right by nearest stamp within tolerance
        j = np.clip(np.searchsorted(tr, tl), 1, max(len(tr) - 1, 1)) if len(tr) > 1 else np.zeros_like(tl)
        j = np.where(np.abs(tr[j - 1] - tl) < np.abs(tr[j] - tl), j - 1, j) if len(tr) > 1 else j
        ok = np.abs(tr[j] - tl) <= PAIR_TOLERANCE_NS if len(tr) else np.zeros(len(tl), bool)
        if not np.any(ok):
            raise DataError(f"{root}: no left image has a right image within {PAIR_TOLERANCE_NS} ns")
        self._t_ns = tl[ok]
        self._left = [root / "cam0" / "data" / nl[i] for i in np.flatnonzero(ok)]
        self._right = [root / "cam1" / "data" / nr[k] for k in j[ok]]
        # optional ground truth: validated now, not after a whole run
        self._gt = body_ground_truth(root / "state_groundtruth_estimate0" / "data.csv", 1, self.camera.T_vehicle_sensor)

    def __len__(self) -> int:
        return len(self._t_ns)

    def timestamps(self) -> np.ndarray:
        return self._t_ns

    def _load_raw(self, f: Path) -> np.ndarray:
        img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        return self.check_image(img, f)

    def _load(self, index: int) -> StereoImages:
        left, right = self.rectifier.rectify(self._load_raw(self._left[index]), self._load_raw(self._right[index]))
        return StereoImages(int(self._t_ns[index]), index, left, right)

    def ground_truth(self) -> GroundTruth | None:
        """Left rectified camera poses from ``state_groundtruth_estimate0`` (body poses), if present."""
        return self._gt


def body_ground_truth(path: Path, ns_per_unit: int, T_body_cam: np.ndarray) -> GroundTruth | None:
    """Camera poses from a CSV of body poses (time, x y z, qw qx qy qz; time in units of
    ``ns_per_unit`` ns) composed with the camera's place on the body; None when the file is absent."""
    if not path.is_file():
        return None
    try:
        rows = np.loadtxt(path, delimiter=",", comments="#", ndmin=2)
    except (ValueError, UnicodeDecodeError) as err:
        raise DataError(f"{path}: malformed ({' '.join(str(err).split())})") from None
    if rows.shape[0] == 0:
        raise DataError(f"{path}: no pose rows")
    if rows.shape[1] < 8:
        raise DataError(f"{path}: {rows.shape[1]} columns per row, expected at least 8 (time, x y z, qw qx qy qz)")
    lines = np.array(
        [i + 1 for i, line in enumerate(_text(path).splitlines()) if line.strip() and not line.lstrip().startswith("#")]
    )
    bad = np.flatnonzero(~np.isfinite(rows[:, :8]).all(axis=1))
    if len(bad):
        raise DataError(f"{path}:{lines[bad[0]]}: NaN or infinite value")
    q_norm = np.linalg.norm(rows[:, 4:8], axis=1)
    bad = np.flatnonzero(np.abs(q_norm - 1.0) > QUATERNION_NORM_TOLERANCE)
    if len(bad):
        raise DataError(f"{path}:{lines[bad[0]]}: quaternion norm {q_norm[bad[0]]:.6g} is not 1")
    check_increasing(rows[:, 0].astype(np.int64), lines, path)
    T_world_body = np.tile(np.eye(4), (len(rows), 1, 1))
    T_world_body[:, :3, 3] = rows[:, 1:4]
    from scipy.spatial.transform import Rotation  # here: ~0.3 s to import

    T_world_body[:, :3, :3] = Rotation.from_quat(rows[:, [5, 6, 7, 4]]).as_matrix()
    return GroundTruth(rows[:, 0].astype(np.int64) * ns_per_unit, T_world_body @ T_body_cam)


def is_stereo_pairs(path: Path) -> bool:
    return (path / "sensor_left.yaml").is_file() and (path / "left_0.png").is_file()


class StereoPairsSource(FrameSource):
    """Raw stereo pairs ``left_K.png``/``right_K.png`` with ``sensor_left.yaml``/``sensor_right.yaml``
    (ASL camera yamls) and optional ``groundtruth.csv`` (index, p_x, p_y, p_z, q_w, q_x, q_y, q_z of
    T_world_body): the layout of the shipped EuRoC revisit pairs. Rectified on load; frames are
    K = 0, 1, ... with nominal times K seconds (the pairs carry no timestamps).
    """

    format_name = "stereo-pairs"
    gravity_aligned_truth = True  # groundtruth.csv holds EuRoC body poses (world z up)

    def __init__(self, path: str | Path, alpha: float = 0.0):
        self.path = Path(path)
        if not self.path.is_dir():
            raise FileNotFoundError(f"{self.path}: no such folder")
        left = read_sensor_yaml(self.path / "sensor_left.yaml")
        right = read_sensor_yaml(self.path / "sensor_right.yaml")
        self.rectifier = StereoRectifier.from_raw(
            left, right, alpha=alpha, where=f"{self.path / 'sensor_left.yaml'}, {self.path / 'sensor_right.yaml'}"
        )
        self.camera = self.rectifier.camera
        n = 0
        while (self.path / f"left_{n}.png").is_file():
            n += 1
        if n == 0:
            raise DataError(f"{self.path}: no left_0.png")
        self._n = n
        self._gt = body_ground_truth(self.path / "groundtruth.csv", NS_PER_S, self.camera.T_vehicle_sensor)

    def __len__(self) -> int:
        return self._n

    def timestamps(self) -> np.ndarray:
        return np.arange(self._n, dtype=np.int64) * NS_PER_S

    def _load(self, index: int) -> StereoImages:
        raw = []
        for side in ("left", "right"):
            f = self.path / f"{side}_{index}.png"
            raw.append(self.check_image(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE), f))
        left, right = self.rectifier.rectify(*raw)
        return StereoImages(int(self.timestamps()[index]), index, left, right)

    def ground_truth(self) -> GroundTruth | None:
        """Left rectified camera poses from ``groundtruth.csv`` (body poses, time in seconds)."""
        return self._gt
