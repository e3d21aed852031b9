"""``m2s2hil sim``: the simulated rig."""

from __future__ import annotations

import typer

app = typer.Typer(help="Simulated devices.", no_args_is_help=True)
