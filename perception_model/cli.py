"""The ``perception-model`` command: fit, evaluate and apply the perception model.

    perception-model fit LANDMARKS.csv|.parquet... --out DIR [--method binned|mle]   # DIR/model.json, DIR/fit.png
    perception-model evaluate DIR/model.json LANDMARKS.csv|.parquet... [--out DIR] [--json]
    perception-model constraint DIR/model.json --landmarks L.csv --positions P.csv [--out DIR | --out -]

The conventions of both console scripts (one-line usage errors, ``--out DIR`` always a folder, ``--force``
to replace outputs, ``--json`` a flag) are written in ``perception_model.commandline``.

This package imports nothing from ``vtr`` and its command knows no maps: the ``perception-model`` console
script installed with ``vtr`` (``vtr.cli.perception_model``) holds ``fit`` and ``evaluate`` from here and
declares the map-aware commands itself (``constraint`` with ``--map`` as well as ``--landmarks``,
``envelope``), built from the options and helpers of ``constraint`` here (``landmarks_option``,
``confidence_options``, ``constraint_output_options``, ``resolve_c_bar``, ``report_constraint``...).

A thin adapter over the library: known errors (``PerceptionModelError``, unreadable files)
become one line ``perception-model: error: ...`` on stderr and exit code 1; library warnings are
shown as ``perception-model: warning: ...``. Angles are printed in the model's unit. The defaults of the
options are the library's (``perception_model.settings``); ``fit`` and ``evaluate`` build one
``FitSettings`` record from their options (bin widths converted from degrees there, once).
"""

from __future__ import annotations

import csv
import json
import math
import os
import sys
import warnings
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from .commandline import OneLineGroup, force_option, version_option
from .errors import InputDataError, PerceptionModelError, PerceptionModelWarning
from .outputs import existing_output, replace_file, replace_text
from .plots import figure_problem, plot_fit
from .settings import (
    CI_METHODS,
    METHODS,
    MIN_BOOTSTRAP,
    THESIS_C_BAR,
    THESIS_L_MIN,
    THESIS_PITCH_DOWN_RAD,
    UNIT_SCALE,
    FitSettings,
)

if TYPE_CHECKING:
    import numpy as np

PROG = "perception-model"
DIST = "vtr"  # the distribution that ships this package
#: The defaults the options show: the fit's settings record (bin widths shown in degrees, the CLI's unit) and
#: the thesis camera pitch in degrees.
_FIT = FitSettings()
_PITCH_DEG = math.degrees(THESIS_PITCH_DOWN_RAD)


class _Group(OneLineGroup):
    """Click group that reports known errors and warnings in one line each."""

    def invoke(self, ctx: click.Context) -> Any:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                return super().invoke(ctx)
            except BrokenPipeError:  # output piped into e.g. `head`: stop quietly
                devnull = os.open(os.devnull, os.O_WRONLY)
                os.dup2(devnull, sys.stdout.fileno())
                sys.exit(1)
            except (PerceptionModelError, OSError) as err:
                _flush_warnings(caught)
                click.echo(f"{PROG}: error: {_one_line(err)}", err=True)
                sys.exit(1)
            finally:
                _flush_warnings(caught)


def _one_line(err: BaseException) -> str:
    if isinstance(err, OSError) and err.filename:
        return f"{err.filename}: {err.strerror or err}"
    return " ".join(str(err).split())


def _flush_warnings(caught: list[warnings.WarningMessage]) -> None:
    while caught:
        w = caught.pop(0)
        click.echo(f"{PROG}: warning: {_one_line(Exception(str(w.message)))}", err=True)


def _version() -> str:
    from importlib.metadata import version

    return version(DIST)


def check_output(path: Path, force: bool, *, folder: bool = False, option: str | None = None,
                 inputs: tuple[Path | None, ...] = ()) -> None:
    """The output rule of every command (:func:`perception_model.outputs.existing_output`: never without
    ``--force`` over an output, never through a link or over one of ``inputs``) as an error."""
    problem = existing_output(path, force, folder=folder, option=option, inputs=inputs)
    if problem is not None:
        raise InputDataError(problem)


def deprecated(message: str) -> None:
    warnings.warn(message, PerceptionModelWarning, stacklevel=2)


