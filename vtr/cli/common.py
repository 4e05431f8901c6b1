"""Options and helpers shared by the ``vtr`` subcommands, and the one place errors become one line."""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from perception_model.commandline import force_option

from ..errors import VtrError

if TYPE_CHECKING:
    import numpy as np

    from ..config import Config

# Nothing numerical is imported here or by any vtr.cli module at import time (a help page must start
# fast: tests/cli/test_startup.py); commands import the library where they run.

EXIT_SIGINT = 130  # shell convention: 128 + signal number
EXIT_SIGTERM = 143


def load_config(path: Path | None, threads: int | None = None) -> Config:
    """The configuration of ``--config`` (defaults without it), with ``--threads`` applied when given; a key of an
    older version loads under its new name with a one-line warning on stderr."""
    from ..config import Config

    config = Config.load(path, warn=lambda line: click.echo(f"warning: {line}", err=True)) if path else Config()
    return config if threads is None else config.replace("features", threads=threads)


#: without a terminal, a progress line every this many items (and at the first and the last)
PROGRESS_LINE_EVERY = 100


_PLURALS = {"vertex": "vertices"}


class LineProgress:
    """Progress for a log or a pipe: ``DESC: k/N UNITs`` lines on stderr at the first item, every ``every``
    items and at the last (no carriage returns); the same methods as the tqdm bars used here."""

    def __init__(self, total: int | None, desc: str, unit: str, every: int = PROGRESS_LINE_EVERY) -> None:
        self.total, self.desc, self.unit, self.every, self.n = total, desc, unit, max(1, every), 0
        self._postfix = ""

    def update(self, n: int = 1) -> None:
        before, self.n = self.n, self.n + n
        if before == 0 or self.n // self.every > before // self.every or self.n == self.total:
            of = f"/{self.total}" if self.total else ""
            click.echo(f"{self.desc}: {self.n}{of} {_PLURALS.get(self.unit, self.unit + 's')}{self._postfix}", err=True)

    def set_postfix_str(self, text: str) -> None:
        self._postfix = f" ({text})" if text else ""

    def close(self) -> None:
        pass

    def __enter__(self) -> LineProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _NoProgress(LineProgress):
    def __init__(self) -> None:
        super().__init__(None, "", "")

    def update(self, n: int = 1) -> None:
        pass


def make_bar(
    total: int | None,
    desc: str,
    unit: str = "frame",
    *,
    disable: bool = False,
    every: int = PROGRESS_LINE_EVERY,
    leave: bool = False,
) -> Any:
    """A progress bar on stderr: tqdm on a terminal, :class:`LineProgress` lines when stderr is a log or a
    pipe, nothing when ``disable``."""
    import sys

    if disable:
        return _NoProgress()
    if sys.stderr.isatty():
        from tqdm import tqdm

        return tqdm(total=total, desc=desc, unit=unit, dynamic_ncols=True, leave=leave)
    return LineProgress(total, desc, unit, every)


def progress_bar(unit: str = "frame") -> Callable[[Iterable[Any], int | None, str], Iterator[Any]]:
    """A progress factory ``bar(items, total, desc)`` (as ``vtr.app.pipeline`` takes): :func:`make_bar`
    around the items."""

    def bar(items: Iterable[Any], total: int | None, desc: str) -> Iterator[Any]:
        with_bar = make_bar(total, desc, unit)
        try:
            for item in items:
                yield item
                with_bar.update(1)
        finally:
            with_bar.close()

    return bar


OUTPUTS_KEY = "vtr.outputs"  # click context meta: the output paths a command writes


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


def check_out_dir(path: Path, force: bool, option: str = "--out") -> None:
    """Refuse, before any work starts, an output folder that cannot be written or that already holds files
    (unless ``force``): one line, ``OutputError`` (:func:`vtr.io.outputs.check_output_folder`). Its path is
    noted for later write errors."""
    from ..io.outputs import check_output_folder

    note_outputs(path)
    check_output_folder(path, option, force)


def check_out_file(path: Path, force: bool, inputs: tuple[Path | None, ...] = ()) -> None:
    """Refuse, before any work starts, an output file that exists (unless ``force``), is a folder, a link or
    one of the command's ``inputs`` (:func:`vtr.io.outputs.check_new_output`); write it with
    :func:`vtr.io.outputs.write_output`."""
    from ..io.outputs import check_new_output

    note_outputs(path)
    check_new_output(path, force, inputs=inputs)


