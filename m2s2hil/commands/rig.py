"""``m2s2hil rig``: inspect and check rig configurations."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from m2s2hil.config import load_rig

app = typer.Typer(help="Rig configuration.", no_args_is_help=True)


@app.command("check")
def check(rig: Path | None = typer.Argument(None, help="rig TOML file (default: built-in)")) -> None:
    """Validate a rig file and show its devices."""
    cfg = load_rig(rig)
    t = Table(title=cfg.rig.name)
    for col in ("device", "protocol", "port", "baud"):
        t.add_column(col)
    for name, dev in cfg.devices.items():
        t.add_row(name, dev.protocol, dev.port, str(dev.baudrate))
    t.add_row("camera", "u3v", cfg.camera.port, "-")
    Console().print(t)
    for name, faults in cfg.simulation.faults.items():  # said aloud: a fault file on a real bench surprises
        typer.echo(f"injected faults on {name}: {', '.join(f.kind for f in faults)}")
    typer.echo(f"ok: {rig or 'built-in simulated rig'} (sha256 {cfg.digest[:12]})")
