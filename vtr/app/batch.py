"""``vtr batch``: every teach and repeat of a manifest as tasks on a Dask cluster, resumable.

A manifest (YAML) lists routes, each a teach source and any number of repeat sources::

    config: base.yaml          # optional: defaults for every run (a `vtr config` file)
    frames: "0::2"             # optional: default frame selection of every run
    routes:
      - name: field_a
        teach: /data/field_a/teach
        repeats: [/data/field_a/rep1, {source: /data/field_a/rep2, frames: "0:500", name: rep2_short}]

A run given as a mapping takes ``source`` and optionally ``name`` (its output folder), ``frames``,
``config`` and ``format``; a route may set ``frames``, ``config`` and ``format`` for its own runs.
Relative paths are relative to the manifest's folder. Each run writes ``OUT/<route>/teach/`` or
``OUT/<route>/<repeat name>/`` (a repeat's default name is its source's name without suffix), the
same files as ``vtr teach --out`` / ``vtr repeat --out``; the taught map is ``OUT/<route>/teach/route.vtrmap``
and each repeat appends to its own copy of it (so repeats of a route run in parallel, never write the
same file, and give the same result whatever the order they run in).

Resume: a run is done when its folder's ``run.json`` says ``finished`` (run.json is written last);
anything else (no run.json: interrupted; ``failed``) is deleted and run again. A failing run writes
run.json with status ``failed`` and its error; the other runs go on (its route's repeats are
``blocked`` when a teach fails). A worker process that dies mid-run (killed, out of memory) is
replaced and its run started again by Dask, from an empty folder.

The library never prints: progress goes to a callback, the summary is returned.
"""

from __future__ import annotations

import csv
import logging
import re
import shutil
import sqlite3
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import yaml

from ..config import Config
from ..errors import ConfigError, DataError
from .runlog import STATUS_FAILED, STATUS_FINISHED, RunLog, read_run, run_status

MAP_NAME = "route.vtrmap"          # the taught map inside OUT/<route>/teach/ (each repeat holds a copy)
TEACH_FOLDER = "teach"
SUMMARY_CSV = "summary.csv"
FIT_FOLDER = "fit"
DEFAULT_RETRIES = 2                # extra attempts of a task that raised inside Dask (its worker died: see above)
NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")   # route and run names are folder names
RUN_KEYS = {"source", "name", "frames", "config", "format"}
ROUTE_KEYS = {"name", "teach", "repeats", "frames", "config", "format"}
TOP_KEYS = {"routes", "frames", "config", "format"}

# statuses of a run in a batch
FINISHED = "finished"     # ran now, to the end
RESUMED = "resumed"       # finished by an earlier invocation; skipped
FAILED = "failed"         # stopped on an error (run.json holds it)
BLOCKED = "blocked"       # a repeat whose route's teach did not finish
DONE = (FINISHED, RESUMED)


# ------------------------------------------------------------------------------------------ manifest


@dataclass(frozen=True)
class RunSpec:
    """One teach or repeat of a manifest: where its data is and where it writes."""

    route: str
    name: str                       # output folder inside OUT/<route>/ ("teach" for the teach)
    source: Path
    frames: str | None = None
    config: Path | None = None
    fmt: str | None = None

    @property
    def is_teach(self) -> bool:
        return self.name == TEACH_FOLDER

    @property
    def kind(self) -> str:
        return "teach" if self.is_teach else "repeat"

    def folder(self, out: Path) -> Path:
        return Path(out) / self.route / self.name


@dataclass(frozen=True)
class RouteSpec:
    name: str
    teach: RunSpec
    repeats: tuple[RunSpec, ...]


@dataclass(frozen=True)
class Manifest:
    path: Path
    routes: tuple[RouteSpec, ...]

    def runs(self) -> list[RunSpec]:
        """Every run, each route's teach before its repeats."""
        return [r for route in self.routes for r in (route.teach, *route.repeats)]


