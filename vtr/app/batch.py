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

Resume: a run is done when its folder's ``run.json`` says ``finished`` (run.json is written last) and its
``batch_key.json`` matches what would make it now (source path and size, frames, format, the run's config
without its thread count, the vtr version, and for a repeat its teach's key): a changed manifest reruns
what changed, and the summary says what changed. A finished run whose key changed is rerun beside it
(``OUT/<route>/.vtr-rerun-<run>/``) and its outputs are moved in only when the rerun finished
(:meth:`vtr.app.outputs.OutputFolder.adopt`): a failed rerun leaves the finished outputs (a taught map may be
the only copy) and says so. Anything else (no run.json: interrupted; ``failed``) has the files vtr made in its
folder removed (:mod:`vtr.app.outputs`: only those) and runs again.
One batch at a time writes an output folder (``OUT/.vtr-batch.lock``, an ``flock``); ``OUT`` must be apart
from every source (neither inside one nor holding one), and nothing vtr did not make there (a symbolic
link as a route folder) is written through.

The local cluster listens on loopback only, with TLS and temporary credentials made for the batch
(``Security.temporary()``): only the batch's own client and workers can connect. Its dashboard is off
unless asked (``dashboard=True``: on loopback). A failing run writes
run.json with status ``failed`` and its error; the other runs go on (its route's repeats are
``blocked`` when a teach fails). A worker process that dies mid-run (killed, out of memory) is
replaced and its run started again by Dask, from an empty folder.

The library never prints: progress goes to a callback, the summary is returned.
"""

from __future__ import annotations

import csv
import fcntl
import hashlib
import json
import logging
import os
import re
import signal
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import yaml

from .. import __version__
from ..config import Config, DuplicateKeyError, UniqueKeyLoader
from ..errors import ConfigError, DataError, OutputError, VtrError
from .fingerprint import source_fingerprint
from .outputs import RECORD, OutputFolder, check_apart, check_no_links
from .runfiles.run_json import STATUS_FAILED, STATUS_FINISHED, RunLog, read_run

MAP_NAME = "route.vtrmap"          # the taught map inside OUT/<route>/teach/ (each repeat holds a copy)
TEACH_FOLDER = "teach"
SUMMARY_CSV = "summary.csv"
FIT_FOLDER = "fit"
DEFAULT_RETRIES = 2                # extra attempts of a task that raised inside Dask (its worker died: see above)
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")   # route and run names are folder names (fullmatch)
LOCK_NAME = ".vtr-batch.lock"      # one batch per OUT (flock)
#: the HTTP routes the batch's own cluster serves when its dashboard is off
HEALTH_ONLY_ROUTES = ("distributed.http.health",)
KEY_NAME = "batch_key.json"        # what made a run (resume compares it)
RESERVED_NAMES = {SUMMARY_CSV, FIT_FOLDER, LOCK_NAME, RECORD}   # OUT's own files: no route may be named so
MAX_WORKERS_PER_CORE = 4           # --workers above this many per core only thrash (each worker is a process)
SCHEDULER_SCHEMES = ("tcp", "tls")
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


class _ManifestLoader(UniqueKeyLoader):
    """YAML as written: no YAML 1.1 base-60 numbers (an unquoted ``frames: 1:10`` is the string "1:10", not 70),
    and no key given twice (:class:`vtr.config.UniqueKeyLoader`)."""


_ManifestLoader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers
            if tag not in ("tag:yaml.org,2002:int", "tag:yaml.org,2002:float")]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()}
for _tag, _pattern, _first in (
        ("tag:yaml.org,2002:int", r"^(?:[-+]?0b[0-1_]+|[-+]?0[0-7_]+|[-+]?(?:0|[1-9][0-9_]*)|[-+]?0x[0-9a-fA-F_]+)$",
         "-+0123456789"),
        ("tag:yaml.org,2002:float", r"^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+][0-9]+)?"
         r"|\.[0-9][0-9_]*(?:[eE][-+][0-9]+)?|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$", "-+0123456789.")):
    _ManifestLoader.add_implicit_resolver(_tag, re.compile(_pattern), list(_first))


def load_manifest(path: str | Path) -> Manifest:
    """Read and check a batch manifest; errors name the file and the field."""
    from perception_model.inputs import input_problem

    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such manifest file")
    problem = input_problem(path)                # a folder, a named pipe or a device: never opened
    if problem is not None:
        raise DataError(f"{path}: {problem}")
    try:
        doc = yaml.load(path.read_text(encoding="utf-8-sig"), Loader=_ManifestLoader)  # noqa: S506 - a SafeLoader
    except DuplicateKeyError as err:
        raise ConfigError(f"{path}: {err}") from None
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: cannot parse YAML ({str(err).splitlines()[0]})") from err
    except RecursionError:
        raise ConfigError(f"{path}: nested too deeply to read (a manifest is routes, runs and their keys)") from None
    except (UnicodeDecodeError, OSError) as err:
        raise ConfigError(f"{path}: cannot read the manifest ({err})") from err
    if not isinstance(doc, dict) or not isinstance(doc.get("routes"), list) or not doc["routes"]:
        raise ConfigError(f"{path}: expected a mapping with a non-empty list 'routes'")
    _check_keys(doc, TOP_KEYS, f"{path}")
    base = path.parent
    defaults = _defaults(doc, {}, base, f"{path}")
    routes: list[RouteSpec] = []
    seen: set[str] = set()
    for i, entry in enumerate(doc["routes"]):
        where = f"{path}: routes[{i}]"
        if not isinstance(entry, dict):
            raise ConfigError(f"{where}: expected a mapping with name, teach, repeats")
        _check_keys(entry, ROUTE_KEYS, where)
        name = _name(entry.get("name"), f"{where}.name")
        where = f"{path}: route {name!r}"
        if name.casefold() in seen:
            raise ConfigError(f"{where}: route name used twice (names differing only in case count as one folder)")
        if name in RESERVED_NAMES or name.casefold() in {n.casefold() for n in RESERVED_NAMES}:
            raise ConfigError(f"{where}: {name!r} is the name of the batch's own output "
                              f"({', '.join(sorted(RESERVED_NAMES))}); rename the route")
        seen.add(name.casefold())
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
            if run.name.casefold() in names:
                raise ConfigError(f"{where}.repeats[{j}]: output folder {run.name!r} is used twice in the route "
                                  f"(give the repeat a distinct 'name')")
            names.add(run.name.casefold())
            repeats.append(run)
        routes.append(RouteSpec(name, teach, tuple(repeats)))
    return Manifest(path, tuple(routes))


def _check_keys(doc: dict, allowed: set[str], where: str) -> None:
    unknown = sorted(set(doc) - allowed)
    if unknown:
        raise ConfigError(f"{where}: unknown key {unknown[0]!r} (allowed: {', '.join(sorted(allowed))})")


def _name(value: Any, where: str) -> str:
    if not isinstance(value, str) or not NAME_PATTERN.fullmatch(value):
        raise ConfigError(f"{where}: {value!r} is not a usable folder name (1-100 letters, digits, '.', '_', '-', "
                          "starting with a letter or digit)")
    return value


def _path(value: Any, base: Path, where: str) -> Path:
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{where}: expected a path, got {value!r}")
    p = Path(value).expanduser()
    return p if p.is_absolute() else base / p


def _defaults(doc: dict, inherited: dict, base: Path, where: str) -> dict:
    out = dict(inherited)
    if doc.get("frames") is not None:
        frames = doc["frames"]
        if not isinstance(frames, str) or any(not c.isprintable() for c in frames):
            raise ConfigError(f"{where}.frames: {frames!r} is not a frame range (write START:STOP:STEP, e.g. "
                              "\"0:100:2\")")
        out["frames"] = frames
    if doc.get("config") is not None:
        out["config"] = _path(doc["config"], base, f"{where}.config")
    if doc.get("format") is not None:
        if not isinstance(doc["format"], str):
            raise ConfigError(f"{where}.format: {doc['format']!r} is not a format name")
        out["fmt"] = doc["format"]
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
        if name == TEACH_FOLDER:
            raise ConfigError(f"{where}.name: {name!r} is the route's teach folder; give the repeat another 'name'")
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
    changed: str | None = None      # why a run finished before was run again (what of its key changed)

    @property
    def localized_pct(self) -> float | None:
        if self.localized is None or not self.vertices:
            return None
        return 100.0 * self.localized / self.vertices

    @property
    def ok(self) -> bool:
        return self.status in DONE


SUMMARY_NUMBERS = {"frames": int, "vertices": int, "localized": int, "median_inliers": float, "seconds": float}


def checked_run(folder: Path) -> dict[str, Any] | None:
    """``folder/run.json`` checked for what the batch reads from it: None when there is none; ``DataError``
    (one line naming the file and the field) when it is not what vtr writes (edited by hand?)."""
    p = Path(folder) / "run.json"
    if not p.exists() and not p.is_symlink():
        return None
    hint = f"; remove {p} to run it again"
    doc = read_run(folder)
    if doc is None:
        raise DataError(f"{p}: not a JSON object as vtr writes it{hint}")
    status = doc.get("status", STATUS_FINISHED)
    if status not in (STATUS_FINISHED, STATUS_FAILED):
        raise DataError(f"{p}: status {status!r} is not {STATUS_FINISHED!r} or {STATUS_FAILED!r}{hint}")
    summary = doc.get("summary", {})
    if not isinstance(summary, dict):
        raise DataError(f"{p}: 'summary' is {type(summary).__name__}, expected a mapping{hint}")
    for key, kind in SUMMARY_NUMBERS.items():
        v = summary.get(key)
        ok = v is None or (not isinstance(v, bool) and isinstance(v, int | float) and (kind is float or
                                                                                    isinstance(v, int)))
        if not ok or (isinstance(v, float) and v != v and key != "median_inliers"):
            raise DataError(f"{p}: 'summary.{key}' is {v!r}, expected {'an integer' if kind is int else 'a number'}"
                            f"{hint}")
    if doc.get("error") is not None and not isinstance(doc["error"], str):
        raise DataError(f"{p}: 'error' is {type(doc['error']).__name__}, expected text{hint}")
    return doc


def outcome_from_folder(spec: RunSpec, folder: Path, status: str, changed: str | None = None) -> RunOutcome:
    """The outcome recorded in ``folder/run.json``."""
    doc = checked_run(folder) or {}
    s = doc.get("summary") or {}
    return RunOutcome(spec.route, spec.name, spec.kind, status, frames=s.get("frames"), vertices=s.get("vertices"),
                      localized=s.get("localized"), median_inliers=s.get("median_inliers"), seconds=s.get("seconds"),
                      error=doc.get("error"), changed=changed)


def run_key(spec: RunSpec, teach_key: dict[str, Any] | None = None) -> dict[str, Any]:
    """What makes a run's result: its source (path, files, bytes, and a fingerprint of their content:
    :func:`vtr.app.fingerprint.source_fingerprint`), frames, format, config (without the thread count: results are
    identical for every count), the vtr version; a repeat's teach key too."""
    config = run_config(spec, None).to_dict()
    config.get("features", {}).pop("threads", None)
    src = spec.source.resolve()
    files = [src] if src.is_file() else [f for f in src.rglob("*") if f.is_file()]
    key: dict[str, Any] = {
        "source": str(src), "source_files": len(files), "source_bytes": sum(f.stat().st_size for f in files),
        "source_content": source_fingerprint(src),
        "frames": spec.frames, "format": spec.fmt,
        "config": hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode()).hexdigest(),
        "version": __version__}
    if teach_key is not None:
        key["teach"] = hashlib.sha256(json.dumps(teach_key, sort_keys=True).encode()).hexdigest()
    return key


