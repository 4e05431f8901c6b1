"""The ``vtr`` command: a thin adapter over the library.

Known errors (``VtrError``, and any ``OSError``: missing file, full disk, no permission) become one
line on stderr naming the file, and exit code 1.
Subcommands live in sibling modules and register on ``main``.
"""

from __future__ import annotations

import sys

import click

from .. import __version__
from ..errors import VtrError


def _versions() -> str:
    """Import each heavy dependency (so a broken install shows here) and report its installed version."""
    from importlib import import_module, metadata

    parts = [f"vtr {__version__}"]
    for module, dist in (("numpy", "numpy"), ("numba", "numba"), ("scipy", "scipy"), ("cv2", "opencv-python-headless"),
                         ("gtsam", "gtsam"), ("open3d", "open3d"), ("rosbags", "rosbags")):
        import_module(module)
        parts.append(f"{module} {metadata.version(dist)}")
    return ", ".join(parts)


class _Group(click.Group):
    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except (VtrError, OSError) as err:
            from .common import OUTPUTS_KEY, error_line

            click.echo(f"vtr: error: {error_line(err, ctx.meta.get(OUTPUTS_KEY))}", err=True)
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
