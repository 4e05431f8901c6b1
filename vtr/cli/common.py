"""Options and helpers shared by the ``vtr`` subcommands."""

from __future__ import annotations

from pathlib import Path

import click

from ..config import Config


def load_config(path: Path | None, threads: int | None = None) -> Config:
    """The configuration of ``--config`` (defaults without it), with ``--threads`` applied when given."""
    config = Config.load(path) if path else Config()
    if threads is not None:
        config.features.threads = threads
    return config


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
threads_option = click.option("--threads", type=click.IntRange(min=0), default=None,
                              help="Threads for the per-frame work (features.threads; 0 = every core, the default). "
                                   "Results are identical for every value.")