def key_change(folder: Path, key: dict[str, Any]) -> str | None:
    """None when ``folder``'s run was made with ``key``; else what changed (for the summary)."""
    try:
        data = OutputFolder(folder).read_own(KEY_NAME)     # never through a link vtr did not make
        old = None if data is None else json.loads(data)
    except (OSError, ValueError):
        old = None
    if not isinstance(old, dict):
        return "no record of what made it"
    diff = [k for k in key if old.get(k) != key[k]]
    if not diff:
        return None
    names = {"source_files": "source", "source_bytes": "source", "source_content": "source", "teach": "its teach"}
    what = sorted({names.get(k, k) for k in diff})
    detail = f" ({old.get('frames')!r} -> {key['frames']!r})" if "frames" in diff else ""
    return f"rerun: {', '.join(what)} changed{detail}"


def run_config(spec: RunSpec, threads: int | None) -> Config:
    config = Config.load(spec.config) if spec.config is not None else Config()
    if threads is not None:
        config.features.threads = threads
    return config


def copy_map(src: Path, dst: Path) -> None:
    """Copy a closed map file consistently (SQLite's online backup: WAL content included)."""
    if not src.is_file():
        raise DataError(f"{src}: the taught map is missing (its teach did not finish)")
    from ..map import copy_map_file

    copy_map_file(src, dst)


