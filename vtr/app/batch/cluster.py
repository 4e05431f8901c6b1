"""The Dask side of a batch: the checked cluster size and scheduler address, the client on a new local cluster or a
running scheduler, and the runs submitted to it.

The local cluster's dashboard is off unless asked (then on loopback); without it the scheduler's and workers' HTTP
servers answer ``/health`` only. A worker process that dies mid-run (killed, out of memory) is replaced and its run
started again by Dask, from an empty folder; a Ctrl-C interrupts only the batch, which closes the cluster in order.
See the README's "Batches" section and ``docs/outputs.md``.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from ...errors import ConfigError
from ...parallel import available_cores
from .layout import FAILED, TEACH_FOLDER
from .manifest import RunSpec
from .options import BatchOptions
from .outcome import RunOutcome
from .run import execute_run
from .tls import local_security

MAX_WORKERS_PER_CORE = 4  # --workers above this many per core only thrash (each worker is a process)
SCHEDULER_SCHEMES = ("tcp", "tls")
#: the HTTP routes the batch's own cluster serves when its dashboard is off
HEALTH_ONLY_ROUTES = ("distributed.http.health",)


def check_workers(workers: int | None) -> int:
    """The local cluster's size: 1 to ``MAX_WORKERS_PER_CORE`` x cores (more only thrash: each is a process
    with its own memory); default every core."""

    cores = available_cores()
    if workers is None:
        return cores
    limit = MAX_WORKERS_PER_CORE * cores
    if isinstance(workers, bool) or not isinstance(workers, int) or not 1 <= workers <= limit:
        raise ConfigError(
            f"--workers {workers!r}: expected 1 to {limit} ({MAX_WORKERS_PER_CORE} per core on {cores} cores)"
        )
    return workers


def check_scheduler(address: str | None) -> str | None:
    """``--scheduler``: ``tls://HOST:PORT`` (or ``tcp://`` on a trusted network), checked before connecting."""

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
    if (
        parts.scheme not in SCHEDULER_SCHEMES
        or not parts.hostname
        or port is None
        or not 1 <= port <= 65535
        or parts.path not in ("", "/")
        or parts.query
        or parts.fragment
        or parts.username
    ):
        raise ConfigError(msg)
    return address


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

    def __init__(self, opts: BatchOptions, workers: int) -> None:
        self.opts, self.workers = opts, workers
        self.cluster: Any = None  # distributed.LocalCluster
        self.client: Any = None  # distributed.Client

    def __enter__(self) -> Any:
        import dask  # Dask only for a batch that starts its cluster
        from distributed import Client, LocalCluster

        if self.opts.scheduler:
            try:  # tls:// takes its certificates from Dask's config (distributed.comm.tls.*)
                self.client = Client(self.opts.scheduler, timeout=30)
            except (OSError, TimeoutError, ValueError, TypeError) as err:  # TypeError: distributed's TLS setup
                raise ConfigError(f"--scheduler {self.opts.scheduler}: cannot connect ({one_line(err)})") from None
            return self.client
        security = local_security()
        kwargs = {
            "n_workers": self.workers,
            "threads_per_worker": 1,
            "processes": True,
            "host": "127.0.0.1",
            "protocol": "tls://",
            "security": security,
            # the HTTP server (health, and the dashboard only when asked) on loopback, any free port
            "dashboard_address": "127.0.0.1:0",
            "scheduler_kwargs": {"dashboard": self.opts.dashboard},
            "silence_logs": logging.ERROR,
            **self.opts.cluster_kwargs,
        }
        # a dead worker's task is given to another one this many times before it counts as failed; without the
        # dashboard, the scheduler's and workers' HTTP servers answer /health only (not the logs, worker addresses
        # and memory that Dask's default routes serve to anyone on the machine)
        settings: dict[str, Any] = {"distributed.scheduler.allowed-failures": max(self.opts.retries, 1)}
        if not self.opts.dashboard:
            settings.update(
                {
                    "distributed.scheduler.http.routes": list(HEALTH_ONLY_ROUTES),
                    "distributed.worker.http.routes": list(HEALTH_ONLY_ROUTES),
                }
            )
        with dask.config.set(settings), _workers_ignore_ctrl_c():
            self.cluster = LocalCluster(**kwargs)
        self.client = Client(self.cluster, security=security)
        if self.opts.dashboard and self.opts.on_dashboard is not None:
            self.opts.on_dashboard(str(self.cluster.dashboard_link))
        return self.client

    def __exit__(self, *exc: object) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def _run_on(
    client: Any,
    pending: list[tuple[RunSpec, dict[str, Any], str | None]],
    outcomes: dict[RunSpec, RunOutcome],
    out: Path,
    threads: int | None,
    opts: BatchOptions,
    report: Callable[[RunSpec, RunOutcome], None],
) -> None:
    from distributed import as_completed  # Dask, imported with the cluster

    futures: dict[Any, RunSpec] = {}
    submitted: dict[tuple[str, str], Any] = {}
    for spec, key, changed in pending:  # teaches come before their repeats (Manifest.runs order)

        def prior(name: str, spec: RunSpec = spec) -> Any:  # its future, or its outcome when resumed
            fut = submitted.get((spec.route, name))
            return (
                fut
                if fut is not None
                else next(o for s, o in outcomes.items() if s.route == spec.route and s.name == name)
            )

        teach: Any = None if spec.is_teach else prior(TEACH_FOLDER)
        earlier = [prior(name) for name in spec.after]  # flown before it: it waits for them (experiences)
        fut = client.submit(
            execute_run,
            spec,
            str(out),
            threads,
            teach,
            opts.on_start,
            key,
            changed,
            earlier,
            retries=opts.retries,
            key=f"{spec.route}/{spec.name}-{time.time_ns()}",
            pure=False,
        )
        futures[fut] = spec
        submitted[spec.route, spec.name] = fut
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
