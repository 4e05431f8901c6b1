"""``vtr teach`` and ``vtr repeat``."""

from __future__ import annotations

from pathlib import Path

import click

from . import main
from .common import (
    config_option,
    format_option,
    frames_option,
    load_config,
    progress_bar,
    source_argument,
    threads_option,
)

map_option = click.option("--map", "map_path", type=click.Path(path_type=Path), required=True,
                          help="Map file (SQLite; created by teach, appended to by repeat).")


@main.command("teach")
@source_argument
@map_option
@frames_option
@click.option("--out", type=click.Path(path_type=Path), default=None,
              help="Also write trajectory_tum.txt, frames.csv and run.json here.")
@config_option
@format_option
@threads_option
def teach_cmd(source: Path, map_path: Path, frames: str | None, out: Path | None, config_path: Path | None,
              fmt: str | None, threads: int | None) -> None:
    """Teach a route: odometry over SOURCE, keyframes written to a new map MAP."""
    from ..app.pipeline import teach_command

    summary = teach_command(source, map_path, frames, load_config(config_path, threads), out, fmt, progress_bar())
    for line in summary.lines():
        click.echo(line)


@main.command("repeat")
@source_argument
@map_option
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Output folder.")
@frames_option
@click.option("--rate", "rate_hz", type=float, default=None, metavar="HZ",
              help="Rate of the smoothed controller state in state.csv (default: smoothing.rate_hz, 50).")
@config_option
@format_option
@threads_option
def repeat_cmd(source: Path, map_path: Path, out: Path, frames: str | None, rate_hz: float | None,
               config_path: Path | None, fmt: str | None, threads: int | None) -> None:
    """Repeat a taught route: localize every new keyframe of SOURCE against the map."""
    from ..app.pipeline import repeat_command

    summary = repeat_command(source, map_path, out, frames, load_config(config_path, threads), fmt, progress_bar(),
                             rate_hz=rate_hz)
    for line in summary.lines():
        click.echo(line)
    click.echo(f"wrote {out}/localization.csv, landmarks.csv, state.csv, trajectory_tum.txt, report.png, run.json")