@click.group(cls=_Group, name=PROG)
@version_option(_version(), PROG)
def main() -> None:
    """Perception model for visual teach and repeat: p = c1 cos(c2 theta) exp(c3 alpha)."""


def bin_options(command: Callable[..., Any]) -> Callable[..., Any]:
    """The (alpha, theta) bin widths used by fitting and by R^2 in evaluation (degrees)."""
    for name, default, what in (("--theta-bin", _FIT.theta_bin_deg, "View-angle"),
                                ("--alpha-bin", _FIT.alpha_bin_deg, "Parallax")):
        command = click.option(name, type=click.FloatRange(min=0.0, min_open=True), default=default,
                               show_default=True, help=f"{what} bin width (degrees).")(command)
    return command


# --------------------------------------------------------------------------- fit
@main.command("fit")
@click.argument("landmarks", nargs=-1, required=True, type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(path_type=Path),
    help="Output folder: model.json and fit.png (the figure). Deprecated: a FILE.json path writes that file.",
)
@force_option("model.json and the figure")
@click.option(
    "--method",
    type=click.Choice(METHODS),
    default=_FIT.method,
    show_default=True,
    help="binned: thesis protocol (weighted LSQ on bin frequencies); mle: Bernoulli likelihood.",
)
@click.option(
    "--plot",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Write the figure (observed inlier frequency per (alpha, theta) bin beside the fitted surface) here "
    "instead of OUT/fit.png.",
)
@click.option(
    "--unit",
    type=click.Choice(list(UNIT_SCALE)),
    default=_FIT.angle_unit,
    show_default=True,
    help="Angle unit of the fitted constants.",
)
@click.option(
    "--holdout",
    type=click.FloatRange(0.0, 1.0, max_open=True),
    default=_FIT.holdout_fraction,
    show_default=True,
    help="Fraction of localizations held out for evaluation.",
)
@click.option("--seed", type=int, default=_FIT.seed, show_default=True, help="Seed of the hold-out split/bootstrap.")
@bin_options
@click.option(
    "--min-bin-count",
    type=click.IntRange(min=1),
    default=_FIT.min_bin_count,
    show_default=True,
    help="Bins with fewer observations are not used.",
)
@click.option(
    "--ci",
    type=click.Choice(CI_METHODS),
    default=_FIT.ci,
    show_default=True,
    help="Confidence intervals of the binned fit (MLE always uses the Fisher information).",
)
@click.option(
    "--bootstrap",
    "n_bootstrap",
    type=click.IntRange(min=MIN_BOOTSTRAP),
    default=_FIT.n_bootstrap,
    show_default=True,
    help="Bootstrap replicates for --ci bootstrap.",
)
def fit_cmd(
    landmarks: tuple[Path, ...],
    out: Path,
    force: bool,
    method: str,
    plot: Path | None,
    unit: str,
    holdout: float,
    seed: int,
    alpha_bin: float,
    theta_bin: float,
    min_bin_count: int,
    ci: str,
    n_bootstrap: int,
) -> None:
    """Fit the model to landmarks files (.csv or .parquet): OUT/model.json and OUT/fit.png."""
    from .fit import fit_observations
    from .landmarks_file import FIT_FIELDS, read_landmarks_files

    if out.suffix.lower() == ".json":
        deprecated(f"--out {out}: a model file is deprecated; give a folder (--out DIR writes DIR/model.json and "
                   "DIR/fit.png)")
        model_path = out
    else:
        check_output(out, force, folder=True, option="--out", inputs=landmarks)
        model_path = out / "model.json"
        plot = out / "fit.png" if plot is None else plot
    check_output(model_path, force, inputs=landmarks)
    if plot is not None:
        problem = figure_problem(plot)
        if problem is not None:
            raise InputDataError(f"--plot {problem}")
        check_output(plot, force, inputs=(*landmarks, model_path))
    obs = read_landmarks_files(landmarks, FIT_FIELDS)
    settings = FitSettings.from_degrees(
        alpha_bin_deg=alpha_bin, theta_bin_deg=theta_bin, min_bin_count=min_bin_count, method=method,
        angle_unit=unit, holdout_fraction=holdout, seed=seed, ci=ci, n_bootstrap=n_bootstrap,
    )  # fmt: skip
    result = fit_observations(obs, settings)
    check_output(model_path, force, inputs=landmarks)      # again: the fit may have taken minutes
    if plot is not None:
        check_output(plot, force, inputs=(*landmarks, model_path))
    model_path.parent.mkdir(parents=True, exist_ok=True)
    data = obs.describe()
    result.model.save(model_path, fit=result.to_dict(), data=data)
    click.echo(_fit_summary(result, data))
    click.echo(f"wrote {model_path}")
    if plot is not None:
        plot_fit(result, plot, settings.min_bin_count)
        click.echo(f"wrote {plot}")


