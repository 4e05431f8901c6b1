"""CLOUD run folders (Greeff thesis §9.5): monocular images plus GPS, attitude, IMU and gimbal streams.

A run folder holds ``images/`` (left camera only, named in acquisition order) and comma-delimited
text streams, one row per sample, ``timestamp, values...`` with Unix-ns timestamps:

=================== ====== ===================================================== ==================
file                rate   values (unit)                                         frame
=================== ====== ===================================================== ==================
``imageids.txt``    15 Hz  image id as found in ``images/``                      -
``velocities.txt``  50 Hz  vx, vy, vz (m/s)                                      ground ENU
``attitude.txt``    100 Hz quaternion (``quat_order``, default x y z w) rotating vehicle FLU -> ground ENU
``acceleration.txt`` 400 Hz ax, ay, az (m/s^2, raw IMU specific force)          vehicle FLU
``gps.txt``         50 Hz  latitude (deg), longitude (deg), altitude (m, WGS84 ellipsoid)
``gimbalstate.txt`` 50 Hz  x, y, z (m), quaternion: ``T_base_camera``            base FLU <- camera
``gimbalangles.txt`` 50 Hz roll, pitch, yaw (deg, ZYX) of the gimbal frame w.r.t. NED; yaw relative
                           to the vehicle heading (DJI SDK convention)
=================== ====== ===================================================== ==================

The thesis names ``velocities.txt``, ``attitude.txt``, ``acceleration.txt``, ``gps.txt`` and
``gimbalstate.txt``; the image-id and gimbal-angle file names are not given there, so the reader
accepts the aliases in ``STREAM_FILES`` (the writer uses the first). The order of the quaternion
components is not stated either: ``quat_order`` ('xyzw', the ROS order, or 'wxyz') selects it, and
every quaternion must be of unit norm (a wrong column count or order usually fails that check).

Frames (``T_a_b`` maps b to a): ground ENU (world), NED (``R_ENU_NED``); vehicle and base are FLU,
base shifted vertically from the vehicle (``T_vehicle_base``, published with the dataset, identity by
default); camera is the OpenCV optical frame (x right, y down, z forward). The gimbal frame is taken
as FRD with x along the optical axis, so ``R_gimbal_camera`` (default ``R_GIMBAL_CAMERA``) permutes
the axes.

What works with CLOUD here: the run is **monocular**, so it is *not* a stereo ``FrameSource``
(stereo odometry, teach and repeat need a stereo source and ``open_source`` refuses a CLOUD
folder). ``CloudRun`` gives typed streams, the GPS track in ENU metres relative to the first fix
(WGS84 -> ECEF -> ENU), a vehicle reference trajectory (GPS position + attitude) and the camera
reference trajectory at image times (with the gimbal state) for evaluating localization, and the
left images as a ``Sequence`` of ``MonoImage``.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import cv2
import numpy as np
from numpy.typing import ArrayLike

from ..errors import DataError
from .base import GroundTruth

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
STREAM_COLUMNS = {"velocities": 3, "attitude": 4, "acceleration": 3, "gps": 3, "gimbal_state": 7,
                  "gimbal_angles": 3}
QUAT_ORDERS = ("xyzw", "wxyz")
#: a quaternion whose norm differs from 1 by more than this is a malformed row
QUAT_NORM_TOL = 1e-3
MONO16_SHIFT = 8  # 16-bit images -> 8 bit by keeping the high byte
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pgm", ".bmp", ".tif", ".tiff")

# WGS84 ellipsoid
WGS84_A = 6378137.0  # semi-major axis (m)
WGS84_F = 1.0 / 298.257223563  # flattening
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)  # first eccentricity squared
ECEF_TO_GEODETIC_ITERATIONS = 8  # fixed-point iterations; converge to < 1e-9 m near the surface

#: R_enu_ned (its own inverse)
R_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: R_flu_frd: vehicle FLU <- FRD
R_FLU_FRD = np.diag([1.0, -1.0, -1.0])
#: R_gimbal_camera: gimbal FRD (x along the optical axis) <- camera optical (x right, y down, z forward)
R_GIMBAL_CAMERA = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def _transform() -> Any:
    """``scipy.spatial.transform``, imported on first use (~0.3 s: not on the path of other formats)."""
    from scipy.spatial import transform

    return transform


# ---------------------------------------------------------------------------------------------
# geodesy


def geodetic_to_ecef(lat_deg: ArrayLike, lon_deg: ArrayLike, alt_m: ArrayLike) -> np.ndarray:
    """WGS84 latitude/longitude (deg) and ellipsoidal height (m) -> ECEF (N, 3) in metres."""
    lat, lon = np.radians(np.asarray(lat_deg, float)), np.radians(np.asarray(lon_deg, float))
    h = np.asarray(alt_m, float)
    sl = np.sin(lat)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * sl**2)  # prime vertical radius of curvature
    x = (n + h) * np.cos(lat) * np.cos(lon)
    y = (n + h) * np.cos(lat) * np.sin(lon)
    z = (n * (1.0 - WGS84_E2) + h) * sl
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def ecef_to_geodetic(p_ecef: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ECEF (N, 3) m -> WGS84 latitude (deg), longitude (deg), ellipsoidal height (m)."""
    p = np.asarray(p_ecef, float)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    lon = np.arctan2(y, x)
    r = np.hypot(x, y)
    lat = np.arctan2(z, r * (1.0 - WGS84_E2))
    h = np.zeros_like(lat)
    for _ in range(ECEF_TO_GEODETIC_ITERATIONS):
        n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
        h = r / np.cos(lat) - n
        lat = np.arctan2(z, r * (1.0 - WGS84_E2 * n / (n + h)))
    return np.degrees(lat), np.degrees(lon), h