force_out_option = force_option("existing output files (in --out)")


def frame_progress(desc: str) -> Callable[[int, int], None]:
    """A ``progress(i, n)`` callback (as ``vtr.sim.synthetic.write_sequence`` takes) drawing a :func:`make_bar`.
    The bar starts with the first call, once its total is known (a cached sequence never calls it and so
    leaves no bar standing at 0)."""
    bars: list[Any] = []

    def cb(i: int, n: int) -> None:
        if not bars:
            bars.append(make_bar(n, desc))
        bars[0].update(1)
        if i + 1 == n:
            bars[0].close()

    return cb


source_argument = click.argument("source", type=click.Path(path_type=Path))
frames_option = click.option(
    "--frames", default=None, metavar="START:STOP:STEP", help="Frames of SOURCE to use (Python slice)."
)
config_option = click.option(
    "--config",
    "config_path",
    type=click.Path(path_type=Path),
    default=None,
    help="YAML/TOML configuration (see `vtr config`).",
)

#: ``--format`` values: the readers of ``vtr.io.FORMATS`` and, as aliases of ``rosbag``, the bag kinds
#: ``vtr convert --to`` writes (tests/cli/test_conventions.py checks the two lists agree).
SOURCE_FORMATS = ("kitti", "euroc", "stereo-pairs", "rosbag", "rosbag1", "rosbag2", "mcap", "cloud")

_SOURCE_OPTIONS = (
    click.option(
        "--format",
        "fmt",
        type=click.Choice(SOURCE_FORMATS),
        default=None,
        help="Force the SOURCE format (default: detect); rosbag1, rosbag2 and mcap are read as rosbag.",
    ),
    click.option("--left-topic", default=None, help="ROS bag SOURCE: left image topic."),
    click.option("--right-topic", default=None, help="ROS bag SOURCE: right image topic."),
    click.option("--left-info-topic", default=None, help="ROS bag SOURCE: left CameraInfo topic."),
    click.option("--right-info-topic", default=None, help="ROS bag SOURCE: right CameraInfo topic."),
    click.option(
        "--allow-unpaired",
        is_flag=True,
        help="ROS bag SOURCE: keep the matched stereo pairs when some images have no partner.",
    ),
)


def source_options(command: Callable[..., Any]) -> Callable[..., Any]:
    """The options of every command reading a SOURCE (format, bag topics, --allow-unpaired), handed
    to the command as one ``source_options: SourceOptions`` argument."""

    @functools.wraps(command)
    def wrapper(
        *args: Any,
        fmt: str | None,
        left_topic: str | None,
        right_topic: str | None,
        left_info_topic: str | None,
        right_info_topic: str | None,
        allow_unpaired: bool,
        **kwargs: Any,
    ) -> Any:
        from ..io.base import SourceOptions

        opts = SourceOptions(fmt, left_topic, right_topic, left_info_topic, right_info_topic, allow_unpaired)
        return command(*args, source_options=opts, **kwargs)

    for option in reversed(_SOURCE_OPTIONS):
        wrapper = option(wrapper)
    return wrapper


def _parse_up(ctx: click.Context, param: click.Parameter, value: str | None) -> np.ndarray | None:
    """``--up X,Y,Z`` as a unit 3-vector (None when not given); a one-line usage error otherwise."""
    if value is None:
        return None
    from ..errors import ConfigError
    from ..map import check_gravity_up

    try:
        parts = [float(x) for x in value.split(",")]
        return check_gravity_up(parts, "--up")
    except (ValueError, ConfigError) as err:
        raise click.BadParameter(
            f"expected three numbers X,Y,Z (a non-zero up direction), got {value!r}"
            + (f" ({err})" if isinstance(err, ConfigError) else "")
        ) from None


def up_option(help_text: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """``--up X,Y,Z``: the up direction (opposite to gravity) in the teach run's first left camera frame."""
    return click.option("--up", "gravity_up", default=None, metavar="X,Y,Z", callback=_parse_up, help=help_text)


threads_option = click.option(
    "--threads",
    type=click.IntRange(min=0),
    default=None,
    help="Threads for the per-frame work (features.threads; 0 = every core, the default). "
    "Results are identical for every value.",
)
