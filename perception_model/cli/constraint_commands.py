"""``perception-model constraint`` and the options and helpers of every constraint table (shared with the map-aware
commands of ``vtr.cli.perception_model``): mu, sigma and the chance-constraint margin along a path, printed and
written as ``constraint.csv``. See ``docs/perception_model.md`` ("Chance constraint").
"""

from __future__ import annotations

import csv
import math
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from ..commandline import force_option
from ..errors import InputDataError
from ..outputs import replace_file
from ..settings import (
    THESIS_C_BAR,
    THESIS_L_MIN,
)

if TYPE_CHECKING:
    import numpy as np

from .common import PITCH_DEG, check_output, deprecated, main


# --------------------------------------------------------------------------- constraint
def _parse_vector(text: str, name: str) -> np.ndarray:
    import numpy as np

    try:
        vec = np.array([float(v) for v in text.split(",")])
    except ValueError:
        raise InputDataError(f"{name} must be three comma-separated numbers, got {text!r}") from None
    if vec.shape != (3,) or not np.all(np.isfinite(vec)):
        raise InputDataError(f"{name} must be three finite comma-separated numbers, got {text!r}")
    return vec


# The options of `constraint` (and of vtr's map-aware commands, which share them): one declaration each.
def landmarks_option(*, required: bool) -> Any:
    """``--landmarks``: trunk landmark positions in frame o."""
    return click.option(
        "--landmarks",
        "landmarks_path",
        required=required,
        type=click.Path(dir_okay=False, path_type=Path),
        help="Trunk landmark positions x,y,z in frame o (CSV with header, or .npy (M, 3)), metres.",
    )


def taught_camera_option(command: Any) -> Any:
    """``--taught-camera``: the origin of landmarks and positions given in frame o."""
    return click.option(
        "--taught-camera",
        default=None,
        help="Taught (trunk) camera position x,y,z in frame o; landmarks and positions are taken relative to it "
        "[default: 0,0,0; --landmarks only].",
    )(command)


def confidence_options(command: Any) -> Any:
    """``--l-min``, ``--c-bar`` and ``--delta``: the bound of the chance constraint (resolve with
    :func:`resolve_c_bar`)."""
    for option in reversed(
        (
            click.option(
                "--l-min", type=float, default=THESIS_L_MIN, show_default=True, help="Minimum inlier count L_min."
            ),
            click.option(
                "--c-bar",
                type=float,
                default=None,
                help=f"Normal quantile c_bar [default: {THESIS_C_BAR:g}, or from --delta].",
            ),
            click.option(
                "--delta",
                type=click.FloatRange(0.0, 0.5, min_open=True, max_open=True),
                default=None,
                help="Allowed failure probability; sets c_bar = sqrt(2) erfinv(1 - 2 delta).",
            ),
        )
    ):
        command = option(command)
    return command


def constraint_output_options(command: Any) -> Any:
    """``--exact/--no-exact``, ``--out`` and ``--force`` of a per-position constraint table."""
    for option in reversed(
        (
            click.option(
                "--exact/--no-exact",
                default=True,
                show_default=True,
                help="Also compute the exact Poisson-binomial failure probability.",
            ),
            click.option(
                "--out",
                "out",
                type=click.Path(allow_dash=True, path_type=Path),
                default=None,
                help="Output folder: constraint.csv, the per-position table ('-': the CSV on stdout, the "
                "summary on stderr). Deprecated: a FILE.csv path writes that file.",
            ),
            force_option("constraint.csv"),
        )
    ):
        command = option(command)
    return command


def resolve_c_bar(c_bar: float | None, delta: float | None) -> float:
    """The normal quantile from ``--c-bar`` or ``--delta`` (at most one), ``THESIS_C_BAR`` by default."""
    from ..constraint import c_bar_from_delta

    if c_bar is not None and delta is not None:
        raise InputDataError("give at most one of --c-bar and --delta")
    return c_bar_from_delta(delta) if delta is not None else (THESIS_C_BAR if c_bar is None else c_bar)


def constraint_output(out: Path | None, force: bool, inputs: tuple[Path | None, ...] = ()) -> tuple[bool, Path | None]:
    """``--out``: (the table to stdout?, the CSV file to write or None), its output rule checked (never over
    one of ``inputs``)."""
    to_stdout = out is not None and str(out) == "-"
    csv_path = None
    if out is not None and not to_stdout:
        if out.suffix.lower() == ".csv":
            deprecated(f"--out {out}: a CSV file is deprecated; give a folder (--out DIR writes DIR/constraint.csv)")
            csv_path = out
        else:
            check_output(out, force, folder=True, option="--out", inputs=inputs)
            csv_path = out / "constraint.csv"
        check_output(csv_path, force, inputs=inputs)
    return to_stdout, csv_path