def _fit_summary(result: Any, data: dict[str, Any]) -> str:
    from .model import THESIS_CONSTANTS_DEG

    unit = result.model.angle_unit
    lines = [
        f"data: {data['n_observations']} observations ({data['n_inliers']} inliers) in "
        f"{data['n_localizations']} localizations from {len(data['files'])} file(s)",
        f"fit ({result.method}, {result.n} training observations, {result.n_bins} bins): "
        f"p = c1 cos(c2 theta) exp(c3 alpha), angles in {unit}",
    ]
    pct = round(100 * result.confidence)
    for c in result.intervals:
        lines.append(
            f"  {c.name} = {c.estimate:+.5g}   {pct}% CI [{c.low:+.5g}, {c.high:+.5g}]  "
            f"(s.e. {c.std_err:.2g}, {result.ci_method})"
        )
    if result.c1_at_bound:
        lines.append(
            "  c1 is at its bound 1 (the model is a probability): unconstrained, the data would push it above 1"
        )
    if unit == "deg":
        lines.append("  thesis: c = ({:.3f}, {:.3f}, {:.3f})".format(*THESIS_CONSTANTS_DEG))
    lines.append(
        f"  R^2 (bins, count-weighted) = {result.r2:.4f}   log-loss = {result.log_loss:.4f}"
        f"{'' if result.converged else '   WARNING: optimizer did not converge: ' + result.message}"
    )
    if result.holdout is not None:
        lines.append("held out:")
        lines.extend("  " + ln for ln in _evaluation_lines(result.holdout))
    return "\n".join(lines)


def _evaluation_lines(ev: Any) -> list[str]:
    lines = [
        f"n = {ev.n} ({ev.n_inliers} inliers)   log-loss = {ev.log_loss:.4f}   Brier = {ev.brier:.4f}   "
        f"R^2 (bins) = {ev.r2:.4f} over {ev.n_bins} bins",
        "calibration:   predicted bin     n   mean predicted   observed  (s.e.)",
    ]
    for c in ev.calibration:
        lines.append(
            f"               [{c.p_low:.1f}, {c.p_high:.1f})  {c.n:8d}   {c.mean_predicted:14.4f}   "
            f"{c.observed:8.4f}  ({c.std_err:.4f})"
        )
    return lines


