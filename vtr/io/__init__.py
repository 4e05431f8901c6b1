"""Frame sources (one interface for every logged format); the writers are `kitti_writer` and `rosbag_writer`."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from ..errors import DataError
from .base import FrameSource, GroundTruth, parse_frame_range
from .cloud import CloudRun, is_cloud_run, refuse_cloud_stereo
from .euroc import EurocSource, StereoPairsSource, euroc_root, is_stereo_pairs
from .kitti import KittiSource, is_kitti
from .rosbag import RosbagSource, is_rosbag

# format name -> (detector on a path, opener); later formats register here
FORMATS: dict[str, tuple[Callable[[Path], bool], Callable[[Path], FrameSource]]] = {
    "kitti": (is_kitti, KittiSource),
    "euroc": (lambda p: euroc_root(p) is not None, EurocSource),
    "stereo-pairs": (is_stereo_pairs, StereoPairsSource),
    "rosbag": (is_rosbag, RosbagSource),
    # CLOUD runs are monocular: detected so that open_source can say why they are refused
    "cloud": (is_cloud_run, refuse_cloud_stereo),
}


def open_source(path: str | Path, format: str | None = None) -> FrameSource:
    """Open a logged stereo source, detecting its format unless ``format`` forces one."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such file or folder")
    if format is not None:
        if format not in FORMATS:
            raise DataError(f"unknown format {format!r}; known: {', '.join(FORMATS)}")
        return FORMATS[format][1](path)
    for _name, (detect, opener) in FORMATS.items():
        if detect(path):
            return opener(path)
    if path.is_dir() and not any(path.iterdir()):
        raise DataError(f"{path}: empty folder")
    raise DataError(f"{path}: unknown layout (expected one of: {', '.join(FORMATS)})")


__all__ = [
    "FORMATS", "CloudRun", "EurocSource", "FrameSource", "GroundTruth", "KittiSource",
    "RosbagSource", "StereoPairsSource", "open_source", "parse_frame_range",
]
