"""Frame sources (one interface for every logged format); the writers are `kitti_writer` and `rosbag_writer`."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

from ..errors import DataError
from .base import FrameSource, GroundTruth, SourceOptions, parse_frame_range
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
#: other names of a format: the bag kinds ``vtr convert --to`` writes are all read by the rosbag reader
FORMAT_ALIASES = {"rosbag1": "rosbag", "rosbag2": "rosbag", "mcap": "rosbag"}


def open_source(path: str | Path, options: SourceOptions | str | None = None, *,
                format: str | None = None) -> FrameSource:
    """Open a logged stereo source, detecting its format unless the options force one.

    ``options`` is a ``SourceOptions`` (format, ROS bag topics, ``allow_unpaired``) or, for short,
    a format name; ``format`` overrides the options' format. Bag options given for another format
    are an error rather than ignored.
    """
    path = Path(path)
    opts = SourceOptions(format=options) if isinstance(options, str) else options or SourceOptions()
    if format is not None:
        opts = dataclasses.replace(opts, format=format)
    if not path.exists():
        raise DataError(f"{path}: no such file or folder")
    name = FORMAT_ALIASES.get(opts.format, opts.format) if opts.format is not None else None
    if name is not None:
        if name not in FORMATS:
            raise DataError(f"unknown format {name!r}; known: {', '.join([*FORMATS, *FORMAT_ALIASES])}")
    else:
        name = next((n for n, (detect, _) in FORMATS.items() if detect(path)), None)
    if name is None:
        if path.is_dir() and not any(path.iterdir()):
            raise DataError(f"{path}: empty folder")
        raise DataError(f"{path}: unknown layout (expected one of: {', '.join(FORMATS)})")
    bag = opts.bag_kwargs()
    if name == "rosbag":
        return RosbagSource(path, **bag)  # type: ignore[arg-type]
    if bag:
        flags = ", ".join("--" + k.replace("_", "-") for k in bag)
        raise DataError(f"{path}: {flags} apply to ROS bag sources only (this is a {name} source)")
    return FORMATS[name][1](path)


__all__ = [
    "FORMATS", "FORMAT_ALIASES", "CloudRun", "EurocSource", "FrameSource", "GroundTruth", "KittiSource",
    "RosbagSource", "SourceOptions", "StereoPairsSource", "open_source", "parse_frame_range",
]
