"""ROS messages a stereo bag carries, as ``vtr`` reads and writes them: the message types, ``CameraInfo`` as
:class:`CameraInfoData` with the rectified :class:`~vtr.camera.StereoCamera` it gives and the check that it is a
real lens, rectification maps for raw images, ``header.stamp`` from the serialized bytes and images decoded to
8-bit grey (docs/inputs.md, "ROS bags")."""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ..camera import StereoCamera
from ..conventions import NS_PER_S
from ..errors import CalibrationError, DataError

IMAGE_MSGTYPE = "sensor_msgs/msg/Image"
COMPRESSED_MSGTYPE = "sensor_msgs/msg/CompressedImage"
IMAGE_MSGTYPES = (IMAGE_MSGTYPE, COMPRESSED_MSGTYPE)
INFO_MSGTYPE = "sensor_msgs/msg/CameraInfo"
TF_MSGTYPE = "tf2_msgs/msg/TFMessage"
TF_STATIC_TOPIC = "/tf_static"

#: mono16 -> mono8 by ``value >> MONO16_SHIFT`` (keep the high byte)
MONO16_SHIFT = 8
#: a distortion coefficient or rotation entry below this is taken as exactly zero / identity
CALIB_EPS = 1e-12

_GREY_FROM = {
    "bgr8": (3, cv2.COLOR_BGR2GRAY),
    "rgb8": (3, cv2.COLOR_RGB2GRAY),
    "bgra8": (4, cv2.COLOR_BGRA2GRAY),
    "rgba8": (4, cv2.COLOR_RGBA2GRAY),
}
_MONO8 = ("mono8", "8uc1")
_MONO16 = ("mono16", "16uc1")
_COMPRESSED_FORMATS = ("png", "jpeg")


# ---------------------------------------------------------------------------------------------
# calibration


@dataclass(frozen=True)
class CameraInfoData:
    """Contents of one ``sensor_msgs/CameraInfo``: image size (px), ``K`` (3x3), ``D`` (distortion
    coefficients of ``distortion_model``), ``R`` (3x3 rotation raw camera -> rectified camera),
    ``P`` (3x4 projection of the rectified camera; ``P[0, 3] = -fx * baseline`` for the right one),
    and the optical ``frame_id`` (x right, y down, z forward)."""

    width: int
    height: int
    K: np.ndarray
    D: np.ndarray
    R: np.ndarray
    P: np.ndarray
    distortion_model: str = "plumb_bob"
    frame_id: str = ""

    @property
    def is_raw(self) -> bool:
        """True when images need undistortion/rectification (non-zero D or R not the identity)."""
        return bool(np.any(np.abs(self.D) > CALIB_EPS) or not np.allclose(self.R, np.eye(3), atol=CALIB_EPS))

    @staticmethod
    def from_stereo(
        camera: StereoCamera, left_frame: str = "camera_left_optical", right_frame: str = "camera_right_optical"
    ) -> tuple[CameraInfoData, CameraInfoData]:
        """CameraInfo of both cameras of a rectified pair (D = 0, R = I, P from K and the baseline)."""
        P = np.hstack([camera.K, np.zeros((3, 1))])
        P_right = P.copy()
        P_right[0, 3] = -camera.fb
        common: dict[str, Any] = dict(width=camera.width, height=camera.height, K=camera.K, D=np.zeros(5), R=np.eye(3))
        return (
            CameraInfoData(P=P, frame_id=left_frame, **common),
            CameraInfoData(P=P_right, frame_id=right_frame, **common),
        )


def stereo_camera_from_info(
    left: CameraInfoData, right: CameraInfoData, where: str, T_vehicle_sensor: np.ndarray | None = None
) -> StereoCamera:
    """Rectified ``StereoCamera`` from the two CameraInfos (intrinsics of P, baseline from the right P)."""
    if (left.width, left.height) != (right.width, right.height):
        raise CalibrationError(
            f"{where}: left CameraInfo is {left.width}x{left.height} but right is {right.width}x{right.height}"
        )
    Pl, Pr = left.P, right.P
    if Pr[0, 0] <= 0 or not np.all(np.isfinite(Pr)):
        raise CalibrationError(f"{where}: right CameraInfo has no projection matrix P (uncalibrated camera?)")
    if not np.allclose(Pl[:, :3], Pr[:, :3], rtol=1e-6, atol=1e-6):
        raise CalibrationError(
            f"{where}: left and right CameraInfo P have different intrinsics (not a rectified stereo pair)"
        )
    baseline = -Pr[0, 3] / Pr[0, 0]
    if baseline <= 0:
        raise CalibrationError(
            f"{where}: right CameraInfo P[0,3] = {Pr[0, 3]} gives baseline {baseline} m "
            "(must be > 0: are left and right swapped?)"
        )
    return StereoCamera(
        fx=Pr[0, 0],
        fy=Pr[1, 1],
        cx=Pr[0, 2],
        cy=Pr[1, 2],
        baseline=baseline,
        width=left.width,
        height=left.height,
        T_vehicle_sensor=np.eye(4) if T_vehicle_sensor is None else T_vehicle_sensor,
    )


