"""The ``perception-model`` console script as installed with ``vtr``: the package's commands plus the map.

``perception_model.cli`` imports nothing from ``vtr`` and knows no maps; this group holds its ``fit`` and
``evaluate`` and the two commands that read a taught map, declared and served here:

    perception-model constraint MODEL.json --landmarks L.csv --positions P.csv
    perception-model constraint MODEL.json --map route.vtrmap --positions P.csv [--out DIR | --out -]
    perception-model envelope MODEL.json --map MAP --out DIR [--up X,Y,Z] [--l-min 30] [--c-bar 3 | --delta D]

``constraint --map`` reads each position's trunk and its landmarks from the map
(:func:`vtr.app.perception.evaluate_on_map`), in the map frame (the teach run's first camera frame: x right,
y down, z forward; see ``perception_model.map_landmarks`` for the orientation/yaw convention); with
``--landmarks`` it is the package's command. ``envelope`` writes ``DIR/envelope.csv`` and ``DIR/envelope.png``
(see :func:`vtr.app.perception.localization_envelope`).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import click

from perception_model.cli import (
    COMMON_FMT,
    PROG,
    Table,
    _Group,
    _parse_vector,
    check_output,
    confidence_options,
    constraint_on_landmarks,
    constraint_output,
    constraint_output_options,
    landmarks_option,
    report_constraint,
    resolve_c_bar,
    taught_camera_option,
)
from perception_model.cli import main as _package_main
from perception_model.commandline import force_option
from perception_model.errors import InputDataError
from perception_model.settings import THESIS_PITCH_DOWN_RAD

from ..errors import VtrError
from .common import make_bar

#: The package's commands this group holds as they are (``constraint`` is declared here, with ``--map``).
PACKAGE_COMMANDS = ("fit", "evaluate")


class _MapGroup(_Group):
    """Known errors of both packages become one line."""

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except VtrError as err:
            click.echo(f"{PROG}: error: {err}", err=True)
            sys.exit(1)


@click.group(cls=_MapGroup, name=PROG)
@click.version_option(None, package_name="vtr", prog_name=PROG, message="%(prog)s %(version)s")
def main() -> None:
    """Fit, evaluate and apply the perception model (with the taught-map commands of vtr)."""


for _name in PACKAGE_COMMANDS:
    main.add_command(_package_main.commands[_name], _name)


@main.command("constraint")
@click.argument("model_path", metavar="MODEL.json", type=click.Path(dir_okay=False, path_type=Path))
@landmarks_option(required=False)
@click.option(
    "--map",
    "map_path",
    type=click.Path(path_type=Path),
    default=None,
    help="A taught vtr map: positions are in its map frame (the teach run's first camera frame, x right, "
    "y down, z forward); each position's trunk is chosen by the localizer's rule.",
)
@click.option(
    "--positions",
    "positions_path",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="Camera positions along the path: CSV x,y,z[,yaw | ,yaw_deg] (yaw in radians); frame o, or the "
    "map frame with --map.",
)
@taught_camera_option
@confidence_options
@click.option(
    "--pitch-deg",
    type=float,
    default=None,
    help=f"Camera pitch below the horizon (degrees) for yaw-defined axes [default: "
    f"{math.degrees(THESIS_PITCH_DOWN_RAD):g}; with --map the trunk's pitch].",
)
@click.option(
    "--yaw-deg",
    type=float,
    default=None,
    help="Camera yaw (degrees, CCW from x; with --map CCW from the map's +z about its -y) where the positions "
    "file has no yaw column [default: 0; with --map the trunk's orientation].",
)
@click.option(
    "--in-view/--all-landmarks",
    default=True,
    show_default=True,
    help="With --map: count only trunk landmarks inside the camera image at each position (the population "
    "of landmarks.csv), or every trunk landmark.",
)
@constraint_output_options
def constraint_cmd(
    model_path: Path,
    landmarks_path: Path | None,
    map_path: Path | None,
    positions_path: Path,
    taught_camera: str | None,
    l_min: float,
    c_bar: float | None,
    delta: float | None,
    pitch_deg: float | None,
    yaw_deg: float | None,
    in_view: bool,
    exact: bool,
    out: Path | None,
    force: bool,
) -> None:
    """Evaluate mu, sigma and the chance-constraint margin along a path.

    With --landmarks, landmarks and positions are in the gravity-aligned frame o (ENU-like, z up);
    the optical axis comes from yaw and --pitch-deg. With --map, each position's trunk is the
    taught vertex the localizer would pick (its window rule, from the vertex nearest to the first
    position) and its landmarks come from the map; without a yaw the camera has the
    trunk's orientation, with a yaw (heading about the map's -y, 0 along +z, positive to the left)
    it is pitched by --pitch-deg or the trunk's pitch (see perception_model.map_landmarks).
    """
    from perception_model.io import read_positions
    from perception_model.model import PerceptionModel

    to_stdout, csv_path = constraint_output(out, force, (model_path, landmarks_path, map_path, positions_path))
    if (landmarks_path is None) == (map_path is None):
        raise InputDataError("give exactly one of --landmarks FILE or --map MAP")
    if map_path is not None and taught_camera is not None:
        raise InputDataError("--taught-camera applies to --landmarks only (with --map the trunk is the origin)")
    cbar = resolve_c_bar(c_bar, delta)
    model = PerceptionModel.load(model_path)
    path = read_positions(positions_path)
    if map_path is not None:
        table = _constraint_on_map(model, map_path, path, l_min, cbar, pitch_deg, yaw_deg, in_view, exact)
    else:
        assert landmarks_path is not None
        table = constraint_on_landmarks(
            model, landmarks_path, path, l_min, cbar, pitch_deg, yaw_deg, taught_camera, exact
        )
    report_constraint(table, l_min, cbar, to_stdout, csv_path)


def _constraint_on_map(
    model: Any,
    map_path: Path,
    path: Any,
    l_min: float,
    cbar: float,
    pitch_deg: float | None,
    yaw_deg: float | None,
    in_view: bool,
    exact: bool,
) -> Table:
    """Per-position rows with each position's trunk taken from a taught vtr map."""
    import numpy as np

    from ..app.perception import evaluate_on_map

    yaw = path.yaw if path.yaw is not None else (None if yaw_deg is None else math.radians(yaw_deg))
    t = evaluate_on_map(
        model,
        map_path,
        path.positions,
        yaw,
        pitch_down=None if pitch_deg is None else math.radians(pitch_deg),
        l_min=l_min,
        c_bar=cbar,
        in_view=in_view,
        exact=exact,
    )
    header = [
        "index",
        "x",
        "y",
        "z",
        "yaw_deg",
        "pitch_deg",
        "trunk_id",
        "trunk_distance_m",
        "n_landmarks",
        "n_in_view",
        "mu",
        "sigma",
        "g",
        "g_conservative",
        "p_fail_normal",
    ]
    if exact:
        header.append("p_fail_exact")
    rows = []
    for i in range(len(t)):
        row: list[Any] = [
            i,
            *t.positions[i].tolist(),
            math.degrees(float(t.yaw[i])),
            math.degrees(float(t.pitch_down[i])),
            int(t.trunk_id[i]),
            float(t.trunk_distance_m[i]),
            int(t.n_landmarks[i]),
            int(t.n_in_view[i]),
            float(t.mu[i]),
            float(t.sigma[i]),
            float(t.g[i]),
            float(t.g_conservative[i]),
            float(t.p_fail_normal[i]),
        ]
        if t.p_fail_exact is not None:
            row.append(float(t.p_fail_exact[i]))
        rows.append(row)
    fmt = [
        ("index", 4, "d"),
        ("x", 8, ".2f"),
        ("y", 8, ".2f"),
        ("z", 8, ".2f"),
        ("yaw_deg", 7, ".1f"),
        ("trunk_id", 12, "d"),
        ("trunk_distance_m", 6, ".2f"),
        ("n_in_view", 6, "d"),
    ]
    fmt += COMMON_FMT + ([("p_fail_exact", 10, ".3e")] if exact else [])
    orientation = "yaw given" if t.yaw_given else "trunk orientation"
    intro = (
        f"map {map_path}: {len(np.unique(t.trunk_id))} trunk(s), {t.n_map_landmarks} landmarks, {len(t)} positions "
        f"({orientation}, {'in-view landmarks' if in_view else 'all trunk landmarks'})"
    )
    return header, rows, fmt, intro


