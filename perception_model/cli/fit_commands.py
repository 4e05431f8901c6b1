"""``perception-model fit`` and ``perception-model evaluate``: one ``FitSettings`` from the options, the library's
fit or evaluation, the summary printed and the outputs written by the output rule. See
``docs/perception_model.md``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from ..commandline import force_option
from ..errors import InputDataError
from ..outputs import replace_text
from ..plots import figure_problem, plot_fit
from ..settings import (
    CI_METHODS,
    METHODS,
    MIN_BOOTSTRAP,
    UNIT_SCALE,
    FitSettings,
)

if TYPE_CHECKING:
    pass

from .common import FIT_DEFAULTS, bin_options, check_output, deprecated, main


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
    default=FIT_DEFAULTS.method,
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
    default=FIT_DEFAULTS.angle_unit,
    show_default=True,
    help="Angle unit of the fitted constants.",
)
@click.option(
    "--holdout",
    type=click.FloatRange(0.0, 1.0, max_open=True),
    default=FIT_DEFAULTS.holdout_fraction,
    show_default=True,
    help="Fraction of localizations held out for evaluation.",
)
@click.option(
    "--seed", type=int, default=FIT_DEFAULTS.seed, show_default=True, help="Seed of the hold-out split/bootstrap."
)
@bin_options
@click.option(
    "--min-bin-count",
    type=click.IntRange(min=1),
    default=FIT_DEFAULTS.min_bin_count,
    show_default=True,
    help="Bins with fewer observations are not used.",
)
@click.option(
    "--ci",
    type=click.Choice(CI_METHODS),
    default=FIT_DEFAULTS.ci,
    show_default=True,
    help="Confidence intervals of the binned fit (MLE always uses the Fisher information).",
)
@click.option(
    "--bootstrap",
    "n_bootstrap",
    type=click.IntRange(min=MIN_BOOTSTRAP),
    default=FIT_DEFAULTS.n_bootstrap,
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
    from ..fit import fit_observations
    from ..landmarks_file import FIT_FIELDS, read_landmarks_files

    if out.suffix.lower() == ".json":
        deprecated(
            f"--out {out}: a model file is deprecated; give a folder (--out DIR writes DIR/model.json and DIR/fit.png)"
        )
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
    check_output(model_path, force, inputs=landmarks)  # again: the fit may have taken minutes
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
    from ..model import THESIS_CONSTANTS_DEG

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
@click.option("--min-bin-count", type=click.IntRange(min=1), default=FIT_DEFAULTS.min_bin_count, show_default=True)
@click.option(
    "--calibration-bins", type=click.IntRange(min=1), default=FIT_DEFAULTS.calibration_bins, show_default=True
)
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
    from ..fit import evaluate
    from ..landmarks_file import FIT_FIELDS, read_landmarks_files
    from ..model import PerceptionModel

    inputs = (model_path, *landmarks)
    if out is not None:
        check_output(out, force, folder=True, option="--out", inputs=inputs)
    json_out = None if out is None else out / "evaluation.json"
    if json_flag not in (None, "-"):
        deprecated(
            f"--json {json_flag}: a file after --json is deprecated; use --out DIR (DIR/evaluation.json) "
            "or --json alone (JSON on stdout)"
        )
        json_out = Path(json_flag)
    if json_out is not None:
        check_output(json_out, force, inputs=inputs)
    model = PerceptionModel.load(model_path)
    obs = read_landmarks_files(landmarks, FIT_FIELDS)
    settings = FitSettings.from_degrees(
        alpha_bin_deg=alpha_bin, theta_bin_deg=theta_bin, min_bin_count=min_bin_count, calibration_bins=calibration_bins
    )
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
