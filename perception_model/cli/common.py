"""What every ``perception-model`` command shares: the click group (known errors and warnings as one line each),
the output rule as an error, deprecation warnings and the bin options. See ``docs/perception_model.md``.
"""

from __future__ import annotations

import math
import os
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from ..commandline import OneLineGroup, version_option
from ..errors import InputDataError, PerceptionModelError, PerceptionModelWarning
from ..outputs import existing_output
from ..settings import THESIS_PITCH_DOWN_RAD, FitSettings

PROG = "perception-model"
DIST = "vtr"  # the distribution that ships this package
#: The defaults the options show: the fit's settings record (bin widths shown in degrees, the CLI's unit) and
#: the thesis camera pitch in degrees.
FIT_DEFAULTS = FitSettings()
PITCH_DEG = math.degrees(THESIS_PITCH_DOWN_RAD)


class _Group(OneLineGroup):
    """Click group that reports known errors and warnings in one line each."""

    def invoke(self, ctx: click.Context) -> Any:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                return super().invoke(ctx)
            except BrokenPipeError:  # output piped into e.g. `head`: stop quietly
                devnull = os.open(os.devnull, os.O_WRONLY)
                os.dup2(devnull, sys.stdout.fileno())
                sys.exit(1)
            except (PerceptionModelError, OSError) as err:
                _flush_warnings(caught)
                click.echo(f"{PROG}: error: {_one_line(err)}", err=True)
                sys.exit(1)
            finally:
                _flush_warnings(caught)


def _one_line(err: BaseException) -> str:
    if isinstance(err, OSError) and err.filename:
        return f"{err.filename}: {err.strerror or err}"
    return " ".join(str(err).split())


def _flush_warnings(caught: list[warnings.WarningMessage]) -> None:
    while caught:
        w = caught.pop(0)
        click.echo(f"{PROG}: warning: {_one_line(Exception(str(w.message)))}", err=True)


def _version() -> str:
    from importlib.metadata import version

    return version(DIST)


def check_output(
    path: Path, force: bool, *, folder: bool = False, option: str | None = None, inputs: tuple[Path | None, ...] = ()
) -> None:
    """The output rule of every command (:func:`perception_model.outputs.existing_output`: never without
    ``--force`` over an output, never through a link or over one of ``inputs``) as an error."""
    problem = existing_output(path, force, folder=folder, option=option, inputs=inputs)
    if problem is not None:
        raise InputDataError(problem)


def deprecated(message: str) -> None:
    warnings.warn(message, PerceptionModelWarning, stacklevel=2)


@click.group(cls=_Group, name=PROG)
@version_option(_version(), PROG)
def main() -> None:
    """Perception model for visual teach and repeat: p = c1 cos(c2 theta) exp(c3 alpha)."""


def bin_options(command: Callable[..., Any]) -> Callable[..., Any]:
    """The (alpha, theta) bin widths used by fitting and by R^2 in evaluation (degrees)."""
    for name, default, what in (
        ("--theta-bin", FIT_DEFAULTS.theta_bin_deg, "View-angle"),
        ("--alpha-bin", FIT_DEFAULTS.alpha_bin_deg, "Parallax"),
    ):
        command = click.option(
            name,
            type=click.FloatRange(min=0.0, min_open=True),
            default=default,
            show_default=True,
            help=f"{what} bin width (degrees).",
        )(command)
    return command


__all__ = ["DIST", "FIT_DEFAULTS", "PITCH_DEG", "PROG", "bin_options", "check_output", "deprecated", "main"]
