"""The ``perception-model`` command: fit, evaluate and apply the perception model.

    perception-model fit LANDMARKS.csv... --out model.json [--method binned|mle] [--plot FIG.png]
    perception-model evaluate model.json LANDMARKS.csv...
    perception-model constraint model.json --landmarks L.csv --positions P.csv

A thin adapter over the library: known errors (``PerceptionModelError``, unreadable files)
become one line ``perception-model: error: ...`` on stderr and exit code 1; library warnings are
shown as ``perception-model: warning: ...``. Angles are printed in the model's unit.
"""

from __future__ import annotations

import csv
import json
import math
import os
import sys
import warnings
from pathlib import Path
from typing import Any

import click
import numpy as np

from .errors import InputDataError, PerceptionModelError

PROG = "perception-model"
DIST = "vtr"  # the distribution that ships this package
#: Defaults of the CLI (library defaults in degrees for display).
DEFAULT_ALPHA_BIN_DEG = 1.0
DEFAULT_THETA_BIN_DEG = 2.5
DEFAULT_PITCH_DEG = 50.0
PLOT_DPI = 120
PLOT_SIZE_IN = (12.0, 4.8)
PLOT_CONTOURS = (0.05, 0.1, 0.2, 0.3, 0.4)


class _Group(click.Group):
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


@click.group(cls=_Group)
@click.version_option(None, package_name=DIST, prog_name=PROG, message="%(prog)s %(version)s")
def main() -> None:
    """Perception model for visual teach and repeat: p = c1 cos(c2 theta) exp(c3 alpha)."""


