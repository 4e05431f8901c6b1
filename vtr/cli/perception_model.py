"""The ``perception-model`` console script as installed with ``vtr``: the package's commands plus the map.

``perception_model.cli`` imports nothing from ``vtr``; this group holds the same commands (``fit``,
``evaluate``, ``constraint``), hands ``constraint --map`` its map reader
(``vtr.app.perception.evaluate_on_map``) through the click context, and adds the map-only command

    perception-model envelope MODEL.json --map MAP --out DIR [--up X,Y,Z] [--l-min 30] [--c-bar 3 | --delta D]

(``DIR/envelope.csv``, ``DIR/envelope.png``; see ``vtr.app.perception.localization_envelope``).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import click

from perception_model.cli import PROG, _Group, _parse_vector, check_output
from perception_model.cli import main as _package_main
from perception_model.commandline import force_option
from perception_model.settings import THESIS_C_BAR, THESIS_L_MIN

from ..errors import VtrError


class _MapGroup(_Group):
    """Known errors of both packages become one line."""

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except VtrError as err:
            click.echo(f"{PROG}: error: {err}", err=True)
            sys.exit(1)


def _map_reader(*args: Any, **kwargs: Any) -> Any:
    from ..app.perception import evaluate_on_map

    return evaluate_on_map(*args, **kwargs)


@click.group(cls=_MapGroup, name=PROG, context_settings={"obj": {"evaluate_on_map": _map_reader}})
@click.version_option(None, package_name="vtr", prog_name=PROG, message="%(prog)s %(version)s")
def main() -> None:
    """Fit, evaluate and apply the perception model (with the taught-map commands of vtr)."""


for _name, _cmd in _package_main.commands.items():
    main.add_command(_cmd, _name)


@main.command("envelope")
@click.argument("model_path", metavar="MODEL.json", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--map", "map_path", required=True, type=click.Path(path_type=Path), help="A taught vtr map.")
@click.option("--out", "out", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Output folder: envelope.csv and envelope.png.")
@force_option("envelope.csv and envelope.png")
@click.option("--up", default="0,-1,0", show_default=True,
              help="Gravity up in the map frame (the teach run's first camera frame); 0,-1,0 for a level camera.")
@click.option("--l-min", type=float, default=THESIS_L_MIN, show_default=True, help="Minimum inlier count L_min.")
@click.option("--c-bar", type=float, default=None,
              help=f"Normal quantile c_bar [default: {THESIS_C_BAR:g}, or from --delta].")
@click.option("--delta", type=click.FloatRange(0.0, 0.5, min_open=True, max_open=True), default=None,
              help="Allowed failure probability; sets c_bar = sqrt(2) erfinv(1 - 2 delta).")
@click.option("--step", "step_m", type=click.FloatRange(min=0.0, min_open=True), default=0.25, show_default=True,
              help="Offset grid step (m).")
@click.option("--max", "max_m", type=click.FloatRange(min=0.0, min_open=True), default=20.0, show_default=True,
              help="Largest offset scanned (m).")
def envelope_cmd(model_path: Path, map_path: Path, out: Path, force: bool, up: str, l_min: float,
                 c_bar: float | None, delta: float | None, step_m: float, max_m: float) -> None:
    """For every taught vertex: how far left/right/up/down the vehicle may move (camera as taught)
    before mu - c_bar sigma < L_min."""
    from perception_model.constraint import c_bar_from_delta
    from perception_model.errors import InputDataError
    from perception_model.model import PerceptionModel

    from ..app.perception import DIRECTIONS, localization_envelope, write_envelope

    if c_bar is not None and delta is not None:
        raise InputDataError("give at most one of --c-bar and --delta")
    c_bar = c_bar_from_delta(delta) if delta is not None else (THESIS_C_BAR if c_bar is None else c_bar)
    check_output(out, force, folder=True, option="--out")
    model = PerceptionModel.load(model_path)
    rows = localization_envelope(model, map_path, l_min=l_min, c_bar=c_bar, up_map=_parse_vector(up, "--up"),
                                 step_m=step_m, max_m=max_m)
    csv_path, png = write_envelope(rows, out, l_min=l_min, title=f"{map_path.name}: localization envelope")
    for d in DIRECTIONS:
        vals = [r.distance_m[d] for r in rows]
        click.echo(f"{d:>5s}: min {min(vals):6.2f} m, median {sorted(vals)[len(vals) // 2]:6.2f} m, "
                   f"{sum(r.capped[d] for r in rows)} of {len(rows)} vertices beyond {max_m:g} m "
                   "(capped: not a result)")
    n_extra = sum(r.any_extrapolated for r in rows)
    if n_extra:
        click.echo(f"warning: at {n_extra} of {len(rows)} vertices the envelope rests on landmarks seen at angles "
                   f"beyond the model's valid range (parallax <= {math.degrees(model.alpha_max):.1f} deg, view <= "
                   f"{math.degrees(model.theta_max):.1f} deg): extrapolated (see the *_extrapolated columns of "
                   "envelope.csv)",
                   err=True)
    click.echo(f"wrote {csv_path} and {png}")


if __name__ == "__main__":  # pragma: no cover
    main()
