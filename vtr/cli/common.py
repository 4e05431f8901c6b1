"""Options and helpers shared by the ``vtr`` subcommands."""

from __future__ import annotations

from pathlib import Path

import click

from ..config import Config


def load_config(path: Path | None) -> Config:
    return Config.load(path) if path else Config()


def progress_bar():
    """A tqdm factory writing to stderr (quiet when not a terminal is fine too)."""
    from tqdm import tqdm

    def bar(items, total, desc):
        return tqdm(items, total=total, desc=desc, unit="frame", dynamic_ncols=True, leave=False)

    return bar


def frame_progress(desc: str):
    """A ``progress(i, n)`` callback (as ``vtr.sim.synthetic.write_sequence`` takes) drawing a tqdm bar."""
    from tqdm import tqdm

    bar = tqdm(desc=desc, unit="frame", dynamic_ncols=True, leave=False)

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
format_option = click.option("--format", "fmt", default=None, help="Force the SOURCE format (default: detect).")