# --------------------------------------------------------------------------- fit
@main.command("fit")
@click.argument("landmarks", nargs=-1, required=True, type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="Model JSON to write.",
)
@click.option(
    "--method",
    type=click.Choice(["binned", "mle"]),
    default="binned",
    show_default=True,
    help="binned: thesis protocol (weighted LSQ on bin frequencies); mle: Bernoulli likelihood.",
)
@click.option(
    "--plot",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="PNG: observed inlier frequency over (alpha, theta) beside the fitted surface.",
)
@click.option(
    "--unit",
    type=click.Choice(["deg", "rad"]),
    default="deg",
    show_default=True,
    help="Angle unit of the fitted constants.",
)
@click.option(
    "--holdout",
    type=click.FloatRange(0.0, 1.0, max_open=True),
    default=0.2,
    show_default=True,
    help="Fraction of localizations held out for evaluation.",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the hold-out split/bootstrap.")
@click.option(
    "--alpha-bin",
    type=click.FloatRange(min=0.0, min_open=True),
    default=DEFAULT_ALPHA_BIN_DEG,
    show_default=True,
    help="Parallax bin width (degrees).",
)
@click.option(
    "--theta-bin",
    type=click.FloatRange(min=0.0, min_open=True),
    default=DEFAULT_THETA_BIN_DEG,
    show_default=True,
    help="View-angle bin width (degrees).",
)
@click.option(
    "--min-bin-count",
    type=click.IntRange(min=1),
    default=10,
    show_default=True,
    help="Bins with fewer observations are not used.",
)
@click.option(
    "--ci",
    type=click.Choice(["sandwich", "bootstrap"]),
    default="sandwich",
    show_default=True,
    help="Confidence intervals of the binned fit (MLE always uses the Fisher information).",
)
@click.option(
    "--bootstrap",
    "n_bootstrap",
    type=click.IntRange(min=2),
    default=200,
    show_default=True,
    help="Bootstrap replicates for --ci bootstrap.",
)
def fit_cmd(
    landmarks: tuple[Path, ...],
    out: Path,
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
    """Fit the model to landmarks.csv files and write model.json."""
    from .fit import BinSpec, fit_observations
    from .io import read_landmarks_csvs

    obs = read_landmarks_csvs(landmarks)
    bins = BinSpec(math.radians(alpha_bin), math.radians(theta_bin), min_bin_count)
    result = fit_observations(
        obs,
        method=method,
        angle_unit=unit,
        holdout_fraction=holdout,
        seed=seed,
        bins=bins,
        ci=ci,
        n_bootstrap=n_bootstrap,
    )  # type: ignore[arg-type]
    out.parent.mkdir(parents=True, exist_ok=True)
    result.model.save(out, fit=result.to_dict(), data=obs.describe())
    click.echo(_fit_summary(result, obs.describe()))
    click.echo(f"wrote {out}")
    if plot is not None:
        _plot_fit(result, plot)
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


def _plot_fit(result: Any, path: Path) -> None:
    """Observed inlier frequency per (alpha, theta) bin beside the fitted surface (cf. thesis Fig. 7.3)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    model = result.model
    k = model.unit_scale
    unit = model.angle_unit
    binned = result.binned
    a_edges, t_edges = binned.alpha_edges, binned.theta_edges
    freq = np.where(binned.count_grid >= 1, binned.frequency_grid, np.nan)
    a_mid = 0.5 * (a_edges[1:] + a_edges[:-1])
    t_mid = 0.5 * (t_edges[1:] + t_edges[:-1])
    fitted = model.probability(a_mid[:, None], t_mid[None, :])
    vmax = float(np.nanmax([np.nanmax(freq) if np.isfinite(freq).any() else 0.0, fitted.max(), 1e-3]))
    fig, axes = plt.subplots(1, 2, figsize=PLOT_SIZE_IN, sharey=True, constrained_layout=True)
    for ax, data, title in (
        (axes[0], freq, "observed inlier frequency"),
        (axes[1], fitted, f"fitted model ({result.method})"),
    ):
        mesh = ax.pcolormesh(a_edges * k, t_edges * k, data.T, vmin=0.0, vmax=vmax, cmap="viridis")
        cs = ax.contour(
            a_mid * k,
            t_mid * k,
            fitted.T,
            levels=[c for c in PLOT_CONTOURS if c < vmax],
            colors="k",
            linewidths=0.8,
        )
        ax.clabel(cs, fontsize=7)
        ax.set_xlabel(f"parallax angle alpha [{unit}]")
        ax.set_title(title)
    axes[0].set_ylabel(f"view angle theta [{unit}]")
    c1, c2, c3 = model.constants
    fig.suptitle(
        f"p = {c1:.3f} cos({c2:.4f} theta) exp({c3:.4f} alpha)   R^2 = {result.r2:.3f}, n = {result.n}"
    )
    fig.colorbar(mesh, ax=axes, label="probability of inlier")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=PLOT_DPI)
    plt.close(fig)


# --------------------------------------------------------------------------- evaluate
@main.command("evaluate")
@click.argument("model_path", metavar="MODEL.json", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("landmarks", nargs=-1, required=True, type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--alpha-bin",
    type=click.FloatRange(min=0.0, min_open=True),
    default=DEFAULT_ALPHA_BIN_DEG,
    show_default=True,
    help="Parallax bin width for R^2 (degrees).",
)
@click.option(
    "--theta-bin",
    type=click.FloatRange(min=0.0, min_open=True),
    default=DEFAULT_THETA_BIN_DEG,
    show_default=True,
    help="View-angle bin width for R^2 (degrees).",
)
@click.option("--min-bin-count", type=click.IntRange(min=1), default=10, show_default=True)
@click.option("--calibration-bins", type=click.IntRange(min=1), default=10, show_default=True)
@click.option(
    "--json",
    "json_out",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Also write the results as JSON.",
)
def evaluate_cmd(
    model_path: Path,
    landmarks: tuple[Path, ...],
    alpha_bin: float,
    theta_bin: float,
    min_bin_count: int,
    calibration_bins: int,
    json_out: Path | None,
) -> None:
    """Report log-loss, calibration and R^2 of a model on (held-out) landmarks.csv files."""
    from .fit import BinSpec, evaluate
    from .io import read_landmarks_csvs
    from .model import PerceptionModel

    model = PerceptionModel.load(model_path)
    obs = read_landmarks_csvs(landmarks)
    bins = BinSpec(math.radians(alpha_bin), math.radians(theta_bin), min_bin_count)
    ev = evaluate(
        model,
        obs.alpha,
        obs.theta,
        obs.inlier,
        bins=bins,
        calibration_bins=calibration_bins,
        source=obs.source_names,
    )
    c1, c2, c3 = model.constants
    click.echo(f"model {model_path}: c = ({c1:.4g}, {c2:.4g}, {c3:.4g}) [{model.angle_unit}]")
    click.echo(f"data: {obs.source_names}")
    for line in _evaluation_lines(ev):
        click.echo(line)
    if json_out is not None:
        json_out.write_text(
            json.dumps(
                {"model": str(model_path), "data": obs.describe(), "evaluation": ev.to_dict()}, indent=2
            )
            + "\n"
        )
        click.echo(f"wrote {json_out}")


# --------------------------------------------------------------------------- constraint
def _parse_vector(text: str, name: str) -> np.ndarray:
    try:
        vec = np.array([float(v) for v in text.split(",")])
    except ValueError:
        raise InputDataError(f"{name} must be three comma-separated numbers, got {text!r}") from None
    if vec.shape != (3,) or not np.all(np.isfinite(vec)):
        raise InputDataError(f"{name} must be three finite comma-separated numbers, got {text!r}")
    return vec


@main.command("constraint")
@click.argument("model_path", metavar="MODEL.json", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--landmarks",
    "landmarks_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Trunk landmark positions x,y,z in frame o (CSV with header, or .npy (M, 3)), metres.",
)
@click.option(
    "--map",
    "map_path",
    type=click.Path(path_type=Path),
    default=None,
    help="A vtr map (not available yet: use --landmarks).",
)
@click.option(
    "--positions",
    "positions_path",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="Camera positions along the path: CSV x,y,z[,yaw | ,yaw_deg] in frame o (yaw in radians).",
)
@click.option(
    "--taught-camera",
    default="0,0,0",
    show_default=True,
    help="Taught (trunk) camera position x,y,z in frame o; landmarks and positions are taken relative to it.",
)
@click.option("--l-min", type=float, default=30.0, show_default=True, help="Minimum inlier count L_min.")
@click.option(
    "--c-bar", type=float, default=None, help="Normal quantile c_bar [default: 3, or from --delta]."
)
@click.option(
    "--delta",
    type=click.FloatRange(0.0, 0.5, min_open=True, max_open=True),
    default=None,
    help="Allowed failure probability; sets c_bar = sqrt(2) erfinv(1 - 2 delta).",
)
@click.option(
    "--pitch-deg",
    type=float,
    default=DEFAULT_PITCH_DEG,
    show_default=True,
    help="Camera pitch below the horizon (degrees).",
)
@click.option(
    "--yaw-deg",
    type=float,
    default=0.0,
    show_default=True,
    help="Camera yaw (degrees, CCW from x) where the positions file has no yaw column.",
)
@click.option(
    "--exact/--no-exact",
    default=True,
    show_default=True,
    help="Also compute the exact Poisson-binomial failure probability.",
)
@click.option(
    "--out",
    "out",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Write the per-position table as CSV.",
)
def constraint_cmd(
    model_path: Path,
    landmarks_path: Path | None,
    map_path: Path | None,
    positions_path: Path,
    taught_camera: str,
    l_min: float,
    c_bar: float | None,
    delta: float | None,
    pitch_deg: float,
    yaw_deg: float,
    exact: bool,
    out: Path | None,
) -> None:
    """Evaluate mu, sigma and the chance-constraint margin along a path."""
    from .constraint import (
        THESIS_C_BAR,
        PerceptionConstraint,
        c_bar_from_delta,
        delta_from_c_bar,
        normal_tail,
        poisson_binomial_tail,
    )
    from .io import read_points, read_positions
    from .model import PerceptionModel

    if (landmarks_path is None) == (map_path is None):
        raise InputDataError("give exactly one of --landmarks FILE or --map MAP")
    if map_path is not None:
        raise InputDataError(
            f"--map {map_path}: reading landmarks from a vtr map is not available yet "
            "(the map store is not implemented); export the trunk landmarks to CSV and use "
            "--landmarks"
        )
    if c_bar is not None and delta is not None:
        raise InputDataError("give at most one of --c-bar and --delta")
    cbar = c_bar_from_delta(delta) if delta is not None else (THESIS_C_BAR if c_bar is None else c_bar)
    model = PerceptionModel.load(model_path)
    origin = _parse_vector(taught_camera, "--taught-camera")
    assert landmarks_path is not None
    pts = read_points(landmarks_path) - origin
    path = read_positions(positions_path)
    pos = path.positions - origin
    yaw = path.yaw if path.yaw is not None else np.full(pos.shape[0], math.radians(yaw_deg))
    con = PerceptionConstraint(model, pts, l_min=l_min, c_bar=cbar, pitch_down=math.radians(pitch_deg))
    ev = con.evaluate(pos, yaw, gradient=False)
    fail_normal = [
        normal_tail(float(m), float(s), l_min, lower=True) for m, s in zip(ev.mu, ev.sigma, strict=True)
    ]
    fail_exact = [poisson_binomial_tail(p, l_min, lower=True) for p in ev.p] if exact else None

    header = ["index", "x", "y", "z", "yaw_deg", "mu", "sigma", "g", "g_conservative", "p_fail_normal"]
    if fail_exact is not None:
        header.append("p_fail_exact")
    rows = []
    for i in range(pos.shape[0]):
        row: list[Any] = [
            i,
            *path.positions[i].tolist(),
            math.degrees(float(yaw[i])),
            float(ev.mu[i]),
            float(ev.sigma[i]),
            float(ev.g[i]),
            float(ev.g_conservative[i]),
            fail_normal[i],
        ]
        if fail_exact is not None:
            row.append(fail_exact[i])
        rows.append(row)
    click.echo(
        f"{pts.shape[0]} landmarks, {pos.shape[0]} positions, L_min = {l_min:g}, c_bar = {cbar:.4g} "
        f"(delta = {delta_from_c_bar(cbar):.3g}), pitch {pitch_deg:g} deg"
    )
    click.echo(
        f"{'i':>4s} {'x':>8s} {'y':>8s} {'z':>8s} {'yaw':>7s} {'mu':>8s} {'sigma':>7s} {'g':>8s} "
        f"{'g_c':>8s} {'P_fail(N)':>10s}" + (f" {'P_fail(ex)':>10s}" if fail_exact is not None else "")
    )
    for r in rows:
        line = (
            f"{r[0]:4d} {r[1]:8.2f} {r[2]:8.2f} {r[3]:8.2f} {r[4]:7.1f} {r[5]:8.2f} {r[6]:7.2f} {r[7]:8.2f} "
            f"{r[8]:8.2f} {r[9]:10.3e}"
        )
        if fail_exact is not None:
            line += f" {r[10]:10.3e}"
        click.echo(line)
    worst = int(np.argmin(ev.g))
    n_bad = int((ev.g < 0).sum())
    click.echo(
        f"constraint mu - c_bar sigma >= L_min violated at {n_bad} of {pos.shape[0]} positions; "
        f"smallest margin g = {ev.g[worst]:.2f} at index {worst}"
    )
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        with out.open("w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(header)
            writer.writerows(rows)
        click.echo(f"wrote {out}")


if __name__ == "__main__":  # pragma: no cover
    main()