#: A rerun of a finished run is built in ``OUT/<route>/<RERUN_PREFIX><run>`` (a run name starts with a letter or
#: digit, so never one of these) and moved into the run's folder only when it finished.
RERUN_PREFIX = ".vtr-rerun-"


def rerun_folder(out: Path, spec: RunSpec) -> Path:
    return Path(out) / spec.route / f"{RERUN_PREFIX}{spec.name}"


def prepare_run_folder(out: Path, spec: RunSpec, folder: Path | None = None) -> OutputFolder:
    """The run's folder inside ``out`` (or ``folder``, its rerun folder) without what an earlier attempt made
    (only the files vtr recorded there; never through a symbolic link: ``OutputError``)."""
    folder = spec.folder(out) if folder is None else folder
    check_no_links(out, folder)
    folder.mkdir(parents=True, exist_ok=True)
    check_no_links(out, folder)
    own = OutputFolder(folder)
    own.clear()
    return own


def execute_run(spec: RunSpec, out: str, threads: int | None, teach: RunOutcome | None = None,
                on_start: Callable[[RunSpec, Path], None] | None = None, key: dict[str, Any] | None = None,
                changed: str | None = None) -> RunOutcome:
    """One teach or repeat (a Dask task: paths in, a small record out). Never raises for a run's own error:
    it is written to the run's run.json and returned."""
    from .pipeline import repeat_command, teach_command

    folder = spec.folder(Path(out))
    doc = checked_run(folder)
    if doc is not None and doc.get("status", STATUS_FINISHED) == STATUS_FINISHED and \
            (key is None or key_change(folder, key) is None):   # a retry after the run had finished
        return outcome_from_folder(spec, folder, RESUMED)
    if teach is not None and not teach.ok:
        return RunOutcome(spec.route, spec.name, spec.kind, BLOCKED, error=f"teach of {spec.route} {teach.status}")
    # A finished run is replaced only by one that finished: a rerun is built beside it and moved in at the end.
    finished_before = doc is not None and doc.get("status", STATUS_FINISHED) == STATUS_FINISHED
    work = rerun_folder(Path(out), spec) if finished_before else folder
    own = prepare_run_folder(Path(out), spec, work)   # what an interrupted, failed or changed attempt made
    if on_start is not None:
        on_start(spec, folder)
    t0 = time.perf_counter()
    config = Config()
    try:
        config = run_config(spec, threads)
        _opencv_threads(config)
        map_path = own.claim(MAP_NAME)
        if spec.is_teach:
            teach_command(spec.source, map_path, spec.frames, config, work, spec.fmt)
        else:
            taught = OutputFolder(folder.parent / TEACH_FOLDER).own_file(MAP_NAME)   # never a planted link
            copy_map(folder.parent / TEACH_FOLDER / MAP_NAME if taught is None else taught, map_path)
            repeat_command(spec.source, map_path, work, spec.frames, config, spec.fmt)
    except Exception as err:  # noqa: BLE001 - recorded in run.json; the batch goes on
        message = f"{type(err).__name__}: {err}"
        if finished_before:
            message += (f" (the rerun failed; the finished outputs of the earlier run are kept in {folder}, the "
                        f"failed attempt's record is {work / 'run.json'})")
        RunLog(work, spec.kind, config, [spec.source]).write(
            {"seconds": time.perf_counter() - t0, "traceback": traceback.format_exc(limit=8)},
            status=STATUS_FAILED, error=message)
        return outcome_from_folder(spec, work, FAILED, changed)
    if key is not None:
        own.write_text(KEY_NAME, json.dumps(key, indent=1))
    if finished_before:
        OutputFolder(folder).adopt(own, last=(KEY_NAME, "run.json"))
    return outcome_from_folder(spec, folder, FINISHED, changed)


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

