"""CLOUD run folders (thesis §9.5): monocular images plus GPS, attitude, IMU and gimbal streams, read as typed
streams by :class:`CloudRun`, with the GPS track in ENU metres, the vehicle's reference trajectory and the camera's
at image times; not a stereo ``FrameSource`` (the run is monocular). The layout, file names, quaternion order and
frames: docs/inputs.md, "CLOUD run folders" (frames: :mod:`vtr.io.cloud_geometry`; writer:
:mod:`vtr.io.cloud_writer`)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import cv2
import numpy as np

from ..errors import DataError
from .base import GroundTruth
from .cloud_geometry import R_GIMBAL_CAMERA, geodetic_to_enu, rotation_from_gimbal_angles, spatial_transform

IMAGES_DIR = "images"
#: stream name -> accepted file names (the first is the one written)
STREAM_FILES: dict[str, tuple[str, ...]] = {
    "image_ids": ("imageids.txt", "image_ids.txt", "imageid.txt"),
    "velocities": ("velocities.txt",),
    "attitude": ("attitude.txt",),
    "acceleration": ("acceleration.txt",),
    "gps": ("gps.txt",),
    "gimbal_state": ("gimbalstate.txt", "gimbal_state.txt"),
    "gimbal_angles": ("gimbalangles.txt", "gimbal_angles.txt"),
}
#: numeric values per row after the timestamp
STREAM_COLUMNS = {"velocities": 3, "attitude": 4, "acceleration": 3, "gps": 3, "gimbal_state": 7, "gimbal_angles": 3}
QUAT_ORDERS = ("xyzw", "wxyz")
#: a quaternion whose norm differs from 1 by more than this is a malformed row
QUAT_NORM_TOL = 1e-3
MONO16_SHIFT = 8  # 16-bit images -> 8 bit by keeping the high byte
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pgm", ".bmp", ".tif", ".tiff")


# ---------------------------------------------------------------------------------------------
# typed streams


@dataclass(frozen=True)
class Vectors:
    """Timestamped 3-vectors ``xyz`` (N, 3) in ``unit``, expressed in ``frame``."""

    t_ns: np.ndarray
    xyz: np.ndarray
    unit: str
    frame: str


@dataclass(frozen=True)
class Attitude:
    """Vehicle attitude: ``R_enu_vehicle`` (N, 3, 3) rotates vehicle FLU vectors into ground ENU."""

    t_ns: np.ndarray
    quat_xyzw: np.ndarray

    @property
    def R_enu_vehicle(self) -> np.ndarray:
        return spatial_transform().Rotation.from_quat(self.quat_xyzw).as_matrix()

    def at(self, t_ns: np.ndarray) -> np.ndarray:
        """``R_enu_vehicle`` slerped at times inside the stream's span (N, 3, 3)."""
        return _slerp(self.t_ns, spatial_transform().Rotation.from_quat(self.quat_xyzw), np.asarray(t_ns, np.int64))


@dataclass(frozen=True)
class GpsFixes:
    """WGS84 fixes: latitude, longitude (deg), ellipsoidal height (m)."""

    t_ns: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    alt_m: np.ndarray

    @property
    def origin(self) -> tuple[float, float, float]:
        """The first fix (lat deg, lon deg, alt m): origin of ``enu()``."""
        return float(self.lat_deg[0]), float(self.lon_deg[0]), float(self.alt_m[0])

    def enu(self, origin: tuple[float, float, float] | None = None) -> np.ndarray:
        """Positions (N, 3) in metres, ENU axes at ``origin`` (default the first fix)."""
        return geodetic_to_enu(self.lat_deg, self.lon_deg, self.alt_m, *(origin or self.origin))


@dataclass(frozen=True)
class GimbalState:
    """Camera pose on the vehicle base: ``T_base_camera`` (N, 4, 4), metres."""

    t_ns: np.ndarray
    T_base_camera: np.ndarray


@dataclass(frozen=True)
class GimbalAngles:
    """Raw gimbal angles in rad (file: degrees): roll, pitch w.r.t. NED, yaw relative to the vehicle."""

    t_ns: np.ndarray
    roll: np.ndarray
    pitch: np.ndarray
    yaw: np.ndarray


@dataclass(frozen=True)
class VehicleTrajectory:
    """Reference poses of the vehicle: ``T_enu_vehicle`` (N, 4, 4); ENU origin at the first GPS fix."""

    t_ns: np.ndarray
    T_enu_vehicle: np.ndarray


@dataclass(frozen=True)
class MonoImage:
    """One left-camera image (8-bit grey) of a CLOUD run."""

    t_ns: int
    index: int
    image: np.ndarray


def _slerp(t: np.ndarray, rots: Any, tq: np.ndarray) -> np.ndarray:
    if len(t) == 1:
        return np.repeat(rots.as_matrix(), len(tq), axis=0)
    t0 = t[0]
    return spatial_transform().Slerp((t - t0).astype(float), rots)((tq - t0).astype(float)).as_matrix()