def R_enu_ecef(lat0_deg: float, lon0_deg: float) -> np.ndarray:
    """Rotation ECEF -> local ENU at the given geodetic origin."""
    lat, lon = np.radians(lat0_deg), np.radians(lon0_deg)
    sl, cl, sp, cp = np.sin(lon), np.cos(lon), np.sin(lat), np.cos(lat)
    return np.array([[-sl, cl, 0.0], [-sp * cl, -sp * sl, cp], [cp * cl, cp * sl, sp]])


def geodetic_to_enu(lat_deg: ArrayLike, lon_deg: ArrayLike, alt_m: ArrayLike, lat0_deg: float, lon0_deg: float,
                    alt0_m: float) -> np.ndarray:
    """WGS84 fixes -> ENU positions (N, 3) in metres relative to the origin fix (exact, no flat-earth)."""
    d = geodetic_to_ecef(lat_deg, lon_deg, alt_m) - geodetic_to_ecef(lat0_deg, lon0_deg, alt0_m)
    return d @ R_enu_ecef(lat0_deg, lon0_deg).T


def enu_to_geodetic(p_enu: np.ndarray, lat0_deg: float, lon0_deg: float,
                    alt0_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ENU positions (N, 3) m relative to an origin fix -> WGS84 latitude, longitude (deg), height (m)."""
    p = geodetic_to_ecef(lat0_deg, lon0_deg, alt0_m) + np.asarray(p_enu, float) @ R_enu_ecef(lat0_deg, lon0_deg)
    return ecef_to_geodetic(p)


# ---------------------------------------------------------------------------------------------
# gimbal


def vehicle_yaw_ned(R_enu_vehicle: np.ndarray) -> np.ndarray:
    """Heading (rad, ZYX yaw of the vehicle FRD frame in NED, clockwise from north) of (..., 3, 3)."""
    R = R_ENU_NED @ np.asarray(R_enu_vehicle) @ R_FLU_FRD  # R_ned_frd (R_ENU_NED is its own inverse)
    return np.arctan2(R[..., 1, 0], R[..., 0, 0])


def rotation_from_gimbal_angles(roll: ArrayLike, pitch: ArrayLike, yaw_rel: ArrayLike, R_enu_vehicle: np.ndarray,
                                R_vehicle_base: np.ndarray | None = None,
                                R_gimbal_camera: np.ndarray = R_GIMBAL_CAMERA) -> np.ndarray:
    """``R_base_camera`` (N, 3, 3) from gimbal angles (rad; roll/pitch w.r.t. NED, yaw relative to the
    vehicle heading) and the vehicle attitude ``R_enu_vehicle`` (N, 3, 3) at the same times."""
    R_enu_vehicle = np.asarray(R_enu_vehicle, float).reshape(-1, 3, 3)
    psi = vehicle_yaw_ned(R_enu_vehicle) + np.asarray(yaw_rel, float)
    ang = np.stack(np.broadcast_arrays(psi, np.asarray(pitch, float), np.asarray(roll, float)), axis=-1)
    R_ned_gimbal = _transform().Rotation.from_euler("ZYX", ang.reshape(-1, 3)).as_matrix()
    R_vb = np.eye(3) if R_vehicle_base is None else np.asarray(R_vehicle_base, float)
    R_vehicle_camera = np.swapaxes(R_enu_vehicle, -1, -2) @ R_ENU_NED @ R_ned_gimbal @ R_gimbal_camera
    return R_vb.T @ R_vehicle_camera


def gimbal_angles_from_rotation(R_base_camera: np.ndarray, R_enu_vehicle: np.ndarray,
                                R_vehicle_base: np.ndarray | None = None,
                                R_gimbal_camera: np.ndarray = R_GIMBAL_CAMERA,
                                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of ``rotation_from_gimbal_angles``: (roll, pitch, yaw_rel) in rad, yaw wrapped to (-pi, pi]."""
    R_enu_vehicle = np.asarray(R_enu_vehicle, float).reshape(-1, 3, 3)
    R_vb = np.eye(3) if R_vehicle_base is None else np.asarray(R_vehicle_base, float)
    R_ned_gimbal = R_ENU_NED @ R_enu_vehicle @ R_vb @ np.asarray(R_base_camera, float) @ R_gimbal_camera.T
    psi, pitch, roll = _transform().Rotation.from_matrix(R_ned_gimbal.reshape(-1, 3, 3)).as_euler("ZYX").T
    yaw_rel = np.angle(np.exp(1j * (psi - vehicle_yaw_ned(R_enu_vehicle))))
    return roll, pitch, yaw_rel


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
        return _transform().Rotation.from_quat(self.quat_xyzw).as_matrix()

    def at(self, t_ns: np.ndarray) -> np.ndarray:
        """``R_enu_vehicle`` slerped at times inside the stream's span (N, 3, 3)."""
        return _slerp(self.t_ns, _transform().Rotation.from_quat(self.quat_xyzw), np.asarray(t_ns, np.int64))


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
    return _transform().Slerp((t - t0).astype(float), rots)((tq - t0).astype(float)).as_matrix()


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
            raise DataError(f"{path}:{lineno}: expected {ncols + 1} comma-separated values (timestamp and "
                            f"{ncols}), got {len(parts)}: {s!r}")
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
        "run's images, GPS/attitude reference trajectory and gimbal state (localization evaluation).")


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

    def __init__(self, path: str | Path, quat_order: str = "xyzw", T_vehicle_base: np.ndarray | None = None,
                 R_gimbal_camera: np.ndarray = R_GIMBAL_CAMERA):
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
            raise DataError(f"{self.path / STREAM_FILES[name][0]}: missing CLOUD {name} stream "
                            f"(accepted names: {', '.join(STREAM_FILES[name])})")
        return f

    def missing_streams(self) -> list[str]:
        """Names of the streams without a file in the folder."""
        return [n for n in STREAM_FILES if find_stream(self.path, n) is None]

    def validate(self) -> None:
        """Parse every stream and check every image id resolves to a file; raise on the first problem."""
        missing = self.missing_streams()
        if missing:
            raise DataError(f"{self.path}: missing CLOUD stream(s): "
                            + ", ".join(STREAM_FILES[n][0] for n in missing))
        _ = self.images
        for read in (self.velocities, self.acceleration, self.attitude, self.gps, self.gimbal_state,
                     self.gimbal_angles):
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
            raise DataError(f"{f}:{lines[bad[0]]}: quaternion norm {norm[bad[0]]:.6f} is not 1 "
                            f"(malformed row or wrong quat_order {self.quat_order!r})")
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
        T[:, :3, :3] = _transform().Rotation.from_quat(q).as_matrix()
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
        R = rotation_from_gimbal_angles(ga.roll[keep], ga.pitch[keep], ga.yaw[keep], att.at(ga.t_ns[keep]),
                                        self.T_vehicle_base[:3, :3], self.R_gimbal_camera)
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
                    raise DataError(f"{self.stream_path('image_ids')}: row {k + 1} (image id {i!r}): no such "
                                    f"image in {folder}")
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
        T_bc[:, :3, :3] = _slerp(gs.t_ns, _transform().Rotation.from_matrix(gs.T_base_camera[:, :3, :3]), tq)
        T_bc[:, :3, 3] = _interp(gs.t_ns, gs.T_base_camera[:, :3, 3], tq)
        return GroundTruth(tq, T_ev @ self.T_vehicle_base @ T_bc)

    def ground_truth(self) -> GroundTruth:
        """Camera reference trajectory at the image times (same as ``camera_trajectory()``)."""
        return self.camera_trajectory()