SUMMARY_FIELDS = [f.name for f in fields(RunOutcome)] + ["localized_pct"]


def write_summary_csv(path: Path, outcomes: list[RunOutcome]) -> None:
    """summary.csv: one row per run, columns :data:`SUMMARY_FIELDS`."""
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
    dashboard: bool = False             # the local cluster's dashboard (loopback only), off by default
    on_dashboard: Callable[[str], None] | None = None          # told the dashboard's address when it starts
    on_start: Callable[[RunSpec, Path], None] | None = None   # called in the worker before each run (tests)
    cluster_kwargs: dict[str, Any] = field(default_factory=dict)


def check_inputs(manifest: Manifest) -> None:
    """Every source and config file of the manifest exists (checked before anything runs)."""
    for spec in manifest.runs():
        if not spec.source.exists():
            raise DataError(f"{manifest.path}: route {spec.route!r} {spec.name}: {spec.source}: no such file or folder")
        if spec.config is not None and not spec.config.is_file():
            raise DataError(f"{manifest.path}: route {spec.route!r} {spec.name}: {spec.config}: no such config file")


def check_workers(workers: int | None) -> int:
    """The local cluster's size: 1 to ``MAX_WORKERS_PER_CORE`` x cores (more only thrash: each is a process
    with its own memory); default every core."""
    from ..parallel import available_cores

    cores = available_cores()
    if workers is None:
        return cores
    limit = MAX_WORKERS_PER_CORE * cores
    if isinstance(workers, bool) or not isinstance(workers, int) or not 1 <= workers <= limit:
        raise ConfigError(f"--workers {workers!r}: expected 1 to {limit} ({MAX_WORKERS_PER_CORE} per core on "
                          f"{cores} cores)")
    return workers


