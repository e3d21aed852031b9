"""``m2s2hil sessions``: list stored sessions and show one."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

app = typer.Typer(help="Stored sessions.", no_args_is_help=True)


def _when(t: float | None) -> str:
    return "-" if t is None else dt.datetime.fromtimestamp(t, dt.UTC).strftime("%Y-%m-%d %H:%M:%S")


@app.command("list")
def list_cmd(
    root: Path | None = typer.Option(None, "--root", help="data root (default: $M2S2HIL_DATA or ./sessions)"),
) -> None:
    """Every session under the data root, newest first."""
    from m2s2hil.store.session import default_data_root, list_sessions

    root = root or default_data_root()
    infos = list_sessions(root)
    t = Table(title=f"sessions in {root}")
    for col in ("session", "state", "satellite", "build", "frames", "updated (UTC)"):
        t.add_column(col)
    for s in infos:
        t.add_row(s.session_id, s.state, s.satellite or "-", s.build or "-", str(s.frames), _when(s.updated))
    Console().print(t)
    if not infos:
        typer.echo("no sessions")


@app.command("show")
def show_cmd(
    session: str = typer.Argument(..., help="session id"),
    root: Path | None = typer.Option(None, "--root", help="data root"),
    verify: bool = typer.Option(False, "--verify", help="recompute every file's sha256"),
    as_json: bool = typer.Option(False, "--json", help="print the summary as JSON"),
) -> None:
    """A session's summary (and, with --verify, its integrity check)."""
    from m2s2hil.analysis.qc import qc_summary
    from m2s2hil.store.session import SessionStore, default_data_root

    store = SessionStore.open(root or default_data_root(), session)
    try:
        summary = store.summary()
        qc = qc_summary(store.frames())
        if qc.get("scored"):
            summary["qc"] = qc
        problems = store.verify() if verify else None
    finally:
        store.close()
    if as_json:
        if problems is not None:
            summary["problems"] = [p.model_dump() if hasattr(p, "model_dump") else str(p) for p in problems]
        typer.echo(json.dumps(summary, indent=2, default=str))
    else:
        t = Table(title=f"session {session}")
        t.add_column("item")
        t.add_column("value")
        for k, v in summary.items():
            t.add_row(k, json.dumps(v, default=str) if isinstance(v, dict | list) else str(v))
        Console().print(t)
        if problems is not None:
            typer.echo("integrity: ok" if not problems else f"integrity: {len(problems)} problem(s)")
            for p in problems:
                typer.echo(f"  {p}")
    if problems:
        raise typer.Exit(1)
