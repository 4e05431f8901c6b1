"""``vtr teach`` and ``vtr repeat``."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import click

from . import main
from .common import (
    check_out_dir,
    config_option,
    force_out_option,
    frames_option,
    load_config,
    note_outputs,
    progress_bar,
    source_argument,
    source_options,
    threads_option,
    up_option,
)
from .summaries import repeat_lines, teach_lines

if TYPE_CHECKING:
    import numpy as np

    from ..io.base import SourceOptions

map_option = click.option(
    "--map",
    "map_path",
    type=click.Path(path_type=Path),
    required=True,
    help="Map file (SQLite; created by teach, appended to by repeat).",
)


@main.command("teach")
@source_argument
@map_option
@frames_option
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    default=None,
    help="Also write trajectory_tum.txt, frames.csv and run.json here.",
)
@force_out_option
@up_option(
    "Up (opposite to gravity) in the first left camera's frame (x right, y down, z forward), kept in the "
    "map for every reader (state.csv, the perception field, the envelope). E.g. a camera pitched 50 deg "
    "down: 0,-0.643,-0.766. Default: the source's own (EuRoC), else none stored (a level first camera)."
)
@config_option
@source_options
@threads_option
def teach_cmd(
    source: Path,
    map_path: Path,
    frames: str | None,
    out: Path | None,
    force: bool,
    gravity_up: np.ndarray | None,
    config_path: Path | None,
    source_options: SourceOptions,
    threads: int | None,
) -> None:
    """Teach a route: odometry over SOURCE, keyframes written to a new map MAP.

    The teach run ends finished, or aborted with the reason (error, Ctrl-C, SIGTERM, full disk) after
    the keyframes still in the odometry window are written; a teach that wrote nothing leaves no MAP.
    MAP must not exist (a map is never replaced, even with --force: delete it first)."""
    from ..app.pipeline import teach_command
    from ..io.outputs import check_new_output

    check_new_output(map_path, can_force=False)  # the map is never replaced (Map.create checks it again)
    note_outputs(map_path)
    if out is not None:
        check_out_dir(out, force)
    config = load_config(config_path, threads)
    summary = teach_command(
        source, map_path, frames, config, out, source_options, progress_bar(), gravity_up=gravity_up
    )
    for line in teach_lines(summary):
        click.echo(line)


@main.command("repeat")
@source_argument
@map_option
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Output folder.")
@force_out_option
@frames_option
@click.option(
    "--rate",
    "rate_hz",
    type=float,
    default=None,
    metavar="HZ",
    help="Rate of the smoothed controller state in state.csv (default: smoothing.rate_hz, 50; "
    "domain of smoothing.rate_hz).",
)
@click.option(
    "--allow-partial",
    is_flag=True,
    help="Repeat even when the teach run is not finished (aborted or interrupted: route may be cut short).",
)
@click.option(
    "--start-vertex",
    type=click.IntRange(min=0),
    default=None,
    metavar="N",
    help="Optional hint: the repeat starts near taught vertex N (index along the taught path). Never "
    "needed: place recognition finds where on the route the repeat is.",
)
@click.option(
    "--start-distance",
    type=click.FloatRange(min=0.0),
    default=None,
    metavar="M",
    help="Optional hint: the repeat starts M metres along the taught path (as --start-vertex).",
)
@click.option(
    "--read-only-map",
    is_flag=True,
    help="Leave MAP untouched: repeat on a private copy in temporary space (removed at the end) instead "
    "of appending the repeat run to MAP.",
)
@up_option(
    "Up in the teach run's first left camera frame for the controller state; overrides the map's stored "
    "gravity (a warning when they disagree). Default: the map's, else a level first camera."
)
@config_option
@source_options
@threads_option
def repeat_cmd(
    source: Path,
    map_path: Path,
    out: Path,
    force: bool,
    frames: str | None,
    rate_hz: float | None,
    allow_partial: bool,
    start_vertex: int | None,
    start_distance: float | None,
    read_only_map: bool,
    gravity_up: np.ndarray | None,
    config_path: Path | None,
    source_options: SourceOptions,
    threads: int | None,
) -> None:
    """Repeat a taught route: localize every new keyframe of SOURCE against the map.

    The repeat may start anywhere on the route and travel it either way. Refuses a map whose teach run did
    not finish unless --allow-partial. The repeat is appended to MAP as a new run (the documented exception
    to the output rule: MAP is an input that grows), unless --read-only-map."""
    from ..app.pipeline import repeat_command
    from ..errors import UnfinishedRouteError

    note_outputs(map_path)
    check_out_dir(out, force)
    config = load_config(config_path, threads)
    try:
        summary = repeat_command(
            source,
            map_path,
            out,
            frames,
            config,
            source_options,
            progress_bar(),
            rate_hz=rate_hz,
            allow_partial=allow_partial,
            start_vertex=start_vertex,
            start_distance_m=start_distance,
            read_only_map=read_only_map,
            gravity_up=gravity_up,
            warn=lambda line: click.echo(line, err=True),
        )
    except UnfinishedRouteError as err:
        raise err.allowed_by("--allow-partial") from None
    for line in repeat_lines(summary):
        click.echo(line)
    click.echo(f"wrote {out}/localization.csv, landmarks.csv, state.csv, trajectory_tum.txt, report.png, run.json")
