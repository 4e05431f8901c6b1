"""ROS bags (ROS 1 ``.bag``; ROS 2 ``.db3`` and ``.mcap``) as a stereo ``FrameSource`` through ``rosbags``: which
paths are bags, which topics are the two cameras and their ``CameraInfo``, and :class:`RosbagSource`, which pairs
left and right images by header stamp and streams them without loading the bag (messages and calibration:
:mod:`vtr.io.ros_messages`; the writer: :mod:`vtr.io.rosbag_writer`). Formats, calibration, time and memory:
docs/inputs.md, "ROS bags"."""

from __future__ import annotations

import struct
from array import array
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..errors import CalibrationError, DataError
from ..types import StereoImages
from .base import FrameSource
from .ros_messages import (
    IMAGE_MSGTYPES,
    INFO_MSGTYPE,
    MONO16_SHIFT,
    TF_MSGTYPE,
    TF_STATIC_TOPIC,
    CameraInfoData,
    decode_image,
    header_stamp_ns,
    info_from_msg,
    rectify_maps,
    stereo_camera_from_info,
)

#: left/right images of one stereo pair carry header stamps closer than this (ns)
DEFAULT_PAIR_TOLERANCE_NS = 5_000_000
#: topic-name hints used to detect the left and right cameras
LEFT_HINTS = ("left", "cam0")
RIGHT_HINTS = ("right", "cam1")
#: longest /tf_static chain followed from the camera frame to its root
MAX_TF_DEPTH = 32
#: rosbag2 metadata version written
ROS2_BAG_VERSION = 8
BAG_KINDS = ("rosbag1", "rosbag2", "mcap")
ROS1_SUFFIX = ".bag"
ROS2_STORAGE_SUFFIXES = (".db3", ".mcap")


# ---------------------------------------------------------------------------------------------
# bag paths


def _ros2_dir(path: Path) -> Path | None:
    if path.is_dir() and (path / "metadata.yaml").is_file():
        return path
    return None


def is_rosbag(path: Path) -> bool:
    """True for a ROS 1 ``.bag`` file, a ROS 2 bag folder, or a ``.db3``/``.mcap`` storage file."""
    path = Path(path)
    if path.is_file():
        return path.suffix in (ROS1_SUFFIX, *ROS2_STORAGE_SUFFIXES)
    return _ros2_dir(path) is not None


def bag_reader_path(path: Path) -> Path:
    """The path ``rosbags`` should open: the ROS 2 folder when a storage file sits in one."""
    path = Path(path)
    if path.is_file() and path.suffix in ROS2_STORAGE_SUFFIXES and _ros2_dir(path.parent) is not None:
        meta = (path.parent / "metadata.yaml").read_text(errors="replace")
        if path.name in meta:
            return path.parent
    return path


def _read_errors() -> tuple[type[BaseException], ...]:
    """Exceptions that mean 'this bag is corrupt or truncated' (turned into DataError)."""
    from rosbags.highlevel import AnyReaderError  # rosbags only for a bag, here and below
    from rosbags.rosbag1 import ReaderError as ReaderError1
    from rosbags.rosbag2 import ReaderError as ReaderError2

    errs: list[type[BaseException]] = [
        AnyReaderError,
        ReaderError1,
        ReaderError2,
        OSError,
        EOFError,
        struct.error,
        ValueError,
        KeyError,
        IndexError,
        AssertionError,
    ]
    try:
        import apsw

        errs.append(apsw.Error)
    except ImportError:  # pragma: no cover - apsw ships with rosbags
        pass
    return tuple(errs)


# ---------------------------------------------------------------------------------------------
# topic selection


def _strip_compressed(topic: str) -> str:
    return topic[: -len("/compressed")] if topic.endswith("/compressed") else topic


def _namespace(topic: str) -> str:
    return _strip_compressed(topic).rsplit("/", 1)[0]


def _pick_image_topic(topics: dict[str, str], hints: Sequence[str], side: str, where: str) -> str:
    images = sorted(t for t, ty in topics.items() if ty in IMAGE_MSGTYPES)
    cands = [t for t in images if any(h in t.lower() for h in hints)]
    # image_transport records 'x' and 'x/compressed': prefer the uncompressed one
    cands = [t for t in cands if not (t.endswith("/compressed") and _strip_compressed(t) in cands)]
    if len(cands) == 1:
        return cands[0]
    what = "several" if cands else "no"
    raise DataError(
        f"{where}: {what} {side} image topic{'s' if cands else ''} found "
        f"({', '.join(cands) if cands else 'names containing ' + '/'.join(hints)}); image topics "
        f"in the bag: {', '.join(images) or 'none'}; pass {side}_topic (CLI --{side}-topic)"
    )


