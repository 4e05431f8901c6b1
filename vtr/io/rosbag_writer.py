"""Writing stereo pairs as ROS 1 / ROS 2 / MCAP bags (the reader is ``rosbag``)."""

from __future__ import annotations

import struct
from binascii import crc32
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ..camera import StereoCamera
from ..conventions import NS_PER_S
from ..errors import DataError
from ..types import StereoImages
from .outputs import check_new_output
from .ros_messages import (
    _COMPRESSED_FORMATS,
    _MONO8,
    _MONO16,
    COMPRESSED_MSGTYPE,
    IMAGE_MSGTYPE,
    INFO_MSGTYPE,
    TF_MSGTYPE,
    TF_STATIC_TOPIC,
    CameraInfoData,
)
from .rosbag import BAG_KINDS, ROS1_SUFFIX, ROS2_BAG_VERSION


@dataclass(frozen=True)
class BagTopics:
    """Topic names written by ``RosbagWriter``."""

    left: str = "/stereo/left/image_raw"
    right: str = "/stereo/right/image_raw"
    left_info: str = "/stereo/left/camera_info"
    right_info: str = "/stereo/right/camera_info"


class RosbagWriter:
    """Writes stereo pairs as a ROS 1 bag (``kind='rosbag1'``, ``path`` a ``.bag`` file) or a ROS 2 bag
    folder (``'rosbag2'`` sqlite3 storage, ``'mcap'``), one Image + CameraInfo per camera per frame.

    ``encoding``: ``mono8`` (uint8 (H, W); lossless, the default), ``mono16`` (uint16 (H, W)),
    ``bgr8``/``rgb8`` (uint8 (H, W, 3) in that channel order), or ``png``/``jpeg`` (CompressedImage).
    ``camera`` gives rectified CameraInfos (D = 0, R = I); ``infos`` overrides them (e.g. with raw
    calibrations). When ``write_tf``, ``/tf_static`` holds ``T_base_left`` (``base_frame`` <- left
    optical frame; default ``camera.T_vehicle_sensor``). ``add`` writes a pair; ``add_image`` writes
    one camera's image (and CameraInfo), for bags whose cameras are not paired one to one.
    """

    def __init__(
        self,
        path: str | Path,
        camera: StereoCamera,
        kind: str = "rosbag1",
        topics: BagTopics | None = None,
        encoding: str = "mono8",
        infos: tuple[CameraInfoData, CameraInfoData] | None = None,
        write_info: bool = True,
        write_tf: bool = True,
        base_frame: str = "base_link",
        T_base_left: np.ndarray | None = None,
    ):
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # rosbags only when a bag is written

        if kind not in BAG_KINDS:
            raise DataError(f"unknown bag kind {kind!r} (one of {', '.join(BAG_KINDS)})")
        if encoding not in (*_MONO8[:1], *_MONO16[:1], "bgr8", "rgb8", *_COMPRESSED_FORMATS):
            raise DataError(f"encoding {encoding!r} not supported for writing")
        self.path = Path(path)
        check_new_output(self.path, can_force=False)  # the rule's owner: nothing is replaced, no link followed
        if kind == "rosbag1" and self.path.suffix != ROS1_SUFFIX:
            raise DataError(f"{self.path}: a ROS 1 bag file name must end in {ROS1_SUFFIX}")
        self.kind, self.encoding, self.camera = kind, encoding, camera
        self.topics = topics or BagTopics()
        self.infos = infos or CameraInfoData.from_stereo(camera)
        self.write_info, self.write_tf, self.base_frame = write_info, write_tf, base_frame
        self.T_base_left = np.asarray(camera.T_vehicle_sensor if T_base_left is None else T_base_left, float)
        self.ros2 = kind != "rosbag1"
        if self.ros2:
            from rosbags.rosbag2 import StoragePlugin, Writer

            self.ts = get_typestore(Stores.ROS2_HUMBLE)
            plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
            self._writer: Any = Writer(self.path, version=ROS2_BAG_VERSION, storage_plugin=plugin)  # type: ignore[arg-type]
            self._serialize: Any = self.ts.serialize_cdr
        else:
            from rosbags.rosbag1 import Writer  # type: ignore[assignment]

            self.ts = get_typestore(Stores.ROS1_NOETIC)
            if TF_MSGTYPE not in self.ts.types:
                self.ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF_MSGTYPE))
            self._writer = Writer(self.path)  # type: ignore[call-arg]
            self._serialize = self.ts.serialize_ros1
        self._writer.open()
        img_type = COMPRESSED_MSGTYPE if encoding in _COMPRESSED_FORMATS else IMAGE_MSGTYPE
        self._img_type = img_type
        add = self._writer.add_connection
        self._conn = {
            "left": add(self.topics.left, img_type, typestore=self.ts),
            "right": add(self.topics.right, img_type, typestore=self.ts),
        }
        if write_info:
            self._conn["left_info"] = add(self.topics.left_info, INFO_MSGTYPE, typestore=self.ts)
            self._conn["right_info"] = add(self.topics.right_info, INFO_MSGTYPE, typestore=self.ts)
        if write_tf:
            self._conn["tf"] = add(TF_STATIC_TOPIC, TF_MSGTYPE, typestore=self.ts)
        self.count = 0
        self._messages = 0
        self._closed = False

    def _header(self, t_ns: int, frame_id: str) -> Any:
        T = self.ts.types
        stamp = T["builtin_interfaces/msg/Time"](sec=t_ns // NS_PER_S, nanosec=t_ns % NS_PER_S)
        if self.ros2:
            return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)
        return T["std_msgs/msg/Header"](seq=self._messages, stamp=stamp, frame_id=frame_id)

    def _image_msg(self, t_ns: int, img: np.ndarray, frame_id: str) -> Any:
        T = self.ts.types
        img = np.asarray(img)
        header = self._header(t_ns, frame_id)
        if self.encoding in _COMPRESSED_FORMATS:
            ok, buf = cv2.imencode("." + ("jpg" if self.encoding == "jpeg" else "png"), img)
            if not ok:
                raise DataError(f"cannot encode image as {self.encoding}")
            return T[COMPRESSED_MSGTYPE](header=header, format=self.encoding, data=buf.ravel())
        want = {"mono8": (np.uint8, 2), "mono16": (np.uint16, 2), "bgr8": (np.uint8, 3), "rgb8": (np.uint8, 3)}
        dtype, ndim = want[self.encoding]
        if img.dtype != dtype or img.ndim != ndim or (ndim == 3 and img.shape[2] != 3):
            raise DataError(
                f"{self.encoding} needs a {np.dtype(dtype).name} image with {ndim} dims, got {img.dtype} {img.shape}"
            )
        h, w = img.shape[:2]
        if (w, h) != (self.infos[0].width, self.infos[0].height):
            raise DataError(f"image is {w}x{h} but the calibration says {self.infos[0].width}x{self.infos[0].height}")
        img = np.ascontiguousarray(img)
        if img.dtype == np.uint16:
            img = img.astype("<u2")
        data = img.reshape(-1).view(np.uint8)
        return T[IMAGE_MSGTYPE](
            header=header, height=h, width=w, encoding=self.encoding, is_bigendian=0, step=data.size // h, data=data
        )

    def _info_msg(self, t_ns: int, info: CameraInfoData) -> Any:
        T = self.ts.types
        roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        mats = {
            "d": np.asarray(info.D, float),
            "k": np.asarray(info.K, float).ravel(),
            "r": np.asarray(info.R, float).ravel(),
            "p": np.asarray(info.P, float).ravel(),
        }
        if not self.ros2:
            mats = {k.upper(): v for k, v in mats.items()}
        return T[INFO_MSGTYPE](
            header=self._header(t_ns, info.frame_id),
            height=info.height,
            width=info.width,
            distortion_model=info.distortion_model,
            binning_x=0,
            binning_y=0,
            roi=roi,
            **mats,
        )

    def _tf_msg(self, t_ns: int) -> Any:
        T = self.ts.types
        Tm = self.T_base_left
        q = Rotation.from_matrix(Tm[:3, :3]).as_quat()
        tr = T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=Tm[0, 3], y=Tm[1, 3], z=Tm[2, 3]),
            rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        )
        ts = T["geometry_msgs/msg/TransformStamped"](
            header=self._header(t_ns, self.base_frame), child_frame_id=self.infos[0].frame_id, transform=tr
        )
        return T[TF_MSGTYPE](transforms=[ts])

    def _write(self, key: str, t_ns: int, msg: Any) -> None:
        conn = self._conn[key]
        self._writer.write(conn, t_ns, self._serialize(msg, conn.msgtype))

    def add_image(self, side: str, t_ns: int, img: np.ndarray) -> None:
        """Write one image of camera ``side`` ('left' or 'right') stamped ``t_ns`` (int64 ns >= 0; header
        stamp and bag log time), preceded by its CameraInfo."""
        t_ns = int(t_ns)
        if side not in ("left", "right"):
            raise DataError(f"side must be 'left' or 'right', got {side!r}")
        if t_ns < 0:
            raise DataError(f"cannot write negative time {t_ns} ns to a bag")
        if self._messages == 0 and self.write_tf:
            self._write("tf", t_ns, self._tf_msg(t_ns))
        info = self.infos[0 if side == "left" else 1]
        if self.write_info:
            self._write(f"{side}_info", t_ns, self._info_msg(t_ns, info))
        self._write(side, t_ns, self._image_msg(t_ns, img, info.frame_id))
        self._messages += 1

    def add(self, t_ns: int, left: np.ndarray, right: np.ndarray) -> None:
        """Write one stereo pair, both images stamped ``t_ns``."""
        self.add_image("left", t_ns, left)
        self.add_image("right", t_ns, right)
        self.count += 1

    def close(self) -> None:
        """Finish the bag (writes its index / metadata)."""
        if not self._closed:
            self._closed = True
            self._writer.close()
            if self.kind == "mcap":
                add_mcap_chunk_crcs(self.path / f"{self.path.name}.mcap")

    def __enter__(self) -> RosbagWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


