"""``capture``: the operator's command."""

from __future__ import annotations

import typer

app = typer.Typer(help="Capture a session on the rig.")
