"""``vtr odometry``, ``vtr export-trajectory`` and ``vtr demo``."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import click

from . import main
from .common import (
    check_out_dir,
    check_out_file,
    config_option,
    force_out_option,
    frame_progress,
    frames_option,
    load_config,
    progress_bar,
    source_argument,
    source_options,
    threads_option,
)
from .summaries import mission_lines, odometry_lines, repeat_lines, teach_lines

if TYPE_CHECKING:
    from ..io.base import SourceOptions

DEMO_CLIP = "kitti06_clip"


def _find_datasets() -> Path:
    """The shipped ``datasets/`` folder (source checkout), or VTR_DATASETS."""
    import os

    env = os.environ.get("VTR_DATASETS")
    if env:
        return Path(env)
    here = Path(__file__).resolve()
    for parent in here.parents:
        if (parent / "datasets" / DEMO_CLIP).is_dir():
            return parent / "datasets"
    return Path("datasets")


@main.command("odometry")
@source_argument
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Output folder.")
@force_out_option
@frames_option
@config_option
@source_options
@threads_option
def odometry_cmd(
    source: Path,
    out: Path,
    force: bool,
    frames: str | None,
    config_path: Path | None,
    source_options: SourceOptions,
    threads: int | None,
) -> None:
    """Stereo visual odometry over SOURCE (KITTI or EuRoC folder, bag...)."""
    from ..app.pipeline import odometry_command

    check_out_dir(out, force)
    config = load_config(config_path, threads)
    summary = odometry_command(source, out, frames, config, source_options, progress_bar())
    for line in odometry_lines(summary):
        click.echo(line)
    click.echo(f"wrote {out}/trajectory_tum.txt, frames.csv, trajectory.png, run.json")


@main.command("export-trajectory")
@click.argument("tum_file", type=click.Path(path_type=Path))
@click.argument("out_file", type=click.Path(path_type=Path))
@click.option("--to", "fmt", type=click.Choice(["tum", "kitti", "euroc"]), required=True)
@click.option("--force", is_flag=True, help="Replace OUT_FILE if it exists.")
def export_trajectory_cmd(tum_file: Path, out_file: Path, fmt: str, force: bool) -> None:
    """Convert a TUM trajectory (as written by vtr) to KITTI or EuRoC format."""
    from ..errors import DataError
    from ..io.outputs import write_output
    from ..io.trajectory import read_tum, write_trajectory

    if not tum_file.is_file():
        raise DataError(f"{tum_file}: no such file")
    check_out_file(out_file, force, inputs=(tum_file,))
    t_ns, T = read_tum(tum_file)
    write_output(out_file, lambda tmp: write_trajectory(tmp, t_ns, T, fmt), force, inputs=(tum_file,))
    click.echo(f"wrote {len(t_ns)} poses to {out_file} ({fmt})")


#: What ``vtr demo`` writes in its ``--out`` (each recorded there; anything else in the folder is left alone).
DEMO_ENTRIES = ("route.vtrmap", "odometry", "teach", "repeat", "aerial")


@main.command("demo")
@click.option("--out", type=click.Path(path_type=Path), default=Path("out/demo"), show_default=True)
@click.option(
    "--aerial/--no-aerial",
    default=True,
    show_default=True,
    help="Step 4: the synthetic aerial mission (renders ~150 frames, about a minute).",
)
def demo_cmd(out: Path, aerial: bool) -> None:
    """Teach and repeat on the shipped KITTI clip (teach even frames, repeat odd ones) with a short report,
    then the whole perception mission on a synthetic aerial scene (teach, offset repeats, model, envelope).

    The one command that replaces its outputs without --force: OUT is the demo's own folder, rewritten
    by every run (only what the demo made there: a file or folder of yours at one of its names is refused)."""
    from ..app.outputs import OutputFolder
    from ..app.pipeline import odometry_command, repeat_command, teach_command
    from ..config import Config

    clip = _find_datasets() / DEMO_CLIP
    config = Config()
    check_out_dir(out, force=True)  # the documented exception: the demo rewrites its own folder...
    own = OutputFolder.prepare(out)
    own.claim_entries(DEMO_ENTRIES)  # ...and only what its record says it made there (not a user's map)
    map_path = out / "route.vtrmap"
    own.remove_entry("route.vtrmap")
    click.echo(f"vtr demo on {clip}")
    click.echo("1/4 stereo odometry over all frames")
    for line in odometry_lines(odometry_command(clip, out / "odometry", None, config, None, progress_bar())):
        click.echo("    " + line)
    click.echo("2/4 teach on the even frames")
    for line in teach_lines(teach_command(clip, map_path, "0::2", config, out / "teach", None, progress_bar())):
        click.echo("    " + line)
    click.echo("3/4 repeat on the odd frames, localizing against the taught path")
    for line in repeat_lines(repeat_command(clip, map_path, out / "repeat", "1::2", config, None, progress_bar())):
        click.echo("    " + line)
    if not aerial:
        click.echo(
            f"report: {out}/repeat/report.png, {out}/odometry/trajectory.png; "
            f"records: {out}/repeat/localization.csv, landmarks.csv; map: {map_path}"
        )
        return
    click.echo(
        "4/4 synthetic aerial mission: teach, repeats at 0/1/2/4/8 m to the left (and 16/24 m held out), "
        "model fitted on their landmarks, localization envelope"
    )
    from ..app.mission import run_aerial_mission

    mission = run_aerial_mission(out / "aerial", config, progress=lambda name: frame_progress(f"render {name}"))
    for line in mission_lines(mission):
        click.echo("    " + line)
    click.echo(
        f"report: {out}/repeat/report.png, {out}/odometry/trajectory.png, {mission.report_html}; "
        f"records: {out}/repeat/localization.csv, landmarks.csv; map: {map_path}"
    )
