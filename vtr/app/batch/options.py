"""How a batch runs: the local cluster's size or a scheduler's address, threads per run, retries, ``--fit``, the
dashboard, and the callbacks of tests and commands. See the README's "Batches" section and ``docs/outputs.md``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .manifest import RunSpec

DEFAULT_RETRIES = 2  # extra attempts of a task that raised inside Dask (its worker died: see above)


@dataclass
class BatchOptions:
    workers: int | None = None  # local cluster size (default: every core)
    scheduler: str | None = None  # address of a running Dask scheduler instead of a local cluster
    threads: int | None = None  # threads per run (default: local: cores // workers; remote: config)
    retries: int = DEFAULT_RETRIES
    fit: bool = False
    dashboard: bool = False  # the local cluster's dashboard (loopback only), off by default
    on_dashboard: Callable[[str], None] | None = None  # told the dashboard's address when it starts
    on_start: Callable[[RunSpec, Path], None] | None = None  # called in the worker before each run (tests)
    cluster_kwargs: dict[str, Any] = field(default_factory=dict)