def check_scheduler(address: str | None) -> str | None:
    """``--scheduler``: ``tls://HOST:PORT`` (or ``tcp://`` on a trusted network), checked before connecting."""
    from urllib.parse import urlsplit

    if address is None:
        return None
    msg = f"--scheduler {address!r}: expected tls://HOST:PORT or tcp://HOST:PORT"
    if not isinstance(address, str) or any(not c.isprintable() or c.isspace() for c in address):
        raise ConfigError(msg)
    try:
        parts = urlsplit(address)
        port = parts.port
    except ValueError:
        raise ConfigError(f"{msg} (port not a number from 1 to 65535)") from None
    if parts.scheme not in SCHEDULER_SCHEMES or not parts.hostname or port is None or not 1 <= port <= 65535 \
            or parts.path not in ("", "/") or parts.query or parts.fragment or parts.username:
        raise ConfigError(msg)
    return address


def check_scheduler_tls(address: str | None) -> None:
    """A ``tls://`` scheduler needs this client's certificates from Dask's configuration; ``ConfigError`` naming the
    settings when there are none (distributed would fail deep inside with a ``TypeError``)."""
    if address is None or not address.startswith("tls://"):
        return
    from distributed.security import Security

    if Security().get_connection_args("client").get("ssl_context") is None:
        raise ConfigError(f"--scheduler {address}: tls:// needs this client's TLS certificates in Dask's configuration "
                          "(distributed.comm.tls.ca-file, distributed.comm.tls.client.cert and .key, e.g. in "
                          "~/.config/dask/distributed.yaml or DASK_DISTRIBUTED__COMM__TLS__CA_FILE=...); none is set")


class BatchLock:
    """``OUT/.vtr-batch.lock`` held (``flock``, exclusive) while a batch writes ``OUT``; a second batch on the
    same folder gets ``OutputError`` at once. The kernel releases it when the process ends, however."""

    def __init__(self, out: Path):
        self.path = Path(out) / LOCK_NAME
        self.fd: int | None = None

    def __enter__(self) -> BatchLock:
        try:
            self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) |
                              getattr(os, "O_CLOEXEC", 0), 0o644)
        except OSError as err:
            raise OutputError(f"{self.path}: cannot open the batch lock ({err.strerror or err})") from None
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(self.fd)
            self.fd = None
            raise OutputError(f"--out {self.path.parent}: another vtr batch is writing this folder (it holds "
                              f"{LOCK_NAME}); wait for it or choose another --out") from None
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


