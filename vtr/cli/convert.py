"""``vtr convert``: copy a stereo source (KITTI/EuRoC folder, ROS bag) to a KITTI folder or a ROS bag."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from . import main
from .common import format_option, frames_option, source_argument

if TYPE_CHECKING:
    from ..io import FrameSource


@main.command("convert")
@source_argument
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--to", "to", type=click.Choice(["kitti", "rosbag1", "rosbag2", "mcap"]), default=None,
              help="Output kind (default: rosbag1 when OUT ends in .bag, else a KITTI folder). "
                   "rosbag2 (sqlite3) and mcap write a ROS 2 bag folder.")
@format_option
@frames_option
@click.option("--left-topic", default=None, help="ROS bag source: left image topic.")
@click.option("--right-topic", default=None, help="ROS bag source: right image topic.")
@click.option("--left-info-topic", default=None, help="ROS bag source: left CameraInfo topic.")
@click.option("--right-info-topic", default=None, help="ROS bag source: right CameraInfo topic.")
@click.option("--allow-unpaired", is_flag=True,
              help="ROS bag source: keep the matched stereo pairs when some images have no partner.")
@click.option("--no-progress", is_flag=True, help="Do not show the progress bar.")
def convert_cmd(source: Path, out: Path, to: str | None, fmt: str | None, frames: str | None,
                left_topic: str | None, right_topic: str | None, left_info_topic: str | None,
                right_info_topic: str | None, allow_unpaired: bool, no_progress: bool) -> None:
    """Convert SOURCE to OUT losslessly (PNG / mono8 images, exact ns stamps, stereo calibration)."""
    from tqdm import tqdm

    from ..app.convert import convert
    from ..io import open_source, parse_frame_range
    from ..io.rosbag import RosbagSource, is_rosbag

    bag_opts: dict[str, Any] = dict(left_topic=left_topic, right_topic=right_topic, left_info_topic=left_info_topic,
                    right_info_topic=right_info_topic)
    use_bag = fmt == "rosbag" or (fmt is None and source.exists() and is_rosbag(source))
    if use_bag and (any(bag_opts.values()) or allow_unpaired):
        if not source.exists():
            raise FileNotFoundError(f"{source}: no such file or folder")
        src: FrameSource = RosbagSource(source, allow_unpaired=allow_unpaired, **bag_opts)
    else:
        if any(bag_opts.values()) or allow_unpaired:
            raise click.UsageError("topic options and --allow-unpaired apply to ROS bag sources only")
        src = open_source(source, fmt)
    with src:
        idx = parse_frame_range(frames, len(src), str(source))
        with tqdm(total=len(idx), unit="frame", desc="convert", disable=no_progress, leave=False) as bar:
            summary = convert(src, out, to=to, indices=idx, progress=lambda n: bar.update(n - bar.n))
    click.echo(summary.line())