def _pick_info_topic(topics: dict[str, str], image_topic: str, hints: Sequence[str], side: str, where: str) -> str:
    infos = sorted(t for t, ty in topics.items() if ty == INFO_MSGTYPE)
    ns = _namespace(image_topic)
    same_ns = [t for t in infos if _namespace(t) == ns]
    if len(same_ns) == 1:
        return same_ns[0]
    hinted = [t for t in infos if any(h in t.lower() for h in hints)]
    if len(hinted) == 1:
        return hinted[0]
    raise CalibrationError(
        f"{where}: no unique CameraInfo topic for {side} image topic {image_topic} (CameraInfo topics: "
        f"{', '.join(infos) or 'none'}); stereo calibration needs sensor_msgs/CameraInfo for both cameras; "
        f"pass {side}_info_topic (CLI --{side}-info-topic)"
    )


# ---------------------------------------------------------------------------------------------
# reader


@dataclass
class _Side:
    topic: str
    conn: Any
    msgtype: str
    stamps: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    logs: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


class RosbagSource(FrameSource):
    """Stereo frames of a ROS 1 or ROS 2 bag (see the module docstring for formats and costs).

    ``left_topic``/``right_topic`` (Image or CompressedImage) and ``left_info_topic``/
    ``right_info_topic`` (CameraInfo) are detected when not given: image topics whose name contains
    ``left``/``cam0`` and ``right``/``cam1``, and the CameraInfo topic in the same namespace.
    ``rectify`` forces (True) or skips (False) rectification of raw images; None decides from D/R.
    """

    format_name = "rosbag"

    def __init__(
        self,
        path: str | Path,
        left_topic: str | None = None,
        right_topic: str | None = None,
        left_info_topic: str | None = None,
        right_info_topic: str | None = None,
        pair_tolerance_ns: int = DEFAULT_PAIR_TOLERANCE_NS,
        allow_unpaired: bool = False,
        mono16_shift: int = MONO16_SHIFT,
        rectify: bool | None = None,
    ):
        from rosbags.highlevel import AnyReader  # rosbags only for a bag
        from rosbags.typesys import Stores, get_typestore

        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"{self.path}: no such file or folder")
        if not is_rosbag(self.path):
            raise DataError(
                f"{self.path}: not a ROS bag (.bag file, ROS 2 bag folder with metadata.yaml, .db3 or .mcap)"
            )
        self._errors = _read_errors()
        # opening and indexing also meet MemoryError: a damaged length field asks for absurd buffers
        self._damage_errors: tuple[type[BaseException], ...] = (*self._errors, MemoryError)
        self.mono16_shift = int(mono16_shift)
        self.pair_tolerance_ns = int(pair_tolerance_ns)
        rpath = bag_reader_path(self.path)
        self.ros2 = rpath.suffix != ROS1_SUFFIX
        default = get_typestore(Stores.ROS2_HUMBLE if self.ros2 else Stores.ROS1_NOETIC)
        self._reader: Any = None  # the open AnyReader
        try:
            reader = AnyReader([rpath], default_typestore=default)
            reader.open()
        except FileNotFoundError:
            raise
        except self._damage_errors as err:
            hint = " (a truncated ROS 1 bag can be repaired with `rosbag reindex`)" if not self.ros2 else ""
            if "end magic" in str(err).lower():  # an MCAP file whose end (footer, index) is missing
                hint = (
                    " (the MCAP file does not end as MCAP files do: it was truncated, e.g. a recording or a "
                    "copy cut short; `mcap recover FILE -o FIXED.mcap` of the mcap CLI rebuilds what is readable)"
                )
            reason = (
                "a record length is absurd (damaged file)"
                if isinstance(err, MemoryError)
                else " ".join(str(err).split()) or type(err).__name__
            )
            raise DataError(f"{self.path}: cannot open bag: {reason}{hint}") from err
        self._reader = reader
        try:
            self._setup(left_topic, right_topic, left_info_topic, right_info_topic, allow_unpaired, rectify)
        except BaseException:
            self.close()
            raise

    # -- opening

    def _setup(
        self,
        left_topic: str | None,
        right_topic: str | None,
        left_info_topic: str | None,
        right_info_topic: str | None,
        allow_unpaired: bool,
        rectify: bool | None,
    ) -> None:
        reader = self._reader
        where = str(self.path)
        conns: dict[str, list] = {}
        for c in reader.connections:
            conns.setdefault(c.topic, []).append(c)
        topics = {t: cs[0].msgtype for t, cs in conns.items()}
        self.topics = dict(topics)
        if not any(ty in IMAGE_MSGTYPES for ty in topics.values()):
            listing = ", ".join(f"{t} ({ty})" for t, ty in sorted(topics.items())) or "none"
            raise DataError(f"{where}: no image topic (sensor_msgs/Image or CompressedImage); topics: {listing}")

        def check(topic: str, types: Sequence[str], what: str) -> str:
            if topic not in topics:
                raise DataError(f"{where}: no topic {topic!r} ({what}); topics: {', '.join(sorted(topics))}")
            if topics[topic] not in types:
                raise DataError(f"{where}: topic {topic} is {topics[topic]}, expected {' or '.join(types)}")
            return topic

        lt = (
            check(left_topic, IMAGE_MSGTYPES, "left images")
            if left_topic
            else _pick_image_topic(topics, LEFT_HINTS, "left", where)
        )
        rt = (
            check(right_topic, IMAGE_MSGTYPES, "right images")
            if right_topic
            else _pick_image_topic(topics, RIGHT_HINTS, "right", where)
        )
        if lt == rt:
            raise DataError(f"{where}: left and right image topics are both {lt}")
        lit = (
            check(left_info_topic, (INFO_MSGTYPE,), "left CameraInfo")
            if left_info_topic
            else _pick_info_topic(topics, lt, LEFT_HINTS, "left", where)
        )
        rit = (
            check(right_info_topic, (INFO_MSGTYPE,), "right CameraInfo")
            if right_info_topic
            else _pick_info_topic(topics, rt, RIGHT_HINTS, "right", where)
        )
        if lit == rit:
            raise CalibrationError(f"{where}: left and right CameraInfo topics are both {lit}")
        self.left_topic, self.right_topic = lt, rt
        self.left_info_topic, self.right_info_topic = lit, rit
        for t in (lt, rt):
            if len(conns[t]) > 1 and len({c.msgtype for c in conns[t]}) > 1:
                raise DataError(f"{where}: topic {t} carries several message types")
        self._left = _Side(lt, conns[lt], topics[lt])
        self._right = _Side(rt, conns[rt], topics[rt])

        self.left_info = self._first_info(conns[lit], lit)
        self.right_info = self._first_info(conns[rit], rit)
        raw = self.left_info.is_raw or self.right_info.is_raw if rectify is None else bool(rectify)
        self.rectified_on_load = raw
        T_root_left = self._tf_static_pose(conns, self.left_info.frame_id)
        T_raw_rect = np.eye(4)
        T_raw_rect[:3, :3] = self.left_info.R.T
        self.camera = stereo_camera_from_info(
            self.left_info, self.right_info, f"{where} [{lit}, {rit}]", T_root_left @ T_raw_rect
        )
        self._maps: Any = None
        if raw:
            self._maps = (
                rectify_maps(self.left_info, f"{where} [{lit}]"),
                rectify_maps(self.right_info, f"{where} [{rit}]"),
            )
        self._index(allow_unpaired)

    def _first_info(self, conns: list, topic: str) -> CameraInfoData:
        try:
            for c, _t, raw in self._reader.messages(connections=conns):
                return info_from_msg(self._reader.deserialize(raw, c.msgtype))
        except self._errors as err:
            raise DataError(f"{self.path} [{topic}]: cannot read CameraInfo: {err}") from err
        raise CalibrationError(
            f"{self.path}: CameraInfo topic {topic} has no message; stereo calibration "
            "needs sensor_msgs/CameraInfo for both cameras"
        )

    def _tf_static_pose(self, conns: dict[str, list], frame: str) -> np.ndarray:
        """``T_root_frame`` from /tf_static (identity when absent)."""
        tf_conns = [c for c in conns.get(TF_STATIC_TOPIC, []) if c.msgtype == TF_MSGTYPE]
        if not frame or not tf_conns:
            return np.eye(4)
        parent_of: dict[str, tuple[str, np.ndarray]] = {}
        try:
            for c, _t, raw in self._reader.messages(connections=tf_conns):
                for tr in self._reader.deserialize(raw, c.msgtype).transforms:
                    q, p = tr.transform.rotation, tr.transform.translation
                    T = np.eye(4)
                    from scipy.spatial.transform import Rotation  # here: ~0.3 s to import

                    T[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
                    T[:3, 3] = [p.x, p.y, p.z]
                    parent_of[tr.child_frame_id.lstrip("/")] = (tr.header.frame_id.lstrip("/"), T)
        except self._errors as err:
            raise DataError(f"{self.path} [{TF_STATIC_TOPIC}]: cannot read: {err}") from err
        T = np.eye(4)
        node = frame.lstrip("/")
        for _ in range(MAX_TF_DEPTH):
            if node not in parent_of:
                break
            node, T_parent_child = parent_of[node]
            T = T_parent_child @ T
        return T

    def _index(self, allow_unpaired: bool) -> None:
        """One pass over both image topics keeping header stamps and log times only."""
        stamps = {self.left_topic: array("q"), self.right_topic: array("q")}
        logs = {self.left_topic: array("q"), self.right_topic: array("q")}
        conns = [*self._left.conn, *self._right.conn]
        counted = 0
        try:
            for c, t, raw in self._reader.messages(connections=conns):
                stamps[c.topic].append(header_stamp_ns(raw, self.ros2))
                logs[c.topic].append(t)
                counted += 1
        except self._damage_errors as err:
            raise DataError(
                f"{self.path}: bag is truncated or corrupt: read error after {counted} image "
                f"messages on {self.left_topic}, {self.right_topic}: {err}"
            ) from err
        for s in (self._left, self._right):
            s.stamps = np.frombuffer(stamps[s.topic], np.int64).copy()
            s.logs = np.frombuffer(logs[s.topic], np.int64).copy()
            expected = sum(int(getattr(c, "msgcount", 0) or 0) for c in s.conn)
            if expected and expected != len(s.stamps):
                raise DataError(
                    f"{self.path}: topic {s.topic}: the bag index lists {expected} messages but "
                    f"{len(s.stamps)} could be read (truncated or partial bag)"
                )
            if len(s.stamps) == 0:
                raise DataError(f"{self.path}: image topic {s.topic} has no message")
            order = np.argsort(s.stamps, kind="stable")
            s.stamps, s.logs = s.stamps[order], s.logs[order]
            dup = np.flatnonzero(np.diff(s.stamps) == 0)
            if len(dup):
                raise DataError(f"{self.path}: topic {s.topic} has two images with header stamp {s.stamps[dup[0]]} ns")
        li, ri = _pair(self._left.stamps, self._right.stamps, self.pair_tolerance_ns)
        nl, nr = len(self._left.stamps), len(self._right.stamps)
        self.unpaired = (nl - len(li), nr - len(ri))
        if len(li) == 0:
            raise DataError(
                f"{self.path}: no left image on {self.left_topic} has a right image on "
                f"{self.right_topic} within {self.pair_tolerance_ns} ns"
            )
        if (len(li) != nl or len(ri) != nr) and not allow_unpaired:
            raise DataError(
                f"{self.path}: left topic {self.left_topic} has {nl} images and right topic {self.right_topic} "
                f"has {nr}; only {len(li)} pairs match by header stamp within {self.pair_tolerance_ns} ns "
                "(pass allow_unpaired=True, CLI --allow-unpaired, to use the matched pairs only)"
            )
        self._l_stamp, self._l_log = self._left.stamps[li], self._left.logs[li]
        self._r_stamp, self._r_log = self._right.stamps[ri], self._right.logs[ri]
        self._t_ns = self._l_stamp.copy()

    # -- FrameSource

    def __len__(self) -> int:
        return len(self._t_ns)

    def timestamps(self) -> np.ndarray:
        return self._t_ns

    def _decode(self, side: _Side, raw: bytes, index: int) -> np.ndarray:
        where = f"{self.path} [{side.topic} frame {index}]"
        try:
            msg = self._reader.deserialize(raw, side.msgtype)
        except self._errors as err:
            raise DataError(f"{where}: corrupt message: {err}") from err
        return self.check_image(decode_image(msg, side.msgtype, where, self.mono16_shift), where)

    def _pair_images(self, index: int, raw_left: bytes, raw_right: bytes) -> StereoImages:
        left = self._decode(self._left, raw_left, index)
        right = self._decode(self._right, raw_right, index)
        if self._maps is not None:
            left = cv2.remap(left, *self._maps[0], cv2.INTER_LINEAR)  # type: ignore[call-overload]
            right = cv2.remap(right, *self._maps[1], cv2.INTER_LINEAR)  # type: ignore[call-overload]
        return StereoImages(int(self._t_ns[index]), index, left, right)

    def _read_one(self, side: _Side, log_ns: int, stamp_ns: int, index: int) -> bytes:
        try:
            for _c, _t, raw in self._reader.messages(connections=side.conn, start=log_ns, stop=log_ns + 1):
                if header_stamp_ns(raw, self.ros2) == stamp_ns:
                    return raw
        except self._errors as err:
            raise DataError(f"{self.path} [{side.topic} frame {index}]: read error: {err}") from err
        raise DataError(
            f"{self.path} [{side.topic}]: message of frame {index} (stamp {stamp_ns} ns) "
            "not found on re-read (bag changed or corrupt)"
        )

    def _load(self, index: int) -> StereoImages:
        self._check_open()
        raw_l = self._read_one(self._left, int(self._l_log[index]), int(self._l_stamp[index]), index)
        raw_r = self._read_one(self._right, int(self._r_log[index]), int(self._r_stamp[index]), index)
        return self._pair_images(index, raw_l, raw_r)

    def __iter__(self) -> Iterator[StereoImages]:
        return self.iter_frames()

    def iter_frames(self, indices: Iterable[int] | None = None) -> Iterator[StereoImages]:
        """Stream frames (all, or the given increasing ``indices``) in one sequential pass."""
        self._check_open()
        sel = list(range(len(self))) if indices is None else [int(i) for i in indices]
        if not sel:
            return
        if any(not 0 <= i < len(self) for i in sel):
            raise IndexError(f"frame index outside {self.path} ({len(self)} frames)")
        if any(b <= a for a, b in zip(sel, sel[1:], strict=False)):
            # not increasing: random access per frame
            for i in sel:
                yield self._load(i)
            return
        want = {
            self.left_topic: {int(self._l_stamp[i]): i for i in sel},
            self.right_topic: {int(self._r_stamp[i]): i for i in sel},
        }
        idx = np.asarray(sel)
        start = int(min(self._l_log[idx].min(), self._r_log[idx].min()))
        stop = int(max(self._l_log[idx].max(), self._r_log[idx].max())) + 1
        pending: dict[int, list] = {}
        pos = 0
        try:
            for c, _t, raw in self._reader.messages(
                connections=[*self._left.conn, *self._right.conn], start=start, stop=stop
            ):
                k = want[c.topic].get(header_stamp_ns(raw, self.ros2))
                if k is None:
                    continue
                slot = pending.setdefault(k, [None, None])
                slot[0 if c.topic == self.left_topic else 1] = raw
                while pos < len(sel) and sel[pos] in pending and None not in pending[sel[pos]]:
                    raw_l, raw_r = pending.pop(sel[pos])
                    frame = self._pair_images(sel[pos], raw_l, raw_r)
                    pos += 1
                    yield frame
        except self._errors as err:
            raise DataError(
                f"{self.path}: read error after {pos} of {len(sel)} frames (truncated or corrupt bag): {err}"
            ) from err
        if pos < len(sel):
            raise DataError(
                f"{self.path}: bag ended after {pos} of {len(sel)} frames: frame {sel[pos]} "
                f"(t {int(self._t_ns[sel[pos]])} ns) is missing its left or right image"
            )

    def _check_open(self) -> None:
        if self._reader is None:
            raise DataError(f"{self.path}: source is closed")

    def close(self) -> None:
        reader, self._reader = self._reader, None
        if reader is not None:
            try:
                reader.close()
            except Exception:  # noqa: BLE001 - closing a broken reader must not mask the first error
                pass


def _pair(tl: np.ndarray, tr: np.ndarray, tol: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices (into sorted ``tl``, ``tr``) of mutually nearest stamps closer than ``tol`` ns."""

    def nearest(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        if len(b) == 1:
            return np.zeros(len(a), np.int64)
        j = np.clip(np.searchsorted(b, a), 1, len(b) - 1)
        return np.where(np.abs(b[j - 1] - a) <= np.abs(b[j] - a), j - 1, j)

    jl = nearest(tl, tr)
    jr = nearest(tr, tl)
    i = np.arange(len(tl))
    ok = (np.abs(tr[jl] - tl) <= tol) & (jr[jl] == i)
    return i[ok], jl[ok]
