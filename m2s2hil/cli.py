"""Command-line entry points: ``m2s2hil`` (umbrella) and ``capture`` (operator).

Subcommand groups live in ``m2s2hil/commands/``, one module each.
"""

from __future__ import annotations

import sys

import typer

from m2s2hil.errors import M2S2Error

app = typer.Typer(
    name="m2s2hil",
    help="Hardware-in-the-loop capture of multispectral satellite-mockup datasets (M2S2).",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
)


def _register() -> None:
    from m2s2hil.commands import rig, sim

    app.add_typer(sim.app, name="sim")
    app.add_typer(rig.app, name="rig")


_register()


def _run(typer_app: typer.Typer) -> None:
    try:
        typer_app(standalone_mode=False)
    except M2S2Error as exc:
        typer.secho(f"error: {exc}", err=True, fg="red")
        sys.exit(exc.exit_code)
    except typer.Abort:
        typer.secho("aborted", err=True)
        sys.exit(130)
    except (typer.BadParameter, typer.Exit) as exc:
        if isinstance(exc, typer.Exit):
            sys.exit(exc.exit_code)
        raise
    except Exception as exc:  # click usage errors arrive here with standalone_mode=False
        import click

        if isinstance(exc, click.ClickException):
            exc.show()
            sys.exit(2)
        raise
    sys.exit(0)


def main() -> None:
    _run(app)


def capture_main() -> None:
    from m2s2hil.commands.capture import app as capture_app

    _run(capture_app)