#: MCAP record opcodes and layout this module reads (https://mcap.dev/spec): magic, Chunk and DataEnd records.
MCAP_MAGIC = b"\x89MCAP0\r\n"
_MCAP_CHUNK, _MCAP_DATA_END = 0x06, 0x0F
_CHUNK_CRC_AT = 24  # the uncompressed CRC follows start time, end time and uncompressed size


def add_mcap_chunk_crcs(path: Path) -> int:
    """Fill in the CRC-32 of every uncompressed chunk of the MCAP file ``path`` (rosbags writes 0: "no check"),
    so that a reader detects a damaged chunk instead of decoding other bytes, then the data section's CRC-32 in
    its DataEnd record (every byte from the leading magic up to DataEnd, as the MCAP libraries check it);
    returns the number of chunks. Compressed chunks keep their CRC (vtr writes none)."""

    n = 0
    with open(path, "r+b") as f:
        data = bytearray(f.read())
        if not data.startswith(MCAP_MAGIC):
            raise DataError(f"{path}: not an MCAP file (no magic)")
        pos = len(MCAP_MAGIC)
        while pos + 9 <= len(data):
            op = data[pos]
            (length,) = struct.unpack_from("<Q", data, pos + 1)
            body = pos + 9
            if op == _MCAP_DATA_END:
                f.seek(body)
                f.write(struct.pack("<I", crc32(data[:pos])))
                break
            if op == _MCAP_CHUNK:
                (name_len,) = struct.unpack_from("<I", data, body + 28)
                compression = data[body + 32 : body + 32 + name_len]
                records_at = body + 32 + name_len + 8
                (size,) = struct.unpack_from("<Q", data, records_at - 8)
                if compression == b"":
                    struct.pack_into("<I", data, body + _CHUNK_CRC_AT, crc32(data[records_at : records_at + size]))
                    f.seek(body + _CHUNK_CRC_AT)
                    f.write(data[body + _CHUNK_CRC_AT : body + _CHUNK_CRC_AT + 4])
                    n += 1
            pos = body + length
    return n


def write_bag(
    path: str | Path, frames: Iterable[StereoImages], camera: StereoCamera, kind: str = "rosbag1", **kwargs: Any
) -> int:
    """Write ``frames`` to a new bag; returns the number of frames written."""
    with RosbagWriter(path, camera, kind=kind, **kwargs) as w:
        for f in frames:
            w.add(f.t_ns, f.left, f.right)
        return w.count