#: coefficients each distortion model may have (ROS: plumb_bob 5, rational_polynomial 8, equidistant 4)
DISTORTION_COUNTS = {
    "plumb_bob": (4, 5, 8),
    "radtan": (4, 5),
    "rational_polynomial": (8, 12, 14),
    "equidistant": (4,),
    "fisheye": (4,),
    "": (0, 4, 5, 8),
}


MIN_CORNER_SCALE, MAX_CORNER_SCALE = 0.05, 20.0  # distorted / undistorted radius at the image corners


def check_distortion(info: CameraInfoData, where: str) -> None:
    """``CalibrationError`` (one line) unless ``K``, ``R`` and ``D`` describe a real lens: finite, a proper
    rotation, a coefficient count of the model, and a distortion that maps the image's field of view one to
    one (the distorted radius grows with the true one out to the image corners; absurd coefficients fold
    the image over, and rectifying with them gives garbage images, not an error)."""
    model = info.distortion_model.lower()
    K, R, D = np.asarray(info.K, float), np.asarray(info.R, float), np.asarray(info.D, float).ravel()
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(R)) and np.all(np.isfinite(D))):
        raise CalibrationError(f"{where}: CameraInfo K, R or D is not finite")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise CalibrationError(f"{where}: CameraInfo K has focal lengths {K[0, 0]:g}, {K[1, 1]:g} (must be > 0)")
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) <= 0:
        raise CalibrationError(f"{where}: CameraInfo R is not a rotation")
    counts = DISTORTION_COUNTS.get(model)
    if counts is not None and len(D) and len(D) not in counts:
        raise CalibrationError(
            f"{where}: distortion model {info.distortion_model!r} takes "
            f"{' or '.join(map(str, counts))} coefficients, CameraInfo D has {len(D)}"
        )
    if not np.any(D):
        return
    # normalized radius of the farthest image corner, sampled from the centre out
    corners = np.array([[0, 0], [info.width, 0], [0, info.height], [info.width, info.height]], float)
    r_max = float(np.max(np.hypot((corners[:, 0] - K[0, 2]) / K[0, 0], (corners[:, 1] - K[1, 2]) / K[1, 1])))
    if model in ("equidistant", "fisheye"):
        theta = np.arctan(np.linspace(0.0, r_max, 400))
        k = np.zeros(4)
        k[: len(D)] = D[:4]
        t2 = theta**2
        r_d = theta * (1 + k[0] * t2 + k[1] * t2**2 + k[2] * t2**3 + k[3] * t2**4)
    else:
        k = np.zeros(14)
        k[: len(D)] = D[:14]
        r = np.linspace(0.0, r_max, 400)
        r2 = r**2
        radial = (1 + k[0] * r2 + k[1] * r2**2 + k[4] * r2**3) / (1 + k[5] * r2 + k[6] * r2**2 + k[7] * r2**3)
        r_d = r * radial
    scale = r_d[-1] / np.tan(theta[-1]) if model in ("equidistant", "fisheye") else radial[-1]
    if np.isfinite(scale) and not MIN_CORNER_SCALE <= scale <= MAX_CORNER_SCALE:
        raise CalibrationError(
            f"{where}: CameraInfo distortion D = {np.array2string(D, precision=4)} scales the "
            f"image corners by {scale:.3g} (a lens stays within {MIN_CORNER_SCALE:g} to "
            f"{MAX_CORNER_SCALE:g}): not a real lens calibration"
        )
    if not np.all(np.isfinite(r_d)) or np.any(np.diff(r_d) <= 0):
        raise CalibrationError(
            f"{where}: CameraInfo distortion D = {np.array2string(D, precision=4)} is not one to "
            "one over the image (the distorted radius stops growing before the corners): not a "
            "real lens calibration"
        )