@main.command("envelope")
@click.argument("model_path", metavar="MODEL.json", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--map", "map_path", required=True, type=click.Path(path_type=Path), help="A taught vtr map.")
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Output folder: envelope.csv and envelope.png.",
)
@force_option("envelope.csv and envelope.png")
@click.option(
    "--up",
    default=None,
    metavar="X,Y,Z",
    help="Gravity up in the map frame (the teach run's first camera frame). Default: the map's stored "
    "gravity (vtr teach --up), else the map's -y, as for a level first camera.",
)
@confidence_options
@click.option(
    "--step",
    "step_m",
    type=click.FloatRange(min=0.0, min_open=True),
    default=0.25,
    show_default=True,
    help="Offset grid step (m).",
)
@click.option(
    "--max",
    "max_m",
    type=click.FloatRange(min=0.0, min_open=True),
    default=20.0,
    show_default=True,
    help="Largest offset scanned (m).",
)
def envelope_cmd(
    model_path: Path,
    map_path: Path,
    out: Path,
    force: bool,
    up: str | None,
    l_min: float,
    c_bar: float | None,
    delta: float | None,
    step_m: float,
    max_m: float,
) -> None:
    """For every taught vertex: how far left/right/up/down the vehicle may move (camera as taught)
    before mu - c_bar sigma < L_min."""
    from perception_model.model import PerceptionModel

    from ..app.perception import DIRECTIONS, localization_envelope, write_envelope

    c_bar = resolve_c_bar(c_bar, delta)
    check_output(out, force, folder=True, option="--out", inputs=(model_path, map_path))
    model = PerceptionModel.load(model_path)
    up_map = None if up is None else _parse_vector(up, "--up")
    bars: list[Any] = []

    def progress(done: int, total: int) -> None:  # a bar on a terminal, a line every 10 vertices in a log
        if not bars:
            bars.append(make_bar(total, "envelope", "vertex", every=10))
        bars[0].update(done - bars[0].n)
        if done == total:
            bars[0].close()

    rows = localization_envelope(
        model, map_path, l_min=l_min, c_bar=c_bar, up_map=up_map, step_m=step_m, max_m=max_m, progress=progress
    )
    csv_path, png = write_envelope(rows, out, l_min=l_min, title=f"{map_path.name}: localization envelope")
    for d in DIRECTIONS:
        vals = [r.distance_m[d] for r in rows]
        click.echo(
            f"{d:>5s}: min {min(vals):6.2f} m, median {sorted(vals)[len(vals) // 2]:6.2f} m, "
            f"{sum(r.capped[d] for r in rows)} of {len(rows)} vertices beyond {max_m:g} m "
            "(capped: not a result)"
        )
    n_extra = sum(r.any_extrapolated for r in rows)
    if n_extra:
        click.echo(
            f"warning: at {n_extra} of {len(rows)} vertices the envelope rests on landmarks seen at angles "
            f"beyond the model's valid range (parallax <= {math.degrees(model.alpha_max):.1f} deg, view <= "
            f"{math.degrees(model.theta_max):.1f} deg): extrapolated (see the *_extrapolated columns of "
            "envelope.csv)",
            err=True,
        )
    click.echo(f"wrote {csv_path} and {png}")


if __name__ == "__main__":  # pragma: no cover
    main()