def _interp(t: np.ndarray, v: np.ndarray, tq: np.ndarray) -> np.ndarray:
    t0 = t[0]
    x, xq = (t - t0).astype(float), (tq - t0).astype(float)
    return np.stack([np.interp(xq, x, v[:, k]) for k in range(v.shape[1])], axis=1)


# ---------------------------------------------------------------------------------------------
# parsing


def _read_rows(path: Path, ncols: int | None) -> tuple[np.ndarray, list[list[str]], np.ndarray]:
    """Rows ``timestamp, v1..vk`` -> (int64 ns, value strings, line numbers). ``ncols`` None: any."""
    try:
        text = path.read_text()
    except UnicodeDecodeError as err:
        raise DataError(f"{path}: not a text file ({err})") from err
    t: list[int] = []
    vals: list[list[str]] = []
    lines: list[int] = []
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = [p.strip() for p in s.split(",")]
        try:
            ts = int(parts[0])
        except ValueError as err:
            if not t and lineno == 1:  # a header row
                continue
            raise DataError(f"{path}:{lineno}: timestamp {parts[0]!r} is not an integer (Unix ns)") from err
        if ncols is not None and len(parts) != ncols + 1:
            raise DataError(
                f"{path}:{lineno}: expected {ncols + 1} comma-separated values (timestamp and "
                f"{ncols}), got {len(parts)}: {s!r}"
            )
        if t and ts < t[-1]:
            raise DataError(f"{path}:{lineno}: timestamp {ts} is earlier than the previous row's {t[-1]}")
        t.append(ts)
        vals.append(parts[1:])
        lines.append(lineno)
    if not t:
        raise DataError(f"{path}: no data rows")
    return np.array(t, np.int64), vals, np.array(lines)


def read_stream(path: Path, ncols: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A numeric CLOUD stream -> (t_ns int64 (N,), values float64 (N, ncols), line numbers (N,))."""
    t, vals, lines = _read_rows(path, ncols)
    try:
        v = np.array(vals, float)
    except ValueError:
        for row, ln in zip(vals, lines, strict=True):
            try:
                [float(x) for x in row]
            except ValueError as err:
                raise DataError(f"{path}:{ln}: non-numeric value in {row!r}") from err
        raise
    bad = np.flatnonzero(~np.all(np.isfinite(v), axis=1))
    if len(bad):
        raise DataError(f"{path}:{lines[bad[0]]}: non-finite value")
    return t, v, lines


# ---------------------------------------------------------------------------------------------
# the run


def find_stream(path: Path, name: str) -> Path | None:
    """The file of stream ``name`` in run folder ``path`` (any accepted alias), or None."""
    for fname in STREAM_FILES[name]:
        if (path / fname).is_file():
            return path / fname
    return None


def is_cloud_run(path: Path) -> bool:
    """True for a folder with ``images/`` and at least one CLOUD stream file."""
    path = Path(path)
    return (path / IMAGES_DIR).is_dir() and any(find_stream(path, n) is not None for n in STREAM_FILES)


def refuse_cloud_stereo(path: Path) -> NoReturn:
    """``open_source`` opener for CLOUD folders: always raises (they hold no stereo pairs)."""
    raise DataError(
        f"{path}: CLOUD runs are monocular (left camera only): stereo odometry, teach and repeat need a "
        "stereo source (KITTI/EuRoC folder or a ROS bag with two cameras). Use vtr.io.cloud.CloudRun for this "
        "run's images, GPS/attitude reference trajectory and gimbal state (localization evaluation)."
    )


class CloudImages(Sequence):
    """The run's left images (8-bit grey, colour converted) at their image-id timestamps."""

    def __init__(self, t_ns: np.ndarray, files: list[Path]):
        self.t_ns, self.files = t_ns, files

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, index: int) -> MonoImage:  # type: ignore[override]
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"image {index} outside run ({n} images)")
        index %= n
        f = self.files[index]
        img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise DataError(f"{f}: cannot decode image (missing or corrupt file)")
        if img.ndim == 3:  # colour runs (UTIAS Day/Winter): OpenCV's BGR luma, as for ROS bgr8 images
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
        if img.dtype == np.uint16:
            img = np.right_shift(img, MONO16_SHIFT).astype(np.uint8)
        return MonoImage(int(self.t_ns[index]), index, img)


