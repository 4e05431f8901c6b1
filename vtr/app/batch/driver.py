"""A whole batch: checks everything checkable first, resumes what is done, runs the rest on the cluster, writes
``summary.csv`` and, with ``--fit``, the model.

``OUT`` must be apart from every source and config (neither inside one nor holding one), and nothing vtr did not
make there (a symbolic link as a route folder) is written through. The library never prints: progress goes to a
callback, the result is returned. See the README's "Batches" section and ``docs/outputs.md``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ...errors import ConfigError, DataError
from ...io.outputs import check_apart, check_no_links
from ...parallel import available_cores, resolve_threads
from ..outputs import OutputFolder
from ..runfiles.run_json import STATUS_FINISHED
from .cluster import MAX_WORKERS_PER_CORE, _DaskClient, _run_on, check_scheduler, check_workers
from .layout import RESUMED, SUMMARY_CSV, TEACH_FOLDER
from .lock import BatchLock
from .manifest import Manifest, RunSpec
from .model_fit import fit_repeats
from .options import BatchOptions
from .outcome import BatchResult, RunOutcome, checked_run, outcome_from_folder, write_summary_csv
from .resume import key_change, run_key
from .tls import check_scheduler_tls


def check_inputs(manifest: Manifest) -> None:
    """Every source and config file of the manifest exists (checked before anything runs)."""
    for spec in manifest.runs():
        if not spec.source.exists():
            raise DataError(f"{manifest.path}: route {spec.route!r} {spec.name}: {spec.source}: no such file or folder")
        if spec.config is not None and not spec.config.is_file():
            raise DataError(f"{manifest.path}: route {spec.route!r} {spec.name}: {spec.config}: no such config file")


def run_batch(
    manifest: Manifest,
    out: str | Path,
    options: BatchOptions | None = None,
    progress: Callable[[RunOutcome, int, int], None] | None = None,
) -> BatchResult:
    """Run every teach and repeat of ``manifest`` into ``out`` on a Dask cluster; see the module doc."""
    opts = options or BatchOptions()
    out = Path(out)
    workers = check_batch(manifest, out, opts)
    own = OutputFolder.prepare(out, names=[SUMMARY_CSV])
    with BatchLock(out):
        return _run_batch(manifest, out, own, opts, workers, progress)


def check_batch(manifest: Manifest, out: Path, opts: BatchOptions) -> int:
    """Everything checkable before a batch starts (inputs exist, ``--workers``, ``--scheduler``, ``out`` apart
    from every source and config); returns the local cluster's size."""

    check_inputs(manifest)
    check_scheduler_tls(opts.scheduler)
    workers = check_workers(opts.workers) if opts.scheduler is None else (opts.workers or available_cores())
    check_scheduler(opts.scheduler)
    if opts.scheduler is None and opts.threads is not None:  # sizes that multiply: processes x threads
        cores = available_cores()
        threads = resolve_threads(opts.threads, "--threads")
        if workers * threads > MAX_WORKERS_PER_CORE * cores:
            raise ConfigError(
                f"--workers {workers} x --threads {opts.threads} is {workers * threads} threads on "
                f"{cores} cores; at most {MAX_WORKERS_PER_CORE * cores}"
            )
    check_apart(Path(out), [p for spec in manifest.runs() for p in (spec.source, spec.config)])
    for route in manifest.routes:
        if (Path(out) / route.name).exists():
            check_no_links(Path(out), Path(out) / route.name / TEACH_FOLDER)
    return workers


def _run_batch(
    manifest: Manifest,
    out: Path,
    own: OutputFolder,
    opts: BatchOptions,
    workers: int,
    progress: Callable[[RunOutcome, int, int], None] | None,
) -> BatchResult:
    runs = manifest.runs()
    for route in manifest.routes:
        check_no_links(out, out / route.name)
    t0 = time.perf_counter()
    outcomes: dict[RunSpec, RunOutcome] = {}
    done = 0

    def report(spec: RunSpec, outcome: RunOutcome) -> None:
        nonlocal done
        outcomes[spec] = outcome
        done += 1
        if progress is not None:
            progress(outcome, done, len(runs))

    pending: list[tuple[RunSpec, dict[str, Any], str | None]] = []
    resumed: list[tuple[RunSpec, RunOutcome]] = []  # every run.json is checked before anything is reported
    teach_keys: dict[str, dict[str, Any]] = {}
    keys: dict[tuple[str, str], dict[str, Any]] = {}
    for spec in runs:
        key = run_key(
            spec, None if spec.is_teach else teach_keys[spec.route], [keys[spec.route, name] for name in spec.after]
        )
        keys[spec.route, spec.name] = key
        if spec.is_teach:
            teach_keys[spec.route] = key
        folder = spec.folder(out)
        doc = checked_run(folder)
        changed = key_change(folder, key) if doc is not None else None
        if doc is not None and doc.get("status", STATUS_FINISHED) == STATUS_FINISHED and changed is None:
            resumed.append((spec, outcome_from_folder(spec, folder, RESUMED)))
        else:
            pending.append(
                (
                    spec,
                    key,
                    changed if doc is not None and doc.get("status", STATUS_FINISHED) == STATUS_FINISHED else None,
                )
            )
    for spec, outcome in resumed:
        report(spec, outcome)
    threads = opts.threads
    if threads is None and opts.scheduler is None:
        threads = max(1, available_cores() // workers)
    where = opts.scheduler or f"local cluster of {workers} workers"
    if pending:
        with _DaskClient(opts, workers) as client:
            _run_on(client, pending, outcomes, out, threads, opts, report)
    ordered = [outcomes[s] for s in runs]
    result = BatchResult(out, ordered, time.perf_counter() - t0, where)
    result.summary_csv = own.write(SUMMARY_CSV, write_summary_csv, ordered)
    if opts.fit:
        result.fit = fit_repeats(manifest, out, ordered)
    return result
