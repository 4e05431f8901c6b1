"""``vtr map info`` and ``vtr export-map``: inspect and export pose-graph maps."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import click

from . import main
from .common import check_out_dir, config_option, force_out_option, load_config
from .summaries import map_check_line

map_argument = click.argument("map_path", metavar="MAP", type=click.Path(path_type=Path))


def _size(n_bytes: int) -> str:
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n_bytes >= scale:
            return f"{n_bytes / scale:.1f} {unit}"
    return f"{n_bytes} B"


@main.group("map")
def map_group() -> None:
    """Inspect pose-graph maps written by `vtr teach` / `vtr repeat`."""


@map_group.command("info")
@map_argument
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
def map_info_cmd(map_path: Path, as_json: bool) -> None:
    """Runs (with their state: running, finished, aborted and why, or interrupted when the writing
    process was killed), vertex/edge/landmark counts, size on disk and format version of MAP."""
    from ..config import Config
    from ..map import Map
    from ..map.experiences import experiences

    with Map.open(map_path, "r") as m:
        stats = m.stats()
        runs = m.runs()
        cam = m.camera
        created = m.meta.get("created", "?")
        up = m.gravity_up
        unclosed = m.not_closed()
        exps = experiences(m, Config().experiences.min_localized_share)
        records = {r.id: m.localization_count(r.id) for r in runs if r.kind == "repeat"}
    if as_json:
        stats["not_closed"] = unclosed
        stats["created"] = created
        stats["camera"] = cam.to_dict()
        stats["gravity_up"] = None if up is None else [float(x) for x in up]
        stats["run_list"] = [
            {
                "id": r.id,
                "kind": r.kind,
                "privileged": r.privileged,
                "state": r.state,
                "reason": r.reason,
                "finished": r.finished,
                "vertices": r.n_vertices,
                "source": r.source,
                "created": r.created,
                "localization_records": records.get(r.id, 0),
            }
            for r in runs
        ]
        stats["experiences"] = [dataclasses.asdict(e) for e in exps]
        click.echo(json.dumps(stats, indent=2))
        return
    click.echo(f"map: {map_path}")
    click.echo(f"format version: {stats['format_version']}  created: {created}")
    click.echo(
        f"camera: {cam.width}x{cam.height} fx={cam.fx:.2f} fy={cam.fy:.2f} cx={cam.cx:.2f} "
        f"cy={cam.cy:.2f} baseline={cam.baseline:.4f} m"
    )
    click.echo(
        "gravity: "
        + (
            "not stored (taught without --up: readers take the first camera as level, up = its -y)"
            if up is None
            else "up " + ",".join(f"{x:.4f}" for x in up) + " in the first teach camera"
        )
    )
    click.echo(f"size on disk: {_size(stats['bytes'])} ({stats['bytes']} bytes)")
    click.echo(
        f"vertices: {stats['vertices']}  edges: {stats['edges']} (temporal {stats['temporal_edges']}, "
        f"spatial {stats['spatial_edges']})  landmarks: {stats['landmarks']}  features: {stats['features']}"
    )
    click.echo(f"runs: {stats['runs']}")
    if runs:
        click.echo(f"  {'id':>4}  {'kind':<6}  {'privileged':<10}  {'state':<11}  {'vertices':>8}  source")
        for r in runs:
            click.echo(
                f"  {r.id:>4}  {r.kind:<6}  {'yes' if r.privileged else 'no':<10}  "
                f"{r.state:<11}  {r.n_vertices:>8}  {r.source or '-'}"
            )
        for r in runs:
            if r.reason:
                click.echo(f"  run {r.id} {r.state}: {r.reason}")
        for r in runs:
            if r.kind == "repeat" and not r.finished and records.get(r.id):
                click.echo(
                    f"  run {r.id} {r.state}: its localization.csv may lack the last of its "
                    f"{records[r.id]} localization records (a killed repeat); `vtr map localizations "
                    f"{map_path} {r.id} --out DIR` writes them all"
                )
        partial = [r.id for r in runs if r.privileged and not r.finished]
        if partial:
            click.echo(
                f"warning: teach run(s) {', '.join(map(str, partial))} not finished: `vtr repeat` refuses "
                "this map unless --allow-partial"
            )
    if exps:
        click.echo(
            f"experiences (repeats a later repeat may localize against; trusted: finished and at least "
            f"{Config().experiences.min_localized_share:.0%} of its keyframes localized):"
        )
        click.echo(f"  {'run':>4}  {'localized':>13}  {'trusted':<7}  {'used':>9}  {'by':>3}")
        for e in exps:
            click.echo(
                f"  {e.run:>4}  {e.localized:>5} / {e.n_vertices:<5}  {'yes' if e.trusted else 'no':<7}  "
                f"{e.used_keyframes:>9}  {e.used_by:>3}" + ("" if e.trusted else f"  ({e.why_not})")
            )
    if unclosed:
        click.echo(f"warning: {unclosed}")


@map_group.command("prune")
@map_argument
@click.option(
    "--keep-last",
    type=int,
    default=None,
    help="Keep the newest this many experiences at each taught vertex (default: experiences.keep_last).",
)
@click.option(
    "--keep-most-used",
    type=int,
    default=None,
    help="... plus this many most used (default: experiences.keep_most_used).",
)
@config_option
@click.option("--dry-run", is_flag=True, help="Say what would be removed; change nothing.")
def map_prune_cmd(
    map_path: Path, keep_last: int | None, keep_most_used: int | None, config_path: Path | None, dry_run: bool
) -> None:
    """Remove the repeat runs of MAP the retention rule does not keep: of the trusted experiences the newest
    KEEP_LAST localized at each taught vertex plus the KEEP_MOST_USED most used stay; older experiences and
    untrusted repeats (aborted, interrupted, localized too little) go. Taught runs are never removed."""
    from ..errors import ConfigError
    from ..map import Map
    from ..map.experiences import prune, retention

    loaded = load_config(config_path)
    config = loaded.experiences
    k_last = config.keep_last if keep_last is None else keep_last
    k_used = config.keep_most_used if keep_most_used is None else keep_most_used
    for name, value in (("--keep-last", k_last), ("--keep-most-used", k_used)):
        if value < 0:
            raise ConfigError(f"{name}: expected a count >= 0, got {value}")
    before = map_path.stat().st_size if map_path.is_file() else 0
    with Map.open(map_path, "r" if dry_run else "a") as m:
        plan = retention(m, k_last, k_used, config.min_localized_share, loaded.localization.neighbour_vertices)
        for run, why in sorted(plan.keep.items()):
            click.echo(f"keep run {run}: {why}")
        if dry_run:
            click.echo(f"would remove {len(plan.remove)} run(s)" + (f": {plan.remove}" if plan.remove else ""))
            return
        vertices = prune(m, plan.remove)
    after = map_path.stat().st_size
    click.echo(
        f"removed {len(plan.remove)} run(s)"
        + (f" {plan.remove}" if plan.remove else "")
        + f", {vertices} vertices; the map is {_size(after)} (was {_size(before)})"
    )


@map_group.command("check")
@map_argument
@click.option(
    "--repair",
    is_flag=True,
    help="Fold data a killed writer left in the map's -wal into the map file first (opens it for writing).",
)
def map_check_cmd(map_path: Path, repair: bool) -> None:
    """Check MAP for damage: SQLite's integrity check, the runs table, every vertex's checksums (maps made by
    this vtr) and data, the taught path (finite rigid poses, increasing times, existing runs) and every
    temporal edge against its poses, that the map is closed (no committed data only in its -wal), and that the
    stored place index is readable and indexes the taught vertices (its digest). Prints one line; exit 1 with
    the first damage found."""
    from ..config import Config
    from ..errors import MapError
    from ..map import Map
    from ..map.check import check_map
    from ..navigation.place import rebuild_place_index, stored_place_index

    if repair:
        with Map.open(map_path, "r") as m:
            pages = m.file.unfolded_pages() if m.not_closed() else 0
        with Map.open(map_path, "a"):
            pass  # a writer folds the log on open; closing returns the file to one self-contained file
        if pages:
            click.echo(f"{map_path}: folded {pages} page(s) of its -wal into the map file")
    with Map.open(map_path, "r") as m:
        report = check_map(m)
        unclosed = m.not_closed()
        taught = any(r.privileged and r.n_vertices for r in m.runs())
        stored = stored_place_index(m) if taught else None
    if unclosed:
        raise MapError(f"{map_path}: {unclosed}")
    place = "no taught route"
    if stored is not None:
        place = (
            "place index matches the taught vertices"
            if stored.index is not None
            else "no place index stored (the first repeat builds it)"
        )
        if stored.problem is not None:
            if not repair:
                raise MapError(
                    f"{map_path}: place index {stored.key}: {stored.problem}; `vtr map check --repair` rebuilds it"
                )
            defaults = Config()
            with Map.open(map_path, "a") as m:
                rebuild_place_index(m, defaults.place, defaults.run.seed)
            click.echo(f"{map_path}: place index {stored.key}: {stored.problem}; rebuilt from the vertices")
            place = "place index rebuilt"
    click.echo(f"{map_check_line(report, map_path)}; {place}")


@map_group.command("localizations")
@map_argument
@click.argument("run", type=int)
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    required=True,
    help="Folder for localization.csv (a killed repeat's own --out, with --force, makes it whole again).",
)
@force_out_option
def map_localizations_cmd(map_path: Path, run: int, out: Path, force: bool) -> None:
    """Write repeat RUN's localization.csv from MAP: one row per vertex of the run, from the localization record
    the map stored with it in the same transaction (a repeat killed midway, even by SIGKILL, may have written
    the last rows of its own localization.csv or not; the map holds every one of its vertices' records).
    landmarks.csv is not in the map."""
    from ..app.outputs import OutputFolder
    from ..app.runfiles.localization_csv import LocalizationWriter
    from ..errors import MapError
    from ..map import Map
    from ..navigation.repeat import localization_of_record

    check_out_dir(out, force)
    with Map.open(map_path, "r") as m:
        info = m.run(run)
        if info.kind != "repeat":
            raise MapError(f"{map_path}: run {run} is a {info.kind} run: only repeats have localizations")
        records = m.localization_records(run)
    if info.n_vertices and not records:
        raise MapError(
            f"{map_path}: repeat run {run} has {info.n_vertices} vertices but no localization records "
            "(written by a vtr before the map kept them)"
        )
    folder = OutputFolder.prepare(out, [map_path], ["localization.csv"])
    with folder.open("localization.csv") as f:
        writer = LocalizationWriter(f)
        for record in records:
            writer.write(localization_of_record(record))
    ok = sum(r.success for r in records)
    click.echo(
        f"wrote {out}/localization.csv: {len(records)} rows ({ok} localized) of repeat run {run} "
        f"({info.state}, {info.n_vertices} vertices)"
    )


@main.command("export-map")
@map_argument
@click.option(
    "--ply",
    "ply_path",
    type=click.Path(path_type=Path),
    required=True,
    help="Output point cloud (.ply): landmarks of every run, coloured by run.",
)
@click.option("--force", is_flag=True, help="Replace the .ply file if it exists.")
@click.option(
    "--gravity-aligned",
    is_flag=True,
    help="Points in the map's gravity frame (z up; the map's stored gravity, else a level first camera) "
    "instead of the first teach camera's frame.",
)
def export_map_cmd(map_path: Path, ply_path: Path, force: bool, gravity_aligned: bool) -> None:
    """Export the landmarks of MAP as a PLY point cloud in the first teach run's world frame.

    Repeat runs linked to the teach run by spatial edges are placed through them; an unlinked
    run stays in its own world frame (reported as "own frame").
    """
    from ..map import Map
    from ..map.export import export_landmarks_ply
    from .common import check_out_file

    check_out_file(ply_path, force, inputs=(map_path,))
    with Map.open(map_path, "r") as m:
        summary = export_landmarks_ply(m, ply_path, gravity_aligned=gravity_aligned)
    total = sum(s.points for s in summary)
    for s in summary:
        rgb = "#" + "".join(f"{round(c * 255):02x}" for c in s.colour)
        frame = ("map gravity frame" if gravity_aligned else "map frame") if s.aligned else "own frame"
        click.echo(f"run {s.run} ({s.kind}): {s.points} landmarks, colour {rgb}, {frame}")
    click.echo(f"wrote {total} points to {ply_path}")
