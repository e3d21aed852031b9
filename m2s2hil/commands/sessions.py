"""``m2s2hil sessions``: list stored sessions, show one, rebuild a damaged journal.

``list``, ``show`` and ``show --verify`` only read: they open the journal read-only and
change nothing in the folder, even while a capture writes the session. A damaged journal
is one line (``show``) or one row marked ``damaged`` (``list``, the others still listed);
``repair`` rebuilds it from the frame files' own metadata and the manifest."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path
from typing import Any

import typer
from rich.console import Console
from rich.table import Table

from m2s2hil.commands.compact import compact_cmd

app = typer.Typer(help="Stored sessions.", no_args_is_help=True)
app.command("compact")(compact_cmd)


def _when(t: float | None) -> str:
    return "-" if t is None else dt.datetime.fromtimestamp(t, dt.UTC).strftime("%Y-%m-%d %H:%M:%S")


@app.command("list")
def list_cmd(
    root: Path | None = typer.Option(None, "--root", help="data root (default: $M2S2HIL_DATA or ./sessions)"),
) -> None:
    """Every session under the data root, newest first."""
    from m2s2hil.store.catalogue import default_data_root, list_sessions

    root = root or default_data_root()
    infos = list_sessions(root)
    t = Table(title=f"sessions in {root}")
    for col in ("session", "state", "satellite", "build", "frames", "updated (UTC)"):
        t.add_column(col)
    for s in infos:
        t.add_row(s.session_id, s.state, s.satellite or "-", s.build or "-", str(s.frames), _when(s.updated))
    Console(width=200).print(t)
    if not infos:
        typer.echo("no sessions")
    for s in infos:
        if s.state == "damaged":
            typer.echo(f"{s.session_id}: damaged: {s.error}; rebuild with: m2s2hil sessions repair "
                       f"{s.session_id} --root {root}")


@app.command("repair")
def repair_cmd(
    session: str = typer.Argument(..., help="session id"),
    root: Path | None = typer.Option(None, "--root", help="data root"),
    force: bool = typer.Option(False, "--force", help="rebuild even a sound journal"),
) -> None:
    """Rebuild a damaged journal from the frame files' metadata and the manifest (the old
    journal is kept beside it; damaged files go to quarantine/ and a resume recaptures them)."""
    from m2s2hil.store.catalogue import default_data_root
    from m2s2hil.store.repair import repair_session

    report = repair_session(root or default_data_root(), session, force=force)
    typer.echo(report.line())


@app.command("register")
def register_cmd(
    session: str = typer.Argument(..., help="session id"),
    root: Path | None = typer.Option(None, "--root", help="data root"),
    max_frames: int = typer.Option(24, "--max-frames", min=3, max=500,
                                   help="frames to fit, spread over the sweep"),
    relabel: bool = typer.Option(True, "--relabel/--no-relabel",
                                 help="rewrite every frame's projected labels at the refined placement"),
) -> None:
    """Register the twin to a session's frames (offset, yaw, tilt bias, scale) and store it;
    then (unless --no-relabel) re-project every frame's labels at the new placement."""
    from m2s2hil.store.catalogue import default_data_root
    from m2s2hil.store.session import SessionStore
    from m2s2hil.twin.registration import EVENT_KIND, register_session

    store = SessionStore.open(root or default_data_root(), session, mode="write")
    try:
        if relabel:  # a damaged label file stops us before anything is written
            from m2s2hil.store.relabel import check_label_file

            for fr in store.frames():
                check_label_file(store, fr.event_id)
        reg = register_session(store, max_frames=max_frames, record=False)
        event = store.record_event(EVENT_KIND, reg.as_dict())
        relabelled = _relabel(store, reg, event) if relabel else None
    finally:
        store.close()
    p = reg.placement
    typer.echo(f"registered {session}: offset ({p.dx_mm:+.2f}, {p.dy_mm:+.2f}) mm, yaw {p.yaw_deg:+.2f} deg, "
               f"tilt bias {p.tilt_bias_deg:+.2f} deg, scale {p.scale:.3f}; residual {reg.residual:.3f} "
               f"over {reg.frames} frames ({reg.azimuth_span_deg:.0f} deg of azimuth)")
    if relabelled is not None:
        typer.echo(f"projected labels rewritten for {relabelled} frame(s) (registration event {event})")


def _relabel(store: Any, reg: Any, event: int) -> int:
    """Re-project every frame's labels at ``reg``'s placement and swap them in, frame by frame
    (m2s2hil.store.relabel); the metadata names the registration event that made them."""
    from m2s2hil.store.relabel import replace_frame_labels
    from m2s2hil.twin.labels import session_labels

    when = next((e.get("time") for e in reversed(store.events()) if e.get("seq") == event), None)
    provenance = {"event": event, "time": when, "residual": round(float(reg.residual), 4),
                  "frames": reg.frames, "stage": "session"}
    n = 0
    for event_id, pl in session_labels(store, reg):
        replace_frame_labels(store, event_id, pl.labels, {**pl.meta(), "registration": provenance},
                             tag=f"r{event}")
        n += 1
    return n


@app.command("show")
def show_cmd(
    session: str = typer.Argument(..., help="session id"),
    root: Path | None = typer.Option(None, "--root", help="data root"),
    verify: bool = typer.Option(False, "--verify", help="recompute every file's sha256"),
    as_json: bool = typer.Option(False, "--json", help="print the summary as JSON"),
) -> None:
    """A session's summary (and, with --verify, its integrity check)."""
    from m2s2hil.analysis.qc import qc_summary
    from m2s2hil.store.catalogue import default_data_root
    from m2s2hil.store.session import SessionStore

    store = SessionStore.open(root or default_data_root(), session)
    try:
        summary = store.summary()
        qc = qc_summary(store.frames())
        if qc.get("scored"):
            summary["qc"] = qc
        from m2s2hil.twin.registration import stored_registration

        registration = stored_registration(store)
        if registration is not None:
            summary["registration"] = registration
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
