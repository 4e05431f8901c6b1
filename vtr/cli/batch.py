"""``vtr batch``: every teach and repeat of a manifest on a Dask cluster (local by default), resumable."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from . import main
from .common import make_bar
from .summaries import batch_table

if TYPE_CHECKING:
    from ..app.batch import RunOutcome


@main.command("batch")
@click.argument("manifest", type=click.Path(path_type=Path))
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    required=True,
    help="Output folder: OUT/<route>/teach/, OUT/<route>/<repeat>/, summary.csv.",
)
@click.option(
    "--workers",
    type=click.IntRange(min=1),
    default=None,
    help="Worker processes of the local cluster (default: every core; at most 4 per core).",
)
@click.option(
    "--scheduler",
    default=None,
    metavar="ADDRESS",
    help="Run on a running Dask scheduler (tls://HOST:8786 with Dask's TLS config, or tcp:// on a "
    "trusted network) instead of a local cluster.",
)
@click.option(
    "--dashboard", is_flag=True, help="Serve the local cluster's Dask dashboard (on 127.0.0.1 only; off by default)."
)
@click.option(
    "--threads",
    type=click.IntRange(min=0),
    default=None,
    help="Threads per run (features.threads; 0 = every core). Default: cores / workers on a local "
    "cluster, the run's config on a scheduler.",
)
@click.option("--fit", is_flag=True, help="Then fit the perception model to every repeat's landmarks (OUT/fit/).")
def batch_cmd(
    manifest: Path,
    out: Path,
    workers: int | None,
    scheduler: str | None,
    dashboard: bool,
    threads: int | None,
    fit: bool,
) -> None:
    """Run every teach and repeat listed in MANIFEST (YAML) as tasks on a Dask cluster.

    A rerun skips runs already finished; a failing run is recorded (its run.json) and the rest go on.
    """
    from ..app.batch import BatchOptions, check_batch, check_scheduler, check_workers, load_manifest, run_batch

    if scheduler is None:
        check_workers(workers)
    check_scheduler(scheduler)
    spec = load_manifest(manifest)
    n_runs = len(spec.runs())
    bars: list[Any] = []  # the progress bar, made at the first report (errors before it stay one line)

    def bar() -> Any:
        if not bars:  # without a terminal: a line per run
            bars.append(make_bar(n_runs, "runs", "run", every=1, leave=True))
        return bars[0]

    def progress(outcome: RunOutcome, done: int, total: int) -> None:
        bar().set_postfix_str(f"{outcome.route}/{outcome.name} {outcome.status}")
        bar().update(1)

    options = BatchOptions(
        workers=workers,
        scheduler=scheduler,
        threads=threads,
        fit=fit,
        dashboard=dashboard,
        on_dashboard=lambda link: click.echo(f"dashboard: {link}", err=True),
    )
    check_batch(spec, out, options)
    try:
        result = run_batch(spec, out, options, progress)
    except KeyboardInterrupt:
        for b in bars:
            b.close()
        click.echo(f"interrupted: finished runs are kept in {out}; run the same command again to do the rest", err=True)
        sys.exit(130)
    finally:
        for b in bars:
            b.close()
    for line in batch_table(result):
        click.echo(line)
    click.echo(f"wrote {result.summary_csv}")
    if result.fit is not None:
        if "error" in result.fit:
            click.echo(f"fit: not done ({result.fit['error']})", err=True)
        else:
            f = result.fit
            consts = "  ".join(f"{k} {v:+.4g}" for k, v in f["constants"].items())
            click.echo(
                f"fit over {f['files']} repeats, {f['observations']} observations: {consts}  "
                f"R^2 {f['r2']:.3f}; wrote {f['model']}, {f['plot']}"
            )
    if result.failed or (result.fit is not None and "error" in result.fit):
        sys.exit(1)  # a failed run, or a fit asked for and not done