@main.command("constraint")
@click.argument("model_path", metavar="MODEL.json", type=click.Path(dir_okay=False, path_type=Path))
@landmarks_option(required=True)
@click.option(
    "--positions",
    "positions_path",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="Camera positions along the path: CSV x,y,z[,yaw | ,yaw_deg] (yaw in radians); frame o.",
)
@taught_camera_option
@confidence_options
@click.option(
    "--pitch-deg",
    type=float,
    default=None,
    help=f"Camera pitch below the horizon (degrees) for yaw-defined axes [default: {PITCH_DEG:g}].",
)
@click.option(
    "--yaw-deg",
    type=float,
    default=None,
    help="Camera yaw (degrees, CCW from x) where the positions file has no yaw column [default: 0].",
)
@constraint_output_options
def constraint_cmd(
    model_path: Path,
    landmarks_path: Path,
    positions_path: Path,
    taught_camera: str | None,
    l_min: float,
    c_bar: float | None,
    delta: float | None,
    pitch_deg: float | None,
    yaw_deg: float | None,
    exact: bool,
    out: Path | None,
    force: bool,
) -> None:
    """Evaluate mu, sigma and the chance-constraint margin along a path.

    Landmarks and positions are in the gravity-aligned frame o (ENU-like, z up); the optical axis
    comes from yaw and --pitch-deg. (The taught-map variant, --map, is the command installed with vtr.)
    """
    from ..io import read_positions
    from ..model import PerceptionModel

    to_stdout, csv_path = constraint_output(out, force, (model_path, landmarks_path, positions_path))
    cbar = resolve_c_bar(c_bar, delta)
    model = PerceptionModel.load(model_path)
    path = read_positions(positions_path)
    table = constraint_on_landmarks(model, landmarks_path, path, l_min, cbar, pitch_deg, yaw_deg, taught_camera, exact)
    report_constraint(table, l_min, cbar, to_stdout, csv_path)


#: A per-position table: header, rows (a list, or an iterator over rows made chunk by chunk), (column, width,
#: format) of the printed columns, the summary's first words.
Table = tuple[list[str], Iterable[list[Any]], list[tuple[str, int, str]], str]
#: The printed columns every constraint table ends with.
COMMON_FMT = [
    ("mu", 8, ".2f"),
    ("sigma", 7, ".2f"),
    ("g", 8, ".2f"),
    ("g_conservative", 8, ".2f"),
    ("p_fail_normal", 10, ".3e"),
]
#: With a CSV written (--out DIR), the terminal shows at most this many rows of the table (the CSV has them all).
MAX_PRINTED_ROWS = 200
#: Positions evaluated at once are bounded so that positions x landmarks stays below this many elements (the
#: evaluation's work arrays are a few of that size: a 2 M-position path is done chunk by chunk, not in GiBs).
MAX_CHUNK_ELEMENTS = 1 << 20
#: A progress line on stderr after each chunk when the path has more positions than this.
PROGRESS_ABOVE_POSITIONS = 50_000


