"""Conversion of any stereo ``FrameSource`` to a KITTI folder or a ROS bag (ROS 1, ROS 2 sqlite3, MCAP).

Lossless: images are written as PNG (KITTI) or ``mono8`` ``sensor_msgs/Image`` (bags) and times as
exact int64 ns (``times_ns.txt`` beside KITTI's ``times.txt``; header stamps in bags), so a folder ->
bag -> folder round trip gives byte-identical pixels and identical stamps. The output is written
under a temporary name and renamed when complete: a failed conversion leaves no output that could
pass for a complete one.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..io.base import FrameSource
from ..io.kitti_writer import KittiWriter
from ..io.outputs import check_new_output
from ..io.rosbag import ROS1_SUFFIX
from ..io.rosbag_writer import RosbagWriter

TARGETS = ("kitti", "rosbag1", "rosbag2", "mcap")
PARTIAL_SUFFIX = ".partial"


@dataclass(frozen=True)
class ConvertSummary:
    """What a conversion wrote."""

    source: Path
    source_format: str
    out: Path
    target: str
    frames: int
    first_t_ns: int
    last_t_ns: int
    bytes_written: int
    seconds: float
    wrote_poses: bool = False


def default_target(out: Path) -> str:
    """Target implied by the output name: ``.bag`` -> rosbag1, otherwise a KITTI folder."""
    return "rosbag1" if Path(out).suffix == ROS1_SUFFIX else "kitti"


def _size(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def _gt_poses(source: FrameSource, indices: Sequence[int]) -> np.ndarray | None:
    """Ground-truth poses of the selected frames when the source has one per frame at the frame times."""
    gt = source.ground_truth()
    if gt is None or len(gt.t_ns) != len(source) or not np.array_equal(gt.t_ns, source.timestamps()):
        return None
    return gt.T_world_cam[np.asarray(indices)]


def convert(
    source: FrameSource,
    out: str | Path,
    to: str | None = None,
    indices: Sequence[int] | None = None,
    progress: Callable[[int], None] | None = None,
) -> ConvertSummary:
    """Write ``source`` (the frames at ``indices``, default all) to ``out`` as ``to`` (see ``TARGETS``).

    ``out`` must not exist (an empty folder is accepted for ``kitti``). ``progress(n)`` is called after
    each frame with the number of frames written so far. Raises ``DataError`` on bad arguments or
    input; the partial output is removed.
    """
    out = Path(out)
    to = to or default_target(out)
    if to not in TARGETS:
        raise DataError(f"unknown target {to!r} (one of {', '.join(TARGETS)})")
    if to == "rosbag1" and out.suffix != ROS1_SUFFIX:
        raise DataError(f"{out}: a ROS 1 bag file name must end in {ROS1_SUFFIX}")
    check_new_output(out, can_force=False, empty_folder_ok=to == "kitti")
    if not out.parent.exists():
        raise DataError(f"{out.parent}: no such folder")
    idx = list(range(len(source))) if indices is None else [int(i) for i in indices]
    if not idx:
        raise DataError(f"{source.path}: no frame selected")
    tmp = out.with_name(out.name + PARTIAL_SUFFIX)
    if to == "rosbag1":  # the ROS 1 reader keys on the .bag suffix
        tmp = out.with_name(out.stem + PARTIAL_SUFFIX + ROS1_SUFFIX)
    if tmp.exists():
        raise DataError(f"{tmp}: left over from an interrupted conversion; remove it first")
    start = time.perf_counter()
    times: list[int] = []
    wrote_poses = False
    try:
        if to == "kitti":
            writer = KittiWriter(tmp, source.camera)
            for f in source.iter_frames(idx):
                writer.add(f.t_ns, f.left, f.right)
                times.append(f.t_ns)
                if progress:
                    progress(len(times))
            poses = _gt_poses(source, idx)
            writer.close(poses)
            wrote_poses = poses is not None
        else:
            with RosbagWriter(tmp, source.camera, kind=to) as bag:
                for f in source.iter_frames(idx):
                    bag.add(f.t_ns, f.left, f.right)
                    times.append(f.t_ns)
                    if progress:
                        progress(len(times))
        if len(times) != len(idx):
            raise DataError(f"{source.path}: read {len(times)} of {len(idx)} frames")
        if to != "rosbag1" and to != "kitti":
            # rosbags names the storage file after the folder: rename it with the folder
            suffix = ".mcap" if to == "mcap" else ".db3"
            inner = tmp / (tmp.name + suffix)
            inner.rename(tmp / (out.name + suffix))
            meta = tmp / "metadata.yaml"
            meta.write_text(meta.read_text().replace(tmp.name + suffix, out.name + suffix))
        if out.exists():  # the accepted empty kitti folder
            out.rmdir()
        tmp.rename(out)
    except BaseException:
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        elif tmp.exists():
            tmp.unlink()
        raise
    return ConvertSummary(
        source=Path(source.path),
        source_format=source.format_name,
        out=out,
        target=to,
        frames=len(times),
        first_t_ns=int(times[0]),
        last_t_ns=int(times[-1]),
        bytes_written=_size(out),
        seconds=time.perf_counter() - start,
        wrote_poses=wrote_poses,
    )