class CloudRun:
    """Typed access to one CLOUD run folder (see the module docstring for streams, units and frames).

    Streams are parsed on first use; a missing or malformed stream raises ``DataError`` naming the
    file (and row). ``validate()`` parses everything at once.
    """

    def __init__(
        self,
        path: str | Path,
        quat_order: str = "xyzw",
        T_vehicle_base: np.ndarray | None = None,
        R_gimbal_camera: np.ndarray = R_GIMBAL_CAMERA,
    ):
        self.path = Path(path)
        if not self.path.is_dir():
            raise FileNotFoundError(f"{self.path}: no such folder")
        if not (self.path / IMAGES_DIR).is_dir():
            raise DataError(f"{self.path}: not a CLOUD run folder (no {IMAGES_DIR}/ subfolder)")
        if quat_order not in QUAT_ORDERS:
            raise DataError(f"quat_order {quat_order!r}: one of {', '.join(QUAT_ORDERS)}")
        self.quat_order = quat_order
        self.T_vehicle_base = np.eye(4) if T_vehicle_base is None else np.asarray(T_vehicle_base, float)
        self.R_gimbal_camera = np.asarray(R_gimbal_camera, float)
        self._cache: dict[str, object] = {}

    # -- files

    def stream_path(self, name: str) -> Path:
        """File of stream ``name``; ``DataError`` naming the expected file when it is missing."""
        f = find_stream(self.path, name)
        if f is None:
            raise DataError(
                f"{self.path / STREAM_FILES[name][0]}: missing CLOUD {name} stream "
                f"(accepted names: {', '.join(STREAM_FILES[name])})"
            )
        return f

    def missing_streams(self) -> list[str]:
        """Names of the streams without a file in the folder."""
        return [n for n in STREAM_FILES if find_stream(self.path, n) is None]

    def validate(self) -> None:
        """Parse every stream and check every image id resolves to a file; raise on the first problem."""
        missing = self.missing_streams()
        if missing:
            raise DataError(f"{self.path}: missing CLOUD stream(s): " + ", ".join(STREAM_FILES[n][0] for n in missing))
        _ = self.images
        for read in (
            self.velocities,
            self.acceleration,
            self.attitude,
            self.gps,
            self.gimbal_state,
            self.gimbal_angles,
        ):
            read()

    def _numeric(self, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, Path]:
        key = f"raw:{name}"
        if key not in self._cache:
            f = self.stream_path(name)
            self._cache[key] = (*read_stream(f, STREAM_COLUMNS[name]), f)
        return self._cache[key]  # type: ignore[return-value]

    def _quats(self, q: np.ndarray, lines: np.ndarray, f: Path) -> np.ndarray:
        q = q[:, [1, 2, 3, 0]] if self.quat_order == "wxyz" else q
        norm = np.linalg.norm(q, axis=1)
        bad = np.flatnonzero(np.abs(norm - 1.0) > QUAT_NORM_TOL)
        if len(bad):
            raise DataError(
                f"{f}:{lines[bad[0]]}: quaternion norm {norm[bad[0]]:.6f} is not 1 "
                f"(malformed row or wrong quat_order {self.quat_order!r})"
            )
        return q / norm[:, None]

    # -- streams

    def velocities(self) -> Vectors:
        """Estimated vehicle velocity (m/s) in ground ENU."""
        t, v, _, _ = self._numeric("velocities")
        return Vectors(t, v, "m/s", "ground ENU")

    def acceleration(self) -> Vectors:
        """Raw accelerometer specific force (m/s^2) in vehicle FLU (about +9.81 on z when level and still)."""
        t, v, _, _ = self._numeric("acceleration")
        return Vectors(t, v, "m/s^2", "vehicle FLU")

    def attitude(self) -> Attitude:
        """Raw attitude: rotation vehicle FLU -> ground ENU."""
        t, q, lines, f = self._numeric("attitude")
        return Attitude(t, self._quats(q, lines, f))

    def gps(self) -> GpsFixes:
        """Raw GPS fixes (deg, deg, m above the WGS84 ellipsoid)."""
        t, v, lines, f = self._numeric("gps")
        bad = np.flatnonzero((np.abs(v[:, 0]) > 90.0) | (np.abs(v[:, 1]) > 180.0))
        if len(bad):
            raise DataError(f"{f}:{lines[bad[0]]}: latitude/longitude out of range: {v[bad[0], :2]}")
        return GpsFixes(t, v[:, 0], v[:, 1], v[:, 2])

    def gimbal_state(self) -> GimbalState:
        """Estimated camera pose on the base, ``T_base_camera``."""
        t, v, lines, f = self._numeric("gimbal_state")
        q = self._quats(v[:, 3:], lines, f)
        T = np.tile(np.eye(4), (len(t), 1, 1))
        T[:, :3, :3] = spatial_transform().Rotation.from_quat(q).as_matrix()
        T[:, :3, 3] = v[:, :3]
        return GimbalState(t, T)

    def gimbal_angles(self) -> GimbalAngles:
        """Raw gimbal angles converted to rad."""
        t, v, _, _ = self._numeric("gimbal_angles")
        r = np.radians(v)
        return GimbalAngles(t, r[:, 0], r[:, 1], r[:, 2])

    def gimbal_rotation_from_angles(self) -> tuple[np.ndarray, np.ndarray]:
        """``(t_ns, R_base_camera)`` computed from the raw gimbal angles and the slerped attitude, at the
        gimbal-angle times inside the attitude span (compare with ``gimbal_state``)."""
        ga, att = self.gimbal_angles(), self.attitude()
        keep = (ga.t_ns >= att.t_ns[0]) & (ga.t_ns <= att.t_ns[-1])
        if not np.any(keep):
            raise DataError(f"{self.path}: gimbal angles and attitude do not overlap in time")
        R = rotation_from_gimbal_angles(
            ga.roll[keep],
            ga.pitch[keep],
            ga.yaw[keep],
            att.at(ga.t_ns[keep]),
            self.T_vehicle_base[:3, :3],
            self.R_gimbal_camera,
        )
        return ga.t_ns[keep], R

    # -- images

    def image_ids(self) -> tuple[np.ndarray, list[str]]:
        """Image timestamps (int64 ns) and ids, from the image-id stream."""
        f = self.stream_path("image_ids")
        t, vals, lines = _read_rows(f, 1)
        return t, [v[0] for v in vals]

    @property
    def images(self) -> CloudImages:
        """Left images in acquisition order (every id must resolve to a file in ``images/``)."""
        if "images" not in self._cache:
            t, ids = self.image_ids()
            folder = self.path / IMAGES_DIR
            names = {e.name for e in os.scandir(folder) if e.is_file()}
            by_stem: dict[str, str] = {}
            for n in names:
                stem, suf = os.path.splitext(n)
                if suf.lower() in IMAGE_SUFFIXES:
                    by_stem.setdefault(stem, n)
            files = []
            for k, i in enumerate(ids):
                name = i if i in names else by_stem.get(i) or by_stem.get(os.path.splitext(i)[0])
                if name is None:
                    raise DataError(
                        f"{self.stream_path('image_ids')}: row {k + 1} (image id {i!r}): no such image in {folder}"
                    )
                files.append(folder / name)
            self._cache["images"] = CloudImages(t, files)
        return self._cache["images"]  # type: ignore[return-value]

    # -- references

    def reference_trajectory(self) -> VehicleTrajectory:
        """``T_enu_vehicle`` at GPS times within the attitude span: GPS position (ENU m relative to the first
        fix) and slerped attitude. The reference for evaluating a localization or odometry track."""
        gps, att = self.gps(), self.attitude()
        keep = (gps.t_ns >= att.t_ns[0]) & (gps.t_ns <= att.t_ns[-1])
        if not np.any(keep):
            raise DataError(f"{self.path}: GPS and attitude streams do not overlap in time")
        T = np.tile(np.eye(4), (int(keep.sum()), 1, 1))
        T[:, :3, :3] = att.at(gps.t_ns[keep])
        T[:, :3, 3] = gps.enu()[keep]
        return VehicleTrajectory(gps.t_ns[keep], T)

    def camera_trajectory(self, t_ns: np.ndarray | None = None) -> GroundTruth:
        """``T_enu_camera`` = ``T_enu_vehicle @ T_vehicle_base @ T_base_camera`` at ``t_ns`` (default the image
        times), interpolated (GPS linearly, attitude and gimbal by slerp); times outside any stream's span
        are dropped."""
        gps, att, gs = self.gps(), self.attitude(), self.gimbal_state()
        tq = self.images.t_ns if t_ns is None else np.asarray(t_ns, np.int64)
        lo = max(gps.t_ns[0], att.t_ns[0], gs.t_ns[0])
        hi = min(gps.t_ns[-1], att.t_ns[-1], gs.t_ns[-1])
        tq = tq[(tq >= lo) & (tq <= hi)]
        if len(tq) == 0:
            raise DataError(f"{self.path}: no requested time lies inside the GPS, attitude and gimbal spans")
        T_ev = np.tile(np.eye(4), (len(tq), 1, 1))
        T_ev[:, :3, :3] = att.at(tq)
        T_ev[:, :3, 3] = _interp(gps.t_ns, gps.enu(), tq)
        T_bc = np.tile(np.eye(4), (len(tq), 1, 1))
        T_bc[:, :3, :3] = _slerp(gs.t_ns, spatial_transform().Rotation.from_matrix(gs.T_base_camera[:, :3, :3]), tq)
        T_bc[:, :3, 3] = _interp(gs.t_ns, gs.T_base_camera[:, :3, 3], tq)
        return GroundTruth(tq, T_ev @ self.T_vehicle_base @ T_bc)

    def ground_truth(self) -> GroundTruth:
        """Camera reference trajectory at the image times (same as ``camera_trajectory()``)."""
        return self.camera_trajectory()
