"""Options and helpers shared by the ``vtr`` subcommands, and the one place errors become one line."""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from ..config import Config
from ..errors import VtrError
from ..io.base import SourceOptions

EXIT_SIGINT = 130                    # shell convention: 128 + signal number
EXIT_SIGTERM = 143


def load_config(path: Path | None, threads: int | None = None) -> Config:
    """The configuration of ``--config`` (defaults without it), with ``--threads`` applied when given."""
    config = Config.load(path) if path else Config()
    if threads is not None:
        config.features.threads = threads
    return config


def progress_bar():
    """A tqdm factory writing to stderr; silent when stderr is not a terminal (a log or a pipe then
    holds only the summary or the one-line error)."""
    from tqdm import tqdm

    def bar(items, total, desc):
        return tqdm(items, total=total, desc=desc, unit="frame", dynamic_ncols=True, leave=False, disable=None)

    return bar


OUTPUTS_KEY = "vtr.outputs"   # click context meta: the output paths a command writes


def note_outputs(*paths: Path | None) -> None:
    """Remember the command's output paths: an ``OSError`` without a file name (a full disk on
    write or close) is reported against them."""
    ctx = click.get_current_context(silent=True)
    if ctx is not None:
        ctx.meta.setdefault(OUTPUTS_KEY, []).extend(str(p) for p in paths if p is not None)


def error_line(err: BaseException, outputs: list[str] | None = None) -> str:
    """One line for a known error: a ``VtrError`` as is, an ``OSError`` as ``path: reason`` (the
    noted ``outputs`` when the error carries no file name).

    When an ``OSError`` is raised while an earlier error propagates (a full disk fails the map write,
    then closing a CSV fails too), the earliest known error of the chain is reported: it is the cause.
    """
    first, seen = err, set()
    ctx = err.__context__ if isinstance(err, OSError) else None
    while ctx is not None and id(ctx) not in seen:
        seen.add(id(ctx))
        if isinstance(ctx, VtrError | OSError):
            first = ctx
        ctx = ctx.__context__
    if isinstance(first, OSError) and first.strerror:
        if first.filename is not None:
            also = f" -> {first.filename2}" if first.filename2 is not None else ""
            return f"{first.filename}{also}: {first.strerror}"
        return f"writing {', '.join(outputs)}: {first.strerror}" if outputs else first.strerror
    return " ".join(str(first).split()) or type(first).__name__


def check_out_dir(path: Path, option: str = "--out") -> None:
    """Refuse an output folder that cannot be written before any work starts (one line, ``OutputError``,
    :func:`vtr.io.outputs.check_output_folder`); its path is noted for later write errors."""
    from ..io.outputs import check_output_folder

    note_outputs(path)
    check_output_folder(path, option)


def frame_progress(desc: str):
    """A ``progress(i, n)`` callback (as ``vtr.sim.synthetic.write_sequence`` takes) drawing a tqdm bar."""
    from tqdm import tqdm

    bar = tqdm(desc=desc, unit="frame", dynamic_ncols=True, leave=False, disable=None)

    def cb(i: int, n: int) -> None:
        bar.total = n
        bar.update(1)
        if i + 1 == n:
            bar.close()

    return cb


source_argument = click.argument("source", type=click.Path(path_type=Path))
frames_option = click.option("--frames", default=None, metavar="START:STOP:STEP",
                             help="Frames of SOURCE to use (Python slice).")
config_option = click.option("--config", "config_path", type=click.Path(path_type=Path), default=None,
                             help="YAML/TOML configuration (see `vtr config`).")

_SOURCE_OPTIONS = (
    click.option("--format", "fmt", default=None, help="Force the SOURCE format (default: detect)."),
    click.option("--left-topic", default=None, help="ROS bag SOURCE: left image topic."),
    click.option("--right-topic", default=None, help="ROS bag SOURCE: right image topic."),
    click.option("--left-info-topic", default=None, help="ROS bag SOURCE: left CameraInfo topic."),
    click.option("--right-info-topic", default=None, help="ROS bag SOURCE: right CameraInfo topic."),
    click.option("--allow-unpaired", is_flag=True,
                 help="ROS bag SOURCE: keep the matched stereo pairs when some images have no partner."),
)


def source_options(command: Callable[..., Any]) -> Callable[..., Any]:
    """The options of every command reading a SOURCE (format, bag topics, --allow-unpaired), handed
    to the command as one ``source_options: SourceOptions`` argument."""

    @functools.wraps(command)
    def wrapper(*args: Any, fmt: str | None, left_topic: str | None, right_topic: str | None,
                left_info_topic: str | None, right_info_topic: str | None, allow_unpaired: bool,
                **kwargs: Any) -> Any:
        opts = SourceOptions(fmt, left_topic, right_topic, left_info_topic, right_info_topic, allow_unpaired)
        return command(*args, source_options=opts, **kwargs)

    for option in reversed(_SOURCE_OPTIONS):
        wrapper = option(wrapper)
    return wrapper


threads_option = click.option("--threads", type=click.IntRange(min=0), default=None,
                              help="Threads for the per-frame work (features.threads; 0 = every core, the default). "
                                   "Results are identical for every value.")
