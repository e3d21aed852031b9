"""``m2s2hil sessions compact SESSION [--root DATA_ROOT]``: convert a session to the compressed
storage format (m2s2hil.store.compact), verified before and after."""

from __future__ import annotations

from pathlib import Path

import typer


def compact_cmd(
    session: str = typer.Argument(..., help="session id"),
    root: Path | None = typer.Option(None, "--root", help="data root (default: $M2S2HIL_DATA or ./sessions)"),
) -> None:
    """Compress a session's raw frames and darks losslessly and drop the cubes that are
    recomputed bit for bit when read; atomic, verified before and after."""
    from m2s2hil.store.catalogue import default_data_root
    from m2s2hil.store.compact import compact_session

    typer.echo(compact_session(root or default_data_root(), session).line())