def run_batch(manifest: Manifest, out: str | Path, options: BatchOptions | None = None,
              progress: Callable[[RunOutcome, int, int], None] | None = None) -> BatchResult:
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
    from ..parallel import available_cores, resolve_threads

    check_inputs(manifest)
    check_scheduler_tls(opts.scheduler)
    workers = check_workers(opts.workers) if opts.scheduler is None else (opts.workers or available_cores())
    check_scheduler(opts.scheduler)
    if opts.scheduler is None and opts.threads is not None:   # sizes that multiply: processes x threads
        cores = available_cores()
        threads = resolve_threads(opts.threads, "--threads")
        if workers * threads > MAX_WORKERS_PER_CORE * cores:
            raise ConfigError(f"--workers {workers} x --threads {opts.threads} is {workers * threads} threads on "
                              f"{cores} cores; at most {MAX_WORKERS_PER_CORE * cores}")
    check_apart(Path(out), [p for spec in manifest.runs() for p in (spec.source, spec.config)])
    for route in manifest.routes:
        if (Path(out) / route.name).exists():
            check_no_links(Path(out), Path(out) / route.name / TEACH_FOLDER)
    return workers


def _run_batch(manifest: Manifest, out: Path, own: OutputFolder, opts: BatchOptions, workers: int,
               progress: Callable[[RunOutcome, int, int], None] | None) -> BatchResult:
    from ..parallel import available_cores

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
    resumed: list[tuple[RunSpec, RunOutcome]] = []     # every run.json is checked before anything is reported
    teach_keys: dict[str, dict[str, Any]] = {}
    for spec in runs:
        key = run_key(spec, None if spec.is_teach else teach_keys[spec.route])
        if spec.is_teach:
            teach_keys[spec.route] = key
        folder = spec.folder(out)
        doc = checked_run(folder)
        changed = key_change(folder, key) if doc is not None else None
        if doc is not None and doc.get("status", STATUS_FINISHED) == STATUS_FINISHED and changed is None:
            resumed.append((spec, outcome_from_folder(spec, folder, RESUMED)))
        else:
            pending.append((spec, key, changed if doc is not None and
                            doc.get("status", STATUS_FINISHED) == STATUS_FINISHED else None))
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


def local_security():
    """TLS with credentials made for this batch alone (a temporary CA-less key pair, never written to disk):
    a process without them cannot connect to the local scheduler or its workers."""
    try:
        from distributed.security import Security

        return Security.temporary()
    except ImportError as err:  # pragma: no cover - cryptography is a dependency
        raise ConfigError(f"the local Dask cluster needs the 'cryptography' package for TLS ({err})") from None


def one_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[0]}" if text else type(err).__name__


@contextmanager
def _workers_ignore_ctrl_c() -> Iterator[None]:
    """SIGINT ignored while the local workers are spawned: they inherit that (a Python process started with
    SIGINT ignored installs no KeyboardInterrupt handler), so a Ctrl-C in the terminal, which reaches the
    whole process group, interrupts only the batch, which closes the cluster in order; the workers print no
    tracebacks. (A nanny restarts a dead worker from its own process, where SIGINT is ignored too.)"""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