def report_constraint(table: Table, l_min: float, cbar: float, to_stdout: bool, csv_path: Path | None) -> None:
    """Print the summary (and the table unless it goes to stdout as CSV), then write the CSV. Rows are streamed:
    the CSV is written as they come (whole: a temporary file renamed at the end), the terminal shows at most
    :data:`MAX_PRINTED_ROWS` of them when a CSV holds them all."""
    from ..constraint import delta_from_c_bar

    header, rows, fmt, intro = table
    echo = (lambda text: click.echo(text, err=True)) if to_stdout else click.echo
    echo(f"{intro}, L_min = {l_min:g}, c_bar = {cbar:.4g} (delta = {delta_from_c_bar(cbar):.3g})")
    cols = [(name, max(width, len(name)), spec) for name, width, spec in fmt]
    gi = header.index("g")
    stats = {"n": 0, "violated": 0, "worst": -1, "g_worst": math.inf}

    def consume(writer: Any) -> None:
        if writer is not None:
            writer.writerow(header)
        elif not to_stdout:
            echo(" ".join(f"{name:>{width}s}" for name, width, _ in cols))
        for r in rows:
            k = stats["n"]
            g = r[gi]
            stats["violated"] += g < 0
            if g < stats["g_worst"] or stats["worst"] < 0:
                stats["g_worst"], stats["worst"] = g, k
            if writer is not None:
                writer.writerow(r)
            if not to_stdout and (csv_path is None or k < MAX_PRINTED_ROWS):
                if k == 0 and writer is not None:
                    echo(" ".join(f"{name:>{width}s}" for name, width, _ in cols))
                echo(" ".join(f"{r[header.index(name)]:{width}{spec}}" for name, width, spec in cols))
            stats["n"] = k + 1

    if to_stdout:
        consume(csv.writer(sys.stdout, lineterminator="\n"))
    elif csv_path is not None:

        def write(tmp: Path) -> None:
            with tmp.open("w", newline="") as fh:
                consume(csv.writer(fh))

        csv_path.parent.mkdir(parents=True, exist_ok=True)
        replace_file(csv_path, write)  # whole, never through a link (refused before the work)
    else:
        consume(None)
    n = stats["n"]
    if csv_path is not None and n > MAX_PRINTED_ROWS:
        echo(f"... {n - MAX_PRINTED_ROWS} more rows in {csv_path}")
    echo(
        f"constraint mu - c_bar sigma >= L_min violated at {stats['violated']} of {n} positions; "
        f"smallest margin g = {stats['g_worst']:.2f} at index {stats['worst']}"
    )
    if csv_path is not None:
        echo(f"wrote {csv_path}")


def position_chunks(n: int, n_landmarks: int) -> Iterator[slice]:
    """Slices of ``range(n)`` with at most :data:`MAX_CHUNK_ELEMENTS` position-landmark pairs each; a progress line
    on stderr after each one when ``n`` is above :data:`PROGRESS_ABOVE_POSITIONS`."""
    size = max(1, MAX_CHUNK_ELEMENTS // max(n_landmarks, 1))
    for start in range(0, n, size):
        stop = min(n, start + size)
        yield slice(start, stop)
        if n > PROGRESS_ABOVE_POSITIONS:
            click.echo(f"constraint: {stop}/{n} positions", err=True)


def constraint_on_landmarks(
    model: Any,
    landmarks_path: Path,
    path: Any,
    l_min: float,
    cbar: float,
    pitch_deg: float | None,
    yaw_deg: float | None,
    taught_camera: str | None,
    exact: bool,
) -> Table:
    """Per-position rows for landmarks given in frame o, evaluated chunk by chunk as they are consumed."""
    import numpy as np

    from ..constraint import PerceptionConstraint, normal_tail, poisson_binomial_tail
    from ..io import read_points

    pitch = PITCH_DEG if pitch_deg is None else pitch_deg
    origin = _parse_vector("0,0,0" if taught_camera is None else taught_camera, "--taught-camera")
    pts = read_points(landmarks_path) - origin
    pos = path.positions - origin
    yaw = path.yaw if path.yaw is not None else np.full(pos.shape[0], math.radians(yaw_deg or 0.0))
    con = PerceptionConstraint(model, pts, l_min=l_min, c_bar=cbar, pitch_down=math.radians(pitch))
    header = ["index", "x", "y", "z", "yaw_deg", "mu", "sigma", "g", "g_conservative", "p_fail_normal"]
    if exact:
        header.append("p_fail_exact")

    def rows() -> Iterator[list[Any]]:
        for part in position_chunks(pos.shape[0], pts.shape[0]):
            ev = con.evaluate(pos[part], yaw[part], gradient=False)
            for j, i in enumerate(range(part.start, part.stop)):
                row: list[Any] = [
                    i,
                    *path.positions[i].tolist(),
                    math.degrees(float(yaw[i])),
                    float(ev.mu[j]),
                    float(ev.sigma[j]),
                    float(ev.g[j]),
                    float(ev.g_conservative[j]),
                    normal_tail(float(ev.mu[j]), float(ev.sigma[j]), l_min, lower=True),
                ]
                if exact:
                    row.append(poisson_binomial_tail(ev.p[j], l_min, lower=True))
                yield row

    fmt = [("index", 4, "d"), ("x", 8, ".2f"), ("y", 8, ".2f"), ("z", 8, ".2f"), ("yaw_deg", 7, ".1f")]
    fmt += COMMON_FMT + ([("p_fail_exact", 10, ".3e")] if exact else [])
    intro = f"{pts.shape[0]} landmarks, {pos.shape[0]} positions, pitch {pitch:g} deg"
    return header, rows(), fmt, intro
