"""``m2s2hil export SESSION --layout m2s2|hf|zarr|envi --out DIR [--root DATA_ROOT]`` (``--format`` is
the same option).

Exporting only reads the session (opened read-only; nothing is recorded in it). The export is
written beside ``--out`` and renamed into place, under a lock the daemon's exports share
(m2s2hil.daemon.export_lock): a second export into the same folder stops at once (exit 1).

Register with ``app.add_typer(export.app, name="export")`` (the command is the group's
callback, so no sub-command name is needed) or ``app.command("export")(export.export_cmd)``.
"""

from __future__ import annotations

from pathlib import Path

import typer

from m2s2hil.daemon.export_lock import export_once
from m2s2hil.errors import UsageError
from m2s2hil.store.catalogue import default_data_root
from m2s2hil.store.export import LAYOUTS
from m2s2hil.store.layout import JOURNAL
from m2s2hil.store.session import SessionStore

app = typer.Typer(
    help="Export a session as the published M2S2 layout, a Hugging Face dataset or a Zarr store.",
    # The command is the group callback: let its options follow the SESSION argument.
    context_settings={"allow_interspersed_args": True},
)


def open_session(session: str, root: Path | None) -> SessionStore:
    """A session by id under the data root, or by the path of its folder."""
    p = Path(session)
    if root is None and (p / JOURNAL).is_file():
        return SessionStore.open_path(p)
    return SessionStore.open(root or default_data_root(), session)


@app.callback(invoke_without_command=True)
def export_cmd(
    session: str = typer.Argument(..., help="session id (or the session's folder)"),
    out: Path = typer.Option(..., "--out", "-o", help="output folder"),
    layout: str = typer.Option("m2s2", "--layout", "--format",
                               help=f"one of: {', '.join((*LAYOUTS, 'envi'))}"),
    root: Path | None = typer.Option(None, "--root", help="data root (default: $M2S2HIL_DATA or ./sessions)"),
    overwrite: bool = typer.Option(False, "--overwrite", help="replace files already in --out"),
) -> None:
    """Export SESSION's frames with their metadata."""
    if layout == "envi":  # one ENVI pair per cube, m2s2hil.integrations.envi
        from m2s2hil.daemon.export_lock import export_lock
        from m2s2hil.integrations.envi import export_envi

        with open_session(session, root) as store, export_lock(out):
            envi = export_envi(store, out, overwrite=overwrite)
        typer.echo(f"exported {envi.images} cube(s) of {session} as envi to {out} ({len(envi.files)} files)")
        return
    if layout not in LAYOUTS:
        raise UsageError(f"--layout must be one of {', '.join((*LAYOUTS, 'envi'))}, not {layout!r}")
    with open_session(session, root) as store:
        res = export_once(store, out, layout, overwrite=overwrite)
    typer.echo(f"exported {res.images} image(s) of {session} as {layout} to {out} ({len(res.files)} files)")