# ---------------------------------------------------------------------------------------------
# writer (synthetic runs for tests and tools)


class CloudRunWriter:
    """Writes a CLOUD run folder with the layout ``CloudRun`` reads (first accepted file names)."""

    def __init__(self, path: str | Path, quat_order: str = "xyzw"):
        if quat_order not in QUAT_ORDERS:
            raise DataError(f"quat_order {quat_order!r}: one of {', '.join(QUAT_ORDERS)}")
        self.path = Path(path)
        (self.path / IMAGES_DIR).mkdir(parents=True, exist_ok=True)
        self.quat_order = quat_order

    def _write(self, name: str, t_ns: ArrayLike, cols: Sequence[ArrayLike], fmt: str) -> Path:
        f = self.path / STREAM_FILES[name][0]
        t_ns = np.asarray(t_ns, np.int64)
        vals = np.column_stack([np.asarray(c, float) for c in cols])
        with open(f, "w") as fh:
            for t, row in zip(t_ns, vals, strict=True):
                fh.write(f"{int(t)}," + ",".join(fmt % x for x in row) + "\n")
        return f

    def _q(self, R: ArrayLike) -> np.ndarray:
        q = _transform().Rotation.from_matrix(np.asarray(R, float).reshape(-1, 3, 3)).as_quat()
        return q[:, [3, 0, 1, 2]] if self.quat_order == "wxyz" else q

    def write_images(self, t_ns: np.ndarray, images: Sequence[np.ndarray], ext: str = ".png") -> None:
        """``images/NNNNNN<ext>`` and the image-id stream (ids without extension)."""
        ids = []
        for k, img in enumerate(images):
            ids.append(f"{k:06d}")
            cv2.imwrite(str(self.path / IMAGES_DIR / f"{ids[-1]}{ext}"), img)
        with open(self.path / STREAM_FILES["image_ids"][0], "w") as fh:
            for t, i in zip(np.asarray(t_ns, np.int64), ids, strict=True):
                fh.write(f"{int(t)},{i}\n")

    def write_velocities(self, t_ns: ArrayLike, v_enu: ArrayLike) -> None:
        """Velocity (m/s) in ground ENU."""
        self._write("velocities", t_ns, list(np.asarray(v_enu, float).T), "%.9f")

    def write_acceleration(self, t_ns: ArrayLike, a_vehicle: ArrayLike) -> None:
        """Specific force (m/s^2) in vehicle FLU."""
        self._write("acceleration", t_ns, list(np.asarray(a_vehicle, float).T), "%.9f")

    def write_attitude(self, t_ns: ArrayLike, R_enu_vehicle: ArrayLike) -> None:
        """Attitude rotations vehicle FLU -> ENU (N, 3, 3)."""
        self._write("attitude", t_ns, list(self._q(R_enu_vehicle).T), "%.12f")

    def write_gps(self, t_ns: ArrayLike, lat_deg: ArrayLike, lon_deg: ArrayLike, alt_m: ArrayLike) -> None:
        """WGS84 fixes (deg, deg, m)."""
        self._write("gps", t_ns, [lat_deg, lon_deg, alt_m], "%.12f")

    def write_gimbal_state(self, t_ns: ArrayLike, T_base_camera: ArrayLike) -> None:
        """Camera poses on the base (N, 4, 4)."""
        T = np.asarray(T_base_camera, float).reshape(-1, 4, 4)
        self._write("gimbal_state", t_ns, [*T[:, :3, 3].T, *self._q(T[:, :3, :3]).T], "%.12f")

    def write_gimbal_angles(self, t_ns: ArrayLike, roll: ArrayLike, pitch: ArrayLike, yaw: ArrayLike) -> None:
        """Gimbal angles given in rad, written in degrees."""
        self._write("gimbal_angles", t_ns, [np.degrees(roll), np.degrees(pitch), np.degrees(yaw)], "%.9f")
