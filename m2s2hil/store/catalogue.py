"""The sessions on a data root: where the root is by default, what ``list_sessions`` finds
there, and one session's summary (``sessions show``, the report, the API).

Listing only reads: every journal is opened read-only, and a session whose journal cannot
be trusted is listed as ``damaged`` with the reason, not skipped. (Not to be confused with
m2s2hil.catalog, the catalogue of satellites and their materials.)
"""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path
from typing import TYPE_CHECKING, Any

from m2s2hil.store.journal import Journal, JournalDamaged, JournalError
from m2s2hil.store.layout import JOURNAL, SESSION_ID_RE, created_from_id
from m2s2hil.store.records import SessionInfo

if TYPE_CHECKING:
    from m2s2hil.store.session import SessionStore


def default_data_root() -> Path:
    """``$M2S2HIL_DATA`` if set, else ``./sessions``."""
    return Path(os.environ.get("M2S2HIL_DATA") or "sessions")


def _info(p: Path) -> SessionInfo:
    j = Journal(p / JOURNAL, read_only=True)
    try:
        damage = j.check()
        if damage is not None:
            raise JournalDamaged(damage)
        row = j.session()
        n = j.query("SELECT COUNT(*) AS n FROM frames")[0]["n"]
        return SessionInfo(session_id=p.name, path=str(p), state=row["state"], satellite=row["satellite"],
                           build=row["build"], created=row["created"], updated=row["updated"], frames=n)
    finally:
        j.close()


def list_sessions(root: str | Path) -> list[SessionInfo]:
    """Every session folder under ``root`` (newest first); a session whose journal cannot
    be read or fails ``quick_check`` is listed as ``damaged`` with the reason in ``error``,
    and the others are listed all the same. Read-only: nothing is changed."""
    root = Path(root)
    if not root.is_dir():
        return []
    out: list[SessionInfo] = []
    for p in root.iterdir():
        if not p.is_dir() or p.name.startswith(".") or not SESSION_ID_RE.match(p.name):
            continue
        if not (p / JOURNAL).is_file():
            continue
        try:
            out.append(_info(p))
        except (JournalError, KeyError, sqlite3.Error) as exc:
            out.append(SessionInfo(session_id=p.name, path=str(p), state="damaged",
                                   created=created_from_id(p.name), error=str(exc)))
    out.sort(key=lambda s: (s.created or 0.0, s.session_id), reverse=True)
    return out


def summary(store: SessionStore) -> dict[str, Any]:
    """An open session's counts against its plan: frames and darks stored, skipped, missing,
    faults, bytes, and its provenance."""
    row = store.journal.session()
    planned = store.sweep.expand(store.rig)
    planned_frames = {e.event_id for e in planned if e.kind == "frame"}
    planned_darks = {e.event_id for e in planned if e.kind == "dark"}
    done = store.completed_event_ids()
    frames = store.frames()
    darks = store.darks()
    if store.kind == "synthetic":  # its plan is what it rendered (m2s2hil.twin.synth), no darks
        planned_frames, planned_darks = {fr.event_id for fr in frames}, set()
    total_bytes = sum(f.bytes for fr in frames for f in fr.files.values())
    total_bytes += sum(f.bytes for d in darks for f in d.files.values())
    return {
        "session_id": store.session_id,
        "path": str(store.path),
        "satellite": store.sweep.satellite,
        "build": store.sweep.build,
        "state": row["state"],
        "created": row["created"],
        "updated": row["updated"],
        "planned_frames": len(planned_frames),
        "planned_darks": len(planned_darks),
        "frames": len(frames),
        "darks": len(done & planned_darks) + len({d.dark_id for d in darks} - planned_darks),
        "frames_planned_stored": len(planned_frames & done),
        "skipped": len(store.skipped_event_ids()),
        "missing": len(planned_frames - done),
        "faults": store.journal.query("SELECT COUNT(*) AS n FROM events WHERE kind = 'fault'")[0]["n"],
        "bytes": total_bytes,
        "rig_digest": store.rig_digest,
        "software_version": store.software_version,
    }
