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


def open_source(
    path: str | Path, options: SourceOptions | str | None = None, *, format: str | None = None
) -> FrameSource:
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
        _check_forced(path, name)
    else:
        name = next((n for n, (detect, _) in FORMATS.items() if detect(path)), None)
    if name is None:
        if path.is_dir() and not any(path.iterdir()):
            raise DataError(f"{path}: empty folder")
        raise DataError(f"{path}: unknown layout (expected one of: {', '.join(FORMATS)}){_layout_hint(path)}")
    bag = opts.bag_kwargs()
    if name == "rosbag":
        return RosbagSource(path, **bag)  # type: ignore[arg-type]
    if bag:
        flags = ", ".join("--" + k.replace("_", "-") for k in bag)
        raise DataError(f"{path}: {flags} apply to ROS bag sources only (this is a {name} source)")
    return FORMATS[name][1](path)


FOLDER_FORMATS = ("kitti", "euroc", "stereo-pairs", "cloud")  # read a folder (a ROS bag may be a file)
BAG_FILES = ("*.db3", "*.mcap")


def _detected(path: Path) -> str | None:
    return next((n for n, (detect, _) in FORMATS.items() if detect(path)), None)


def _check_forced(path: Path, name: str) -> None:
    """A forced ``--format`` that cannot fit ``path`` says so, and what ``path`` looks like instead."""
    other = _detected(path)
    if name in FOLDER_FORMATS and path.is_file():
        hint = f"; it looks like a {other} source: drop --format or pass --format {other}" if other else ""
        raise DataError(f"{path}: is a file, but --format {name} reads a folder{hint}")
    if other is not None and other != name and not FORMATS[name][0](path):
        raise DataError(
            f"{path}: not a {name} source; it looks like a {other} source: drop --format or pass --format {other}"
        )


def _layout_hint(path: Path) -> str:
    """Why a folder is no known layout, when it is nearly one (a ROS 2 bag folder without metadata.yaml)."""
    if path.is_dir():
        bags = sorted(p.name for pattern in BAG_FILES for p in path.glob(pattern))
        if bags and not (path / "metadata.yaml").exists():
            return (
                f"; it holds {bags[0]} but no metadata.yaml: a ROS 2 bag folder needs its metadata.yaml "
                f"(or open the file itself: {path / bags[0]})"
            )
    return ""


__all__ = [
    "FORMATS",
    "FORMAT_ALIASES",
    "CloudRun",
    "EurocSource",
    "FrameSource",
    "GroundTruth",
    "KittiSource",
    "RosbagSource",
    "SourceOptions",
    "StereoPairsSource",
    "open_source",
    "parse_frame_range",
]
