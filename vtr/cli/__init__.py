"""The ``vtr`` command: a thin adapter over the library.

Known errors (``VtrError``, missing files) become one line on stderr and exit code 1.
Subcommands live in sibling modules and register on ``main``.
"""

from __future__ import annotations

import sys

import click

from .. import __version__
from ..errors import VtrError


def _versions() -> str:
    import cv2
    import gtsam
    import numpy
    import open3d
    import rosbags
    import scipy

    parts = [f"vtr {__version__}", f"numpy {numpy.__version__}", f"scipy {scipy.__version__}",
             f"opencv {cv2.__version__}", f"gtsam {getattr(gtsam, '__version__', '?')}",
             f"open3d {open3d.__version__}", f"rosbags {getattr(rosbags, '__version__', '?')}"]
    return ", ".join(parts)


class _Group(click.Group):
    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except (VtrError, FileNotFoundError) as err:
            click.echo(f"vtr: error: {err}", err=True)
            sys.exit(1)


@click.group(cls=_Group)
@click.version_option(__version__, message="%(version)s", prog_name="vtr")
def main() -> None:
    """Visual teach-and-repeat: stereo odometry, maps, localization, smoothing."""


@main.command("versions")
def versions_cmd() -> None:
    """Print the versions of vtr and its heavy dependencies (checks they import)."""
    click.echo(_versions())


@main.command("config")
def config_cmd() -> None:
    """Print the default configuration as YAML (reusable with --config)."""
    from ..config import Config

    click.echo(Config().to_yaml(), nl=False)


def _register() -> None:
    """Import every sibling module; each adds its commands to ``main``."""
    import pkgutil
    from importlib import import_module

    for info in pkgutil.iter_modules(__path__):
        import_module(f"{__name__}.{info.name}")


_register()
