"""``m2s2hil sim serve``: the simulated rig on pseudo-terminals."""

from __future__ import annotations

import signal
import threading
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from m2s2hil.config import load_rig


def serve(
    rig: Path | None = typer.Option(None, "--rig", help="rig TOML file (default: built-in)"),
    write_rig: Path | None = typer.Option(
        None, "--write-rig", help="write a rig file whose serial ports are the pty paths"
    ),
    seconds: float | None = typer.Option(None, "--seconds", help="stop after this long (default: Ctrl-C)"),
) -> None:
    """Serve every serial device of the rig as a simulator on a pseudo-terminal."""
    from m2s2hil.rig.pty_serve import SimServer

    config = load_rig(rig)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    with SimServer(config) as server:
        table = Table(title="simulated devices (real time)")
        for col in ("device", "protocol", "path", "baud"):
            table.add_column(col)
        for d in server.devices:
            table.add_row(d.name, d.protocol, d.path, str(d.baudrate))
        table.add_row("camera", "u3v", "in-process only (USB)", "-")
        Console().print(table)
        if write_rig is not None:
            write_rig.write_text(server.rig_toml())
            typer.echo(f"rig file: {write_rig}")
        typer.echo("serving; Ctrl-C to stop", err=True)
        stop.wait(seconds)
    typer.echo("stopped", err=True)
