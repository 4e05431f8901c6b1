"""``vtr convert``: copy a stereo source (KITTI/EuRoC folder, ROS bag) to a KITTI folder or a ROS bag."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import click

from . import main
from .common import frames_option, make_bar, note_outputs, source_argument, source_options
from .summaries import convert_line

if TYPE_CHECKING:
    from ..io.base import SourceOptions


@main.command("convert")
@source_argument
@click.argument("out", type=click.Path(path_type=Path))
@click.option(
    "--to",
    "to",
    type=click.Choice(["kitti", "rosbag1", "rosbag2", "mcap"]),
    default=None,
    help="Output kind (default: rosbag1 when OUT ends in .bag, else a KITTI folder). "
    "rosbag2 (sqlite3) and mcap write a ROS 2 bag folder.",
)
@frames_option
@source_options
@click.option("--no-progress", is_flag=True, help="Do not show the progress bar.")
def convert_cmd(
    source: Path, out: Path, to: str | None, frames: str | None, source_options: SourceOptions, no_progress: bool
) -> None:
    """Convert SOURCE to OUT losslessly (PNG / mono8 images, exact ns stamps, stereo calibration)."""
    from ..app.convert import convert
    from ..io import open_source, parse_frame_range

    note_outputs(out)
    with open_source(source, source_options) as src:
        idx = parse_frame_range(frames, len(src), str(source))
        with make_bar(len(idx), "convert", disable=no_progress) as bar:
            summary = convert(src, out, to=to, indices=idx, progress=lambda n: bar.update(n - bar.n))
    click.echo(convert_line(summary))
