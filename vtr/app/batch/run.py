"""One teach or repeat of a batch, as a Dask task: paths in, a small :class:`RunOutcome` out.

A run's own error never escapes: it is written to the run's ``run.json`` (status ``failed``) and returned, and the other
runs go on (a route's repeats are ``blocked`` when its teach failed). A repeat appends to its own copy of the taught
map, so repeats of a route run in parallel and give the same result whatever their order; on a route with
``experiences: true`` each starts from the map of the newest finished repeat before it (in the manifest's order).
See the README's "Batches" section and ``docs/outputs.md``.
"""

from __future__ import annotations

import json
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2

from ...config import Config
from ...errors import DataError
from ...map import copy_map_file
from ...parallel import resolve_threads
from ..outputs import OutputFolder
from ..pipeline import repeat_command, teach_command
from ..runfiles.run_json import STATUS_FAILED, STATUS_FINISHED, RunLog
from .layout import BLOCKED, FAILED, FINISHED, KEY_NAME, MAP_NAME, RESUMED, TEACH_FOLDER
from .manifest import RunSpec, run_config
from .outcome import RunOutcome, checked_run, outcome_from_folder
from .resume import key_change, prepare_run_folder, rerun_folder


def copy_map(src: Path, dst: Path) -> None:
    """Copy a closed map file consistently (SQLite's online backup: WAL content included)."""
    if not src.is_file():
        raise DataError(f"{src}: the taught map is missing (its teach did not finish)")

    copy_map_file(src, dst)


def execute_run(
    spec: RunSpec,
    out: str,
    threads: int | None,
    teach: RunOutcome | None = None,
    on_start: Callable[[RunSpec, Path], None] | None = None,
    key: dict[str, Any] | None = None,
    changed: str | None = None,
    earlier: list[RunOutcome] | None = None,
) -> RunOutcome:
    """One teach or repeat (a Dask task: paths in, a small record out). Never raises for a run's own error:
    it is written to the run's run.json and returned. A repeat starts from a copy of the teach's map, or with
    ``earlier`` (the route's repeats flown before it, when they are experiences) of the newest finished one's."""

    folder = spec.folder(Path(out))
    doc = checked_run(folder)
    if (
        doc is not None
        and doc.get("status", STATUS_FINISHED) == STATUS_FINISHED
        and (key is None or key_change(folder, key) is None)
    ):  # a retry after the run had finished
        return outcome_from_folder(spec, folder, RESUMED)
    if teach is not None and not teach.ok:
        return RunOutcome(spec.route, spec.name, spec.kind, BLOCKED, error=f"teach of {spec.route} {teach.status}")
    # A finished run is replaced only by one that finished: a rerun is built beside it and moved in at the end.
    finished_before = doc is not None and doc.get("status", STATUS_FINISHED) == STATUS_FINISHED
    work = rerun_folder(Path(out), spec) if finished_before else folder
    own = prepare_run_folder(Path(out), spec, work)  # what an interrupted, failed or changed attempt made
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
            copy_map(base_map(folder.parent, earlier or []), map_path)
            repeat_command(spec.source, map_path, work, spec.frames, config, spec.fmt)
    except Exception as err:  # noqa: BLE001 - recorded in run.json; the batch goes on
        message = f"{type(err).__name__}: {err}"
        if finished_before:
            message += (
                f" (the rerun failed; the finished outputs of the earlier run are kept in {folder}, the "
                f"failed attempt's record is {work / 'run.json'})"
            )
        RunLog(work, spec.kind, config, [spec.source]).write(
            {"seconds": time.perf_counter() - t0, "traceback": traceback.format_exc(limit=8)},
            status=STATUS_FAILED,
            error=message,
        )
        return outcome_from_folder(spec, work, FAILED, changed)
    if key is not None:
        own.write_text(KEY_NAME, json.dumps(key, indent=1))
    if finished_before:
        OutputFolder(folder).adopt(own, last=(KEY_NAME, "run.json"))
    return outcome_from_folder(spec, folder, FINISHED, changed)


def base_map(route_folder: Path, earlier: list[RunOutcome]) -> Path:
    """The map a repeat starts from: that of the newest of ``earlier`` that finished (it holds the teach and every
    experience before it), else the teach's. Never through a link vtr did not make."""
    for outcome in reversed(earlier):
        if outcome.ok:
            folder = route_folder / outcome.name
            own = OutputFolder(folder).own_file(MAP_NAME)
            return folder / MAP_NAME if own is None else own
    taught = OutputFolder(route_folder / TEACH_FOLDER).own_file(MAP_NAME)
    return route_folder / TEACH_FOLDER / MAP_NAME if taught is None else taught


def _opencv_threads(config: Config) -> None:
    """OpenCV's own pool follows the run's thread count (a batch worker runs one run per core)."""

    cv2.setNumThreads(resolve_threads(config.features.threads))
