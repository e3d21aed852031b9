"""``m2s2hil import PATH --layout m2s2 [--root DATA_ROOT]``.

Register with ``app.add_typer(importer.app, name="import")`` (the command is the group's
callback) or ``app.command("import")(importer.import_cmd)``.
"""

from __future__ import annotations

from pathlib import Path

import typer

from m2s2hil.store.catalogue import default_data_root
from m2s2hil.store.importer import import_dataset

app = typer.Typer(
    help="Import released M2S2 data (or camera raws) into sessions.",
    # The command is the group callback: let its options follow the PATH argument.
    context_settings={"allow_interspersed_args": True},
)


@app.callback(invoke_without_command=True)
def import_cmd(
    path: Path = typer.Argument(..., help="folder holding HIL/<Satellite>/b<N>/e<N>/<light>_<k>.png "
                                          "(and HIL16/, metadata/ when exported by m2s2hil: lossless)"),
    layout: str = typer.Option("m2s2", "--layout", help="input layout (m2s2)"),
    root: Path | None = typer.Option(None, "--root", help="data root (default: $M2S2HIL_DATA or ./sessions)"),
    step: float = typer.Option(10.0, "--azimuth-step",
                               help="degrees between consecutive indices k (when no exported metadata says)"),
) -> None:
    """Import PATH: one session per satellite build."""
    stores = import_dataset(path, root or default_data_root(), layout, azimuth_step_deg=step)
    for st in stores:
        with st:
            typer.echo(f"{st.session_id}: {len(st.frames())} frame(s)")