# --------------------------------------------------------------------------- evaluate
@main.command("evaluate")
@click.argument("model_path", metavar="MODEL.json", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("landmarks", nargs=-1, required=True, type=click.Path(dir_okay=False, path_type=Path))
@bin_options
@click.option("--min-bin-count", type=click.IntRange(min=1), default=_FIT.min_bin_count, show_default=True)
@click.option("--calibration-bins", type=click.IntRange(min=1), default=_FIT.calibration_bins, show_default=True)
@click.option(
    "--out",
    "out",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Output folder: evaluation.json.",
)
@force_option("evaluation.json")
@click.option(
    "--json",
    "json_flag",
    is_flag=False,
    flag_value="-",
    default=None,
    metavar="",
    help="Print the results as JSON on stdout (instead of the table). Deprecated: --json FILE writes FILE.",
)
def evaluate_cmd(
    model_path: Path,
    landmarks: tuple[Path, ...],
    alpha_bin: float,
    theta_bin: float,
    min_bin_count: int,
    calibration_bins: int,
    out: Path | None,
    force: bool,
    json_flag: str | None,
) -> None:
    """Report log-loss, calibration and R^2 of a model on (held-out) landmarks files (.csv or .parquet)."""
    from .fit import evaluate
    from .landmarks_file import FIT_FIELDS, read_landmarks_files
    from .model import PerceptionModel

    inputs = (model_path, *landmarks)
    if out is not None:
        check_output(out, force, folder=True, option="--out", inputs=inputs)
    json_out = None if out is None else out / "evaluation.json"
    if json_flag not in (None, "-"):
        deprecated(f"--json {json_flag}: a file after --json is deprecated; use --out DIR (DIR/evaluation.json) "
                   "or --json alone (JSON on stdout)")
        json_out = Path(json_flag)
    if json_out is not None:
        check_output(json_out, force, inputs=inputs)
    model = PerceptionModel.load(model_path)
    obs = read_landmarks_files(landmarks, FIT_FIELDS)
    settings = FitSettings.from_degrees(alpha_bin_deg=alpha_bin, theta_bin_deg=theta_bin,
                                        min_bin_count=min_bin_count, calibration_bins=calibration_bins)
    ev = evaluate(model, obs.samples(), settings)
    c1, c2, c3 = model.constants
    results = json.dumps({"model": str(model_path), "data": obs.describe(), "evaluation": ev.to_dict()}, indent=2)
    if json_flag == "-":
        click.echo(results)
    else:
        click.echo(f"model {model_path}: c = ({c1:.4g}, {c2:.4g}, {c3:.4g}) [{model.angle_unit}]")
        click.echo(f"data: {obs.source_names}")
        for line in _evaluation_lines(ev):
            click.echo(line)
    if json_out is not None:
        check_output(json_out, force, inputs=inputs)
        json_out.parent.mkdir(parents=True, exist_ok=True)
        replace_text(json_out, results + "\n")
        click.echo(f"wrote {json_out}", err=json_flag == "-")


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
    for option in reversed((
        click.option("--l-min", type=float, default=THESIS_L_MIN, show_default=True,
                     help="Minimum inlier count L_min."),
        click.option("--c-bar", type=float, default=None,
                     help=f"Normal quantile c_bar [default: {THESIS_C_BAR:g}, or from --delta]."),
        click.option("--delta", type=click.FloatRange(0.0, 0.5, min_open=True, max_open=True), default=None,
                     help="Allowed failure probability; sets c_bar = sqrt(2) erfinv(1 - 2 delta)."),
    )):
        command = option(command)
    return command


def constraint_output_options(command: Any) -> Any:
    """``--exact/--no-exact``, ``--out`` and ``--force`` of a per-position constraint table."""
    for option in reversed((
        click.option("--exact/--no-exact", default=True, show_default=True,
                     help="Also compute the exact Poisson-binomial failure probability."),
        click.option("--out", "out", type=click.Path(allow_dash=True, path_type=Path), default=None,
                     help="Output folder: constraint.csv, the per-position table ('-': the CSV on stdout, the "
                     "summary on stderr). Deprecated: a FILE.csv path writes that file."),
        force_option("constraint.csv"),
    )):
        command = option(command)
    return command


def resolve_c_bar(c_bar: float | None, delta: float | None) -> float:
    """The normal quantile from ``--c-bar`` or ``--delta`` (at most one), ``THESIS_C_BAR`` by default."""
    from .constraint import c_bar_from_delta

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
    help=f"Camera pitch below the horizon (degrees) for yaw-defined axes [default: {_PITCH_DEG:g}].",
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
    from .io import read_positions
    from .model import PerceptionModel

    to_stdout, csv_path = constraint_output(out, force, (model_path, landmarks_path, positions_path))
    cbar = resolve_c_bar(c_bar, delta)
    model = PerceptionModel.load(model_path)
    path = read_positions(positions_path)
    table = constraint_on_landmarks(model, landmarks_path, path, l_min, cbar, pitch_deg, yaw_deg, taught_camera,
                                    exact)
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
    from .constraint import delta_from_c_bar

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
        replace_file(csv_path, write)        # whole, never through a link (refused before the work)
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

    from .constraint import PerceptionConstraint, normal_tail, poisson_binomial_tail
    from .io import read_points

    pitch = _PITCH_DEG if pitch_deg is None else pitch_deg
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


if __name__ == "__main__":  # pragma: no cover
    main()
