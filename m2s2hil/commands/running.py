"""How a command-line front end runs: click's standalone mode (usage errors exit 2), and our
typed errors as one line on stderr with their exit code instead of a traceback. Shared by
``m2s2hil.cli`` and the modules that also run as ``python -m`` (``commands.serve``)."""

from __future__ import annotations

import sys

import typer

from m2s2hil.errors import M2S2Error


def run_app(typer_app: typer.Typer) -> None:
    """Run ``typer_app``; an :class:`M2S2Error` becomes ``error: …`` and its ``exit_code``."""
    try:
        typer_app()
    except M2S2Error as exc:
        typer.secho(f"error: {exc}", err=True, fg="red")
        sys.exit(exc.exit_code)