class _DaskClient:
    """A Dask client on ``scheduler`` or on a new local cluster (closed on exit)."""

    def __init__(self, opts: BatchOptions, workers: int):
        self.opts, self.workers = opts, workers
        self.cluster = None

    def __enter__(self):
        import dask
        from distributed import Client, LocalCluster

        if self.opts.scheduler:
            try:        # tls:// takes its certificates from Dask's config (distributed.comm.tls.*)
                self.client = Client(self.opts.scheduler, timeout=30)
            except (OSError, TimeoutError, ValueError, TypeError) as err:   # TypeError: distributed's TLS setup
                raise ConfigError(f"--scheduler {self.opts.scheduler}: cannot connect ({one_line(err)})") from None
            return self.client
        security = local_security()
        kwargs = {"n_workers": self.workers, "threads_per_worker": 1, "processes": True,
                  "host": "127.0.0.1", "protocol": "tls://", "security": security,
                  # the HTTP server (health, and the dashboard only when asked) on loopback, any free port
                  "dashboard_address": "127.0.0.1:0", "scheduler_kwargs": {"dashboard": self.opts.dashboard},
                  "silence_logs": logging.ERROR, **self.opts.cluster_kwargs}
        # a dead worker's task is given to another one this many times before it counts as failed; without the
        # dashboard, the scheduler's and workers' HTTP servers answer /health only (not the logs, worker addresses
        # and memory that Dask's default routes serve to anyone on the machine)
        settings: dict[str, Any] = {"distributed.scheduler.allowed-failures": max(self.opts.retries, 1)}
        if not self.opts.dashboard:
            settings.update({"distributed.scheduler.http.routes": list(HEALTH_ONLY_ROUTES),
                             "distributed.worker.http.routes": list(HEALTH_ONLY_ROUTES)})
        with dask.config.set(settings), _workers_ignore_ctrl_c():
            self.cluster = LocalCluster(**kwargs)
        self.client = Client(self.cluster, security=security)
        if self.opts.dashboard and self.opts.on_dashboard is not None:
            self.opts.on_dashboard(str(self.cluster.dashboard_link))
        return self.client

    def __exit__(self, *exc) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def _run_on(client, pending: list[tuple[RunSpec, dict[str, Any], str | None]], outcomes: dict, out: Path,
            threads: int | None, opts: BatchOptions, report: Callable[[RunSpec, RunOutcome], None]) -> None:
    from distributed import as_completed

    futures: dict[Any, RunSpec] = {}
    teach_of: dict[str, Any] = {}
    for spec, key, changed in pending:          # teaches come before their repeats (Manifest.runs order)
        teach: Any = None
        if not spec.is_teach:                      # its teach's future, or its outcome when resumed
            teach = teach_of.get(spec.route)
            if teach is None:
                teach = next(o for s, o in outcomes.items() if s.route == spec.route and s.is_teach)
        fut = client.submit(execute_run, spec, str(out), threads, teach, opts.on_start, key, changed,
                            retries=opts.retries,
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
    """The landmarks.csv of every finished repeat, each checked to be the file vtr made there (never a link:
    ``OutputError`` naming it, :meth:`vtr.app.outputs.OutputFolder.own_file`)."""
    ok = {(o.route, o.name) for o in outcomes if o.ok and o.kind == "repeat"}
    for spec in manifest.runs():
        if (spec.route, spec.name) in ok:
            folder = spec.folder(out)
            check_no_links(out, folder)
            p = OutputFolder(folder).own_file("landmarks.csv")
            if p is None:
                raise DataError(f"{folder / 'landmarks.csv'}: missing from a finished repeat")
            yield p


def fit_repeats(manifest: Manifest, out: Path, outcomes: list[RunOutcome]) -> dict[str, Any]:
    """One perception-model fit over every finished repeat's landmarks.csv, streamed (one file in memory at a
    time; the binned fit of the thesis protocol, sandwich intervals): OUT/fit/model.json and fit.png.
    Returns what to report, or the error."""
    from perception_model.errors import PerceptionModelError
    from perception_model.fit import fit_binned_stream
    from perception_model.landmarks_file import FIT_FIELDS, read_landmarks
    from perception_model.plots import plot_fit

    try:
        files = list(repeat_landmark_files(manifest, out, outcomes))
    except VtrError as err:
        return {"error": str(err)}
    if not files:
        return {"error": "no finished repeat to fit"}
    check_no_links(out, out / FIT_FOLDER)
    fit_folder = OutputFolder.prepare(out / FIT_FOLDER, names=["model.json", "fit.png"])
    folder = fit_folder.path

    def chunks():
        for f in files:
            own = OutputFolder(f.parent).own_file(f.name)      # again, just before reading it
            if own is None:
                raise PerceptionModelError(f"{f}: removed while the batch read it")
            obs = read_landmarks(own, fields=FIT_FIELDS)
            yield obs.samples()

    try:
        result = fit_binned_stream(chunks, source=f"{len(files)} repeats under {out}")
    except (PerceptionModelError, VtrError) as err:
        return {"error": str(err), "files": len(files)}
    data = {"files": [str(f) for f in files], "n_observations": result.n, "n_inliers": result.n_inliers}
    fit_folder.write("model.json", result.model.save, fit=result.to_dict(), data=data)
    fit_folder.write("fit.png", lambda p: plot_fit(result, p))
    return {"model": folder / "model.json", "plot": folder / "fit.png", "files": len(files),
            "observations": result.n, "constants": {c.name: c.estimate for c in result.intervals},
            "r2": result.r2, "log_loss": result.log_loss}
