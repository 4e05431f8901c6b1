"""Options and helpers shared by the ``vtr`` subcommands."""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType

import click

from ..config import Config
from ..errors import Terminated

EXIT_SIGINT = 130                    # shell convention: 128 + signal number
EXIT_SIGTERM = 143


def _raise_terminated(signum: int, frame: FrameType | None) -> None:
    raise Terminated()


@contextmanager
def sigterm_as_exception() -> Iterator[None]:
    """Within the block SIGTERM raises ``Terminated`` (an orderly exit like Ctrl-C: ``with`` blocks
    close, runs in progress are recorded as aborted); the previous handler comes back after it.
    Only the main thread can handle signals (elsewhere this does nothing)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def error_line(err: BaseException) -> str:
    """An error as one line (an ``OSError`` with its file name, e.g. a full disk)."""
    if isinstance(err, OSError) and err.strerror:
        where = f"{err.filename}: " if err.filename else ""
        return f"{where}{err.strerror}"
    return " ".join(str(err).split()) or type(err).__name__


def load_config(path: Path | None) -> Config:
    return Config.load(path) if path else Config()


def progress_bar():
    """A tqdm factory writing to stderr (quiet when not a terminal is fine too)."""
    from tqdm import tqdm

    def bar(items, total, desc):
        return tqdm(items, total=total, desc=desc, unit="frame", dynamic_ncols=True, leave=False)

    return bar


source_argument = click.argument("source", type=click.Path(path_type=Path))
frames_option = click.option("--frames", default=None, metavar="START:STOP:STEP",
                             help="Frames of SOURCE to use (Python slice).")
config_option = click.option("--config", "config_path", type=click.Path(path_type=Path), default=None,
                             help="YAML/TOML configuration (see `vtr config`).")
format_option = click.option("--format", "fmt", default=None, help="Force the SOURCE format (default: detect).")
