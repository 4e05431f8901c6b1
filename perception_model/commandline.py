"""The conventions both console scripts (``vtr`` and ``perception-model``) follow, written once.

This module imports only click and the standard library (a help page must start fast), and nothing from
``vtr``, so ``perception_model.cli`` can use it alone; ``vtr.cli`` builds on it.

- **Errors.** A usage error (a missing or malformed option, an unknown command) is one line on stderr,
  ``PROG: error: ... (see `PROG CMD --help`)``, and exit code 1, like every other known error
  (:class:`OneLineGroup`).
- **Versions.** ``--version`` prints ``PROG VERSION`` (:func:`version_option`).
- **Outputs.** A command never replaces an existing output unless ``--force``
  (:func:`perception_model.outputs.existing_output`, click-free for the libraries):
  a file is replaced with ``--force``; an output folder (``--out DIR``) that already holds files is
  written into with ``--force`` (files of the same name replaced, others kept). Documented exceptions:
  ``vtr demo`` rewrites its own folder, ``vtr batch --out`` resumes in its folder, ``vtr repeat --map``
  appends a run to the taught map, ``vtr convert`` never replaces its output (delete it first).
- **Names.** ``--out DIR`` is always a folder; ``--json`` is a flag printing JSON on stdout; ``--format``
  and ``--to`` take the names listed in their help; ``--c-bar`` and ``--delta`` are two spellings of the
  constraint's confidence wherever one is taken.
"""

from __future__ import annotations

import sys
from typing import Any

import click

from .outputs import existing_output

__all__ = ["OneLineGroup", "existing_output", "force_option", "version_option"]


class OneLineGroup(click.Group):
    """A click group whose usage errors are one line and exit code 1 (click's own: three lines, exit 2)."""

    def main(
        self,
        args: Any = None,
        prog_name: str | None = None,
        complete_var: str | None = None,
        standalone_mode: bool = True,
        **extra: Any,
    ) -> Any:
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode, **extra)
        try:
            rv = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except click.UsageError as err:
            prog = self.name or prog_name or "command"
            where = f"{err.ctx.command_path} --help" if err.ctx is not None else f"{prog} --help"
            click.echo(f"{prog}: error: {' '.join(err.format_message().split())} (see `{where}`)", err=True)
            sys.exit(1)
        except click.ClickException as err:
            err.show()
            sys.exit(err.exit_code)
        except click.Abort:
            click.echo("Aborted!", err=True)
            sys.exit(1)
        sys.exit(rv if isinstance(rv, int) else 0)


def version_option(version: str, prog: str) -> Any:
    """``--version``: ``PROG VERSION``, the same for every console script of the distribution."""
    return click.version_option(version, prog_name=prog, message="%(prog)s %(version)s")


def force_option(what: str = "its outputs") -> Any:
    """The ``--force`` flag of every command that writes an output which may already exist."""
    return click.option("--force", is_flag=True, help=f"Replace {what} if they exist (default: refuse).")