def rectify_maps(info: CameraInfoData, where: str) -> tuple[np.ndarray, np.ndarray]:
    check_distortion(info, where)
    size = (info.width, info.height)
    model = info.distortion_model.lower()
    if model == "equidistant":
        D = np.zeros(4) if len(info.D) == 0 else np.asarray(info.D[:4], float)
        return cv2.fisheye.initUndistortRectifyMap(info.K, D, info.R, info.P[:3, :3], size, cv2.CV_16SC2)
    if model not in ("plumb_bob", "rational_polynomial", "radtan", ""):
        raise CalibrationError(
            f"{where}: distortion model {info.distortion_model!r} not supported "
            "(plumb_bob, rational_polynomial, equidistant)"
        )
    D = np.asarray(info.D, float) if len(info.D) else np.zeros(5)
    return cv2.initUndistortRectifyMap(info.K, D, info.R, info.P, size, cv2.CV_16SC2)


# ---------------------------------------------------------------------------------------------
# messages


def header_stamp_ns(raw: bytes | memoryview, ros2: bool) -> int:
    """``header.stamp`` (ns) of a serialized message whose first field is a ``std_msgs/Header``.

    ROS 1: ``uint32 seq`` then ``uint32 sec, uint32 nsec``. ROS 2 (CDR): a 4-byte encapsulation
    header (byte 1 odd = little endian) then ``int32 sec, uint32 nanosec``.
    """
    if ros2:
        fmt = "<iI" if raw[1] & 1 else ">iI"
    else:
        fmt = "<II"
    sec, nsec = struct.unpack_from(fmt, raw, 4)
    return sec * NS_PER_S + nsec


def _field(msg: Any, *names: str) -> Any:
    for n in names:
        if hasattr(msg, n):
            return getattr(msg, n)
    raise AttributeError(names[0])


def info_from_msg(msg: Any) -> CameraInfoData:
    return CameraInfoData(
        width=int(msg.width),
        height=int(msg.height),
        K=np.asarray(_field(msg, "k", "K"), float).reshape(3, 3),
        D=np.asarray(_field(msg, "d", "D"), float).ravel(),
        R=np.asarray(_field(msg, "r", "R"), float).reshape(3, 3),
        P=np.asarray(_field(msg, "p", "P"), float).reshape(3, 4),
        distortion_model=str(msg.distortion_model),
        frame_id=str(msg.header.frame_id),
    )


def _to_grey(img: np.ndarray, where: str, mono16_shift: int) -> np.ndarray:
    if img.dtype == np.uint16:
        return np.clip(img >> mono16_shift, 0, 255).astype(np.uint8)
    if img.dtype != np.uint8:
        raise DataError(f"{where}: pixel type {img.dtype} not supported (8 or 16 bit)")
    return img


def decode_image(msg: Any, msgtype: str, where: str, mono16_shift: int = MONO16_SHIFT) -> np.ndarray:
    """8-bit greyscale image (H, W) of an ``Image`` or ``CompressedImage`` message."""
    if msgtype == COMPRESSED_MSGTYPE:
        buf = np.asarray(msg.data, np.uint8)
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
        if img is None:
            raise DataError(f"{where}: cannot decode compressed image (format {msg.format!r})")
        if img.ndim == 3:
            code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
            img = cv2.cvtColor(img, code)
        return _to_grey(img, where, mono16_shift)
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    enc = str(msg.encoding).lower()
    data = np.asarray(msg.data, np.uint8)
    if data.size < h * step or h <= 0 or w <= 0:
        raise DataError(f"{where}: image data has {data.size} bytes, expected {h}x{step} (truncated message?)")
    rows = data[: h * step].reshape(h, step)
    if enc in _MONO8:
        return rows[:, :w].copy()  # own, writable memory (the message buffer is read-only)
    if enc in _MONO16:
        dtype = np.dtype(">u2" if msg.is_bigendian else "<u2")
        img = np.ascontiguousarray(rows[:, : 2 * w]).view(dtype).reshape(h, w).astype(np.uint16)
        return _to_grey(img, where, mono16_shift)
    if enc in _GREY_FROM:
        ch, code = _GREY_FROM[enc]
        return cv2.cvtColor(np.ascontiguousarray(rows[:, : ch * w]).reshape(h, w, ch), code)
    raise DataError(
        f"{where}: image encoding {msg.encoding!r} not supported "
        f"({', '.join((*_MONO8[:1], *_MONO16[:1], *_GREY_FROM))}, or CompressedImage)"
    )