def load_manifest(path: str | Path) -> Manifest:
    """Read and check a batch manifest; errors name the file and the field."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such manifest file")
    try:
        doc = yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: cannot parse YAML ({str(err).splitlines()[0]})") from err
    if not isinstance(doc, dict) or not isinstance(doc.get("routes"), list) or not doc["routes"]:
        raise ConfigError(f"{path}: expected a mapping with a non-empty list 'routes'")
    _check_keys(doc, TOP_KEYS, f"{path}")
    base = path.parent
    defaults = _defaults(doc, {}, base, f"{path}")
    routes, seen = [], set()
    for i, entry in enumerate(doc["routes"]):
        where = f"{path}: routes[{i}]"
        if not isinstance(entry, dict):
            raise ConfigError(f"{where}: expected a mapping with name, teach, repeats")
        _check_keys(entry, ROUTE_KEYS, where)
        name = _name(entry.get("name"), f"{where}.name")
        where = f"{path}: route {name!r}"
        if name in seen:
            raise ConfigError(f"{where}: route name used twice")
        seen.add(name)
        if "teach" not in entry:
            raise ConfigError(f"{where}: no 'teach' source")
        route_defaults = _defaults(entry, defaults, base, where)
        teach = _run(entry["teach"], name, route_defaults, base, f"{where}.teach", TEACH_FOLDER)
        repeats_doc = entry.get("repeats") or []
        if not isinstance(repeats_doc, list):
            raise ConfigError(f"{where}.repeats: expected a list")
        repeats, names = [], {TEACH_FOLDER}
        for j, rep in enumerate(repeats_doc):
            run = _run(rep, name, route_defaults, base, f"{where}.repeats[{j}]", None)
            if run.name in names:
                raise ConfigError(f"{where}.repeats[{j}]: output folder {run.name!r} is used twice in the route "
                                  f"(give the repeat a distinct 'name')")
            names.add(run.name)
            repeats.append(run)
        routes.append(RouteSpec(name, teach, tuple(repeats)))
    return Manifest(path, tuple(routes))


def _check_keys(doc: dict, allowed: set[str], where: str) -> None:
    unknown = sorted(set(doc) - allowed)
    if unknown:
        raise ConfigError(f"{where}: unknown key {unknown[0]!r} (allowed: {', '.join(sorted(allowed))})")


def _name(value: Any, where: str) -> str:
    if not isinstance(value, str) or not NAME_PATTERN.match(value):
        raise ConfigError(f"{where}: {value!r} is not a usable folder name (letters, digits, '.', '_', '-')")
    return value


def _path(value: Any, base: Path, where: str) -> Path:
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{where}: expected a path, got {value!r}")
    p = Path(value).expanduser()
    return p if p.is_absolute() else base / p


def _defaults(doc: dict, inherited: dict, base: Path, where: str) -> dict:
    out = dict(inherited)
    if doc.get("frames") is not None:
        out["frames"] = str(doc["frames"])
    if doc.get("config") is not None:
        out["config"] = _path(doc["config"], base, f"{where}.config")
    if doc.get("format") is not None:
        out["fmt"] = str(doc["format"])
    return out


def _run(entry: Any, route: str, defaults: dict, base: Path, where: str, name: str | None) -> RunSpec:
    if isinstance(entry, str):
        entry = {"source": entry}
    if not isinstance(entry, dict) or "source" not in entry:
        raise ConfigError(f"{where}: expected a source path or a mapping with 'source'")
    _check_keys(entry, RUN_KEYS, where)
    source = _path(entry["source"], base, f"{where}.source")
    own = _defaults(entry, defaults, base, where)
    if name is None:
        name = _name(entry.get("name", source.stem), f"{where}.name")
    elif "name" in entry:
        raise ConfigError(f"{where}: a teach has no 'name' (it writes OUT/<route>/teach)")
    return RunSpec(route, name, source, own.get("frames"), own.get("config"), own.get("fmt"))


# ---------------------------------------------------------------------------------------- one run


@dataclass(frozen=True)
class RunOutcome:
    """What one run of a batch did (one row of the summary table)."""

    route: str
    name: str
    kind: str
    status: str                     # FINISHED, RESUMED, FAILED, BLOCKED
    frames: int | None = None
    vertices: int | None = None
    localized: int | None = None    # repeats: localized vertices
    median_inliers: float | None = None
    seconds: float | None = None    # wall time of the run (as recorded in its run.json)
    error: str | None = None

    @property
    def localized_pct(self) -> float | None:
        if self.localized is None or not self.vertices:
            return None
        return 100.0 * self.localized / self.vertices

    @property
    def ok(self) -> bool:
        return self.status in DONE


def outcome_from_folder(spec: RunSpec, folder: Path, status: str) -> RunOutcome:
    """The outcome recorded in ``folder/run.json``."""
    doc = read_run(folder) or {}
    s = doc.get("summary") or {}
    return RunOutcome(spec.route, spec.name, spec.kind, status, frames=s.get("frames"), vertices=s.get("vertices"),
                      localized=s.get("localized"), median_inliers=s.get("median_inliers"), seconds=s.get("seconds"),
                      error=doc.get("error"))


def run_config(spec: RunSpec, threads: int | None) -> Config:
    config = Config.load(spec.config) if spec.config is not None else Config()
    if threads is not None:
        config.features.threads = threads
    return config


def copy_map(src: Path, dst: Path) -> None:
    """Copy a closed map file consistently (SQLite's online backup: WAL content included)."""
    if not src.is_file():
        raise DataError(f"{src}: the taught map is missing (its teach did not finish)")
    s, d = sqlite3.connect(src), sqlite3.connect(dst)   # read-write: the last one out removes the WAL files
    try:
        s.backup(d)
    finally:
        d.close()
        s.close()


def execute_run(spec: RunSpec, out: str, threads: int | None, teach: RunOutcome | None = None,
                on_start: Callable[[RunSpec, Path], None] | None = None) -> RunOutcome:
    """One teach or repeat (a Dask task: paths in, a small record out). Never raises for a run's own error:
    it is written to the run's run.json and returned."""
    from .pipeline import repeat_command, teach_command

    folder = spec.folder(Path(out))
    if run_status(folder) == STATUS_FINISHED:       # a retry after the run had finished
        return outcome_from_folder(spec, folder, RESUMED)
    if teach is not None and not teach.ok:
        return RunOutcome(spec.route, spec.name, spec.kind, BLOCKED, error=f"teach of {spec.route} {teach.status}")
    shutil.rmtree(folder, ignore_errors=True)       # what an interrupted or failed attempt left
    folder.mkdir(parents=True)
    if on_start is not None:
        on_start(spec, folder)
    t0 = time.perf_counter()
    config = Config()
    try:
        config = run_config(spec, threads)
        _opencv_threads(config)
        if spec.is_teach:
            teach_command(spec.source, folder / MAP_NAME, spec.frames, config, folder, spec.fmt)
        else:
            copy_map(folder.parent / TEACH_FOLDER / MAP_NAME, folder / MAP_NAME)
            repeat_command(spec.source, folder / MAP_NAME, folder, spec.frames, config, spec.fmt)
    except Exception as err:  # noqa: BLE001 - recorded in run.json; the batch goes on
        message = f"{type(err).__name__}: {err}"
        RunLog(folder, spec.kind, config, [spec.source]).write(
            {"seconds": time.perf_counter() - t0, "traceback": traceback.format_exc(limit=8)},
            status=STATUS_FAILED, error=message)
        return outcome_from_folder(spec, folder, FAILED)
    return outcome_from_folder(spec, folder, FINISHED)


def _opencv_threads(config: Config) -> None:
    """OpenCV's own pool follows the run's thread count (a batch worker runs one run per core)."""
    import cv2

    from ..parallel import resolve_threads

    cv2.setNumThreads(resolve_threads(config.features.threads))


# ------------------------------------------------------------------------------------------- batch


@dataclass
class BatchResult:
    out: Path
    outcomes: list[RunOutcome]
    seconds: float
    workers: str                                   # "local N" or the scheduler address
    fit: dict[str, Any] | None = None              # --fit: report (paths, numbers) or error
    summary_csv: Path | None = None

    @property
    def failed(self) -> list[RunOutcome]:
        return [o for o in self.outcomes if not o.ok]

    def table(self) -> list[str]:
        """The summary table, one line per run."""
        head = (f"{'route':<14} {'run':<16} {'status':<9} {'frames':>6} {'localized':>9} {'inliers':>7} "
                f"{'time s':>7}  error")
        lines = [head, "-" * len(head)]
        for o in self.outcomes:
            loc = f"{o.localized_pct:.1f} %" if o.localized_pct is not None else "-"
            inl = f"{o.median_inliers:.0f}" if o.median_inliers is not None else "-"
            sec = f"{o.seconds:.1f}" if o.seconds is not None else "-"
            frames = str(o.frames) if o.frames is not None else "-"
            lines.append(f"{o.route:<14} {o.name:<16} {o.status:<9} {frames:>6} {loc:>9} {inl:>7} {sec:>7}  "
                         f"{(o.error or '').splitlines()[0] if o.error else ''}")
        n = {s: sum(o.status == s for o in self.outcomes) for s in (FINISHED, RESUMED, FAILED, BLOCKED)}
        lines.append(f"{len(self.outcomes)} runs: {n[FINISHED]} finished, {n[RESUMED]} resumed (done before), "
                     f"{n[FAILED]} failed, {n[BLOCKED]} blocked; {self.seconds:.1f} s on {self.workers}")
        return lines


SUMMARY_FIELDS = [f.name for f in fields(RunOutcome)] + ["localized_pct"]


def write_summary_csv(path: Path, outcomes: list[RunOutcome]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(SUMMARY_FIELDS)
        for o in outcomes:
            w.writerow([getattr(o, k) if getattr(o, k) is not None else "" for k in SUMMARY_FIELDS])


@dataclass
class BatchOptions:
    workers: int | None = None          # local cluster size (default: every core)
    scheduler: str | None = None        # address of a running Dask scheduler instead of a local cluster
    threads: int | None = None          # threads per run (default: local: cores // workers; remote: config)
    retries: int = DEFAULT_RETRIES
    fit: bool = False
    on_start: Callable[[RunSpec, Path], None] | None = None   # called in the worker before each run (tests)
    cluster_kwargs: dict[str, Any] = field(default_factory=dict)


def check_inputs(manifest: Manifest) -> None:
    """Every source and config file of the manifest exists (checked before anything runs)."""
    for spec in manifest.runs():
        if not spec.source.exists():
            raise DataError(f"{manifest.path}: route {spec.route!r} {spec.name}: {spec.source}: no such file or folder")
        if spec.config is not None and not spec.config.is_file():
            raise DataError(f"{manifest.path}: route {spec.route!r} {spec.name}: {spec.config}: no such config file")


def run_batch(manifest: Manifest, out: str | Path, options: BatchOptions | None = None,
              progress: Callable[[RunOutcome, int, int], None] | None = None) -> BatchResult:
    """Run every teach and repeat of ``manifest`` into ``out`` on a Dask cluster; see the module doc."""
    from ..parallel import available_cores

    opts = options or BatchOptions()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    runs = manifest.runs()
    check_inputs(manifest)
    t0 = time.perf_counter()
    outcomes: dict[RunSpec, RunOutcome] = {}
    done = 0

    def report(spec: RunSpec, outcome: RunOutcome) -> None:
        nonlocal done
        outcomes[spec] = outcome
        done += 1
        if progress is not None:
            progress(outcome, done, len(runs))

    pending = []
    for spec in runs:
        if run_status(spec.folder(out)) == STATUS_FINISHED:
            report(spec, outcome_from_folder(spec, spec.folder(out), RESUMED))
        else:
            pending.append(spec)
    workers = opts.workers or available_cores()
    threads = opts.threads
    if threads is None and opts.scheduler is None:
        threads = max(1, available_cores() // workers)
    where = opts.scheduler or f"local cluster of {workers} workers"
    if pending:
        with _DaskClient(opts, workers) as client:
            _run_on(client, pending, outcomes, out, threads, opts, report)
    ordered = [outcomes[s] for s in runs]
    result = BatchResult(out, ordered, time.perf_counter() - t0, where)
    result.summary_csv = out / SUMMARY_CSV
    write_summary_csv(result.summary_csv, ordered)
    if opts.fit:
        result.fit = fit_repeats(manifest, out, ordered)
    return result


class _DaskClient:
    """A Dask client on ``scheduler`` or on a new local cluster (closed on exit)."""

    def __init__(self, opts: BatchOptions, workers: int):
        self.opts, self.workers = opts, workers
        self.cluster = None

    def __enter__(self):
        import dask
        from distributed import Client, LocalCluster

        if self.opts.scheduler:
            self.client = Client(self.opts.scheduler)
            return self.client
        kwargs = {"n_workers": self.workers, "threads_per_worker": 1, "processes": True,
                  "dashboard_address": ":0", "silence_logs": logging.ERROR, **self.opts.cluster_kwargs}
        # a dead worker's task is given to another one this many times before it counts as failed
        with dask.config.set({"distributed.scheduler.allowed-failures": max(self.opts.retries, 1)}):
            self.cluster = LocalCluster(**kwargs)
        self.client = Client(self.cluster)
        return self.client

    def __exit__(self, *exc) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def _run_on(client, pending: list[RunSpec], outcomes: dict, out: Path, threads: int | None, opts: BatchOptions,
            report: Callable[[RunSpec, RunOutcome], None]) -> None:
    from distributed import as_completed

    futures: dict[Any, RunSpec] = {}
    teach_of: dict[str, Any] = {}
    for spec in pending:                           # teaches come before their repeats (Manifest.runs order)
        teach: Any = None
        if not spec.is_teach:                      # its teach's future, or its outcome when resumed
            teach = teach_of.get(spec.route)
            if teach is None:
                teach = next(o for s, o in outcomes.items() if s.route == spec.route and s.is_teach)
        fut = client.submit(execute_run, spec, str(out), threads, teach, opts.on_start, retries=opts.retries,
                            key=f"{spec.route}/{spec.name}-{time.time_ns()}", pure=False)
        futures[fut] = spec
        if spec.is_teach:
            teach_of[spec.route] = fut
    try:
        for fut in as_completed(list(futures)):
            spec = futures[fut]
            try:
                outcome = fut.result()
            except Exception as err:  # noqa: BLE001 - the task itself died (e.g. its worker, too many times)
                outcome = RunOutcome(spec.route, spec.name, spec.kind, FAILED, error=f"{type(err).__name__}: {err}")
            report(spec, outcome)
    except BaseException:
        for fut in futures:
            fut.cancel()
        raise


# --------------------------------------------------------------------------------------------- fit


def repeat_landmark_files(manifest: Manifest, out: Path, outcomes: list[RunOutcome]) -> Iterator[Path]:
    ok = {(o.route, o.name) for o in outcomes if o.ok and o.kind == "repeat"}
    for spec in manifest.runs():
        if (spec.route, spec.name) in ok:
            yield spec.folder(out) / "landmarks.csv"


def fit_repeats(manifest: Manifest, out: Path, outcomes: list[RunOutcome]) -> dict[str, Any]:
    """One perception-model fit over every finished repeat's landmarks.csv, streamed (one file in memory at a
    time; the binned fit of the thesis protocol, sandwich intervals): OUT/fit/model.json and fit.png.
    Returns what to report, or the error."""
    from perception_model.cli import plot_fit
    from perception_model.errors import PerceptionModelError
    from perception_model.fit import fit_binned_stream
    from perception_model.landmarks_file import FIT_FIELDS, read_landmarks

    files = list(repeat_landmark_files(manifest, out, outcomes))
    folder = out / FIT_FOLDER
    if not files:
        return {"error": "no finished repeat to fit"}

    def chunks():
        for f in files:
            obs = read_landmarks(f, fields=FIT_FIELDS)
            yield obs.alpha, obs.theta, obs.inlier

    try:
        result = fit_binned_stream(chunks, source=f"{len(files)} repeats under {out}")
    except PerceptionModelError as err:
        return {"error": str(err), "files": len(files)}
    folder.mkdir(parents=True, exist_ok=True)
    data = {"files": [str(f) for f in files], "n_observations": result.n, "n_inliers": result.n_inliers}
    result.model.save(folder / "model.json", fit=result.to_dict(), data=data)
    plot_fit(result, folder / "fit.png")
    return {"model": folder / "model.json", "plot": folder / "fit.png", "files": len(files),
            "observations": result.n, "constants": {c.name: c.estimate for c in result.intervals},
            "r2": result.r2, "log_loss": result.log_loss}
