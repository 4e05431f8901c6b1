"""The ``vtr`` command: a thin adapter over the library.

Known errors (``VtrError``, and any ``OSError``: missing file, full disk, no permission) become one
line on stderr naming the file, and exit code 1; Ctrl-C and SIGTERM end the command in order (runs in
progress are recorded as aborted) with exit codes 130 and 143.
Subcommands live in sibling modules and register on ``main``.
"""

from __future__ import annotations

import atexit
import gc
import sys
from typing import Any

import click

from perception_model.commandline import OneLineGroup, version_option

from .. import __version__
from ..errors import Terminated, VtrError, interruption
from ..signals import sigterm_as_exception
from .common import EXIT_SIGINT, EXIT_SIGTERM, OUTPUTS_KEY, error_line

#: (module to import, distribution) of every dependency `vtr versions` checks; the heavy ones first
DEPENDENCIES = (
    ("numpy", "numpy"),
    ("numba", "numba"),
    ("scipy", "scipy"),
    ("cv2", "opencv-python-headless"),
    ("gtsam", "gtsam"),
    ("open3d", "open3d"),
    ("rosbags", "rosbags"),
    ("pyarrow", "pyarrow"),
    ("osqp", "osqp"),
    ("dask", "dask"),
    ("distributed", "distributed"),
    ("matplotlib", "matplotlib"),
    ("click", "click"),
    ("tqdm", "tqdm"),
    ("yaml", "PyYAML"),
)


def _versions() -> str:
    """Import each heavy dependency (so a broken install shows here) and report its installed version."""
    from importlib import import_module, metadata

    parts = [f"vtr {__version__}"]
    for module, dist in DEPENDENCIES:
        import_module(module)
        parts.append(f"{module} {metadata.version(dist)}")
    return ", ".join(parts)


_final_collection_skipped = False


def skip_final_collection() -> None:
    """Leave the objects alive at exit out of the interpreter's last garbage collections (``gc.freeze`` in an exit
    handler): a run that imported numba, SciPy, GTSAM and matplotlib otherwise spends about a second after its last
    output traversing them all (``tools/bench_processes.py``, phase ``teardown``). Every output is closed before
    the command returns (files and maps by their context managers); every exit handler still runs and objects are
    still freed by reference counting: only reference cycles left at exit stay for the operating system to take
    back. Registered once per process, when a command runs."""
    global _final_collection_skipped
    if not _final_collection_skipped:
        _final_collection_skipped = True
        atexit.register(gc.freeze)


class _Group(OneLineGroup):
    def invoke(self, ctx: click.Context) -> Any:
        skip_final_collection()
        try:
            with sigterm_as_exception():
                return super().invoke(ctx)
        except (VtrError, OSError) as err:
            click.echo(f"vtr: error: {error_line(err, ctx.meta.get(OUTPUTS_KEY))}", err=True)
            sys.exit(1)
        except (KeyboardInterrupt, Terminated, SystemError) as err:
            signal_err = interruption(err)  # a SystemError out of a numba kernel may carry the signal
            if signal_err is None:
                raise
            if isinstance(signal_err, Terminated):
                click.echo("vtr: terminated (SIGTERM)", err=True)
                sys.exit(EXIT_SIGTERM)
            click.echo("vtr: interrupted (Ctrl-C)", err=True)
            sys.exit(EXIT_SIGINT)


@click.group(cls=_Group, name="vtr")
@version_option(__version__, "vtr")
def main() -> None:
    """Visual teach-and-repeat: stereo odometry, maps, localization, smoothing."""


@main.command("versions")
def versions_cmd() -> None:
    """Print the versions of vtr and its heavy dependencies (checks they import)."""
    click.echo(_versions())


@main.command("config")
def config_cmd() -> None:
    """Print the default configuration as YAML (reusable with --config), every key with its comment and
    domain from vtr/config/sections.py."""
    from ..config import Config

    click.echo(Config().to_yaml(comments=True), nl=False)


def _register() -> None:
    """Import every sibling module; each adds its commands to ``main``."""
    import pkgutil
    from importlib import import_module

    for info in pkgutil.iter_modules(__path__):
        if info.name == "perception_model":  # the other console script's group, not vtr's
            continue
        import_module(f"{__name__}.{info.name}")


_register()
