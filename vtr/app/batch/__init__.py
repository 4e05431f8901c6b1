"""``vtr batch``: every teach and repeat of a manifest as tasks on a Dask cluster, resumable.

One module per concern, imports one way (each only from those above it): :mod:`.layout` (the names of ``OUT`` and
the run statuses), :mod:`.manifest` (the YAML manifest), :mod:`.outcome` (what a run did, ``summary.csv``),
:mod:`.resume` (run keys, rerun folders), :mod:`.run` (one run, a Dask task), :mod:`.options`, :mod:`.tls`,
:mod:`.cluster` (Dask), :mod:`.lock`, :mod:`.model_fit` (``--fit``) and :mod:`.driver` (the whole batch). The names
below are the batch's public face. See the README's "Batches" section and ``docs/outputs.md``.
"""

from __future__ import annotations

from .cluster import MAX_WORKERS_PER_CORE, check_scheduler, check_workers
from .driver import check_batch, check_inputs, run_batch
from .layout import BLOCKED, DONE, FAILED, FINISHED, FIT_FOLDER, MAP_NAME, RESUMED, SUMMARY_CSV, TEACH_FOLDER
from .lock import BatchLock
from .manifest import Manifest, RouteSpec, RunSpec, load_manifest
from .model_fit import fit_repeats, repeat_landmark_files
from .options import BatchOptions
from .outcome import BatchResult, RunOutcome, checked_run, outcome_from_folder
from .run import execute_run
from .tls import check_scheduler_tls

__all__ = [
    "BLOCKED",
    "DONE",
    "FAILED",
    "FINISHED",
    "FIT_FOLDER",
    "MAP_NAME",
    "MAX_WORKERS_PER_CORE",
    "RESUMED",
    "SUMMARY_CSV",
    "TEACH_FOLDER",
    "BatchLock",
    "BatchOptions",
    "BatchResult",
    "Manifest",
    "RouteSpec",
    "RunOutcome",
    "RunSpec",
    "check_batch",
    "check_inputs",
    "check_scheduler",
    "check_scheduler_tls",
    "check_workers",
    "checked_run",
    "execute_run",
    "fit_repeats",
    "load_manifest",
    "outcome_from_folder",
    "repeat_landmark_files",
    "run_batch",
]
