"""The sessions on a data root: where the root is by default, what ``list_sessions`` finds
there, and one session's summary (``sessions show``, the report, the API).

Listing only reads: every journal is opened read-only, and a session whose journal cannot
be trusted is listed as ``damaged`` with the reason, not skipped. (Not to be confused with
m2s2hil.catalog, the catalogue of satellites and their materials.)
"""

from __future__ import annotations

import json
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


#: The event a synthetic session's plan is recorded in (``m2s2hil.twin.synth.PLAN_EVENT``, which
#: writes it: the store sits below the twin, so it reads the event itself).
SYNTHETIC_PLAN_EVENT = "synthetic_plan"


def synthetic_planned_views(store: SessionStore) -> int | None:
    """The views a synthetic session was planned to render (its plan event, as
    ``m2s2hil.twin.synth.planned_views`` reads it); None without one."""
    rows = store.journal.query("SELECT payload FROM events WHERE kind = ? ORDER BY seq LIMIT 1",
                               (SYNTHETIC_PLAN_EVENT,))
    views = json.loads(rows[0]["payload"]).get("views") if rows else None
    return int(views) if isinstance(views, int | float) else None


def summary(store: SessionStore) -> dict[str, Any]:
    """An open session's kind and counts against its plan: frames and darks stored, skipped,
    missing, faults, bytes, and its provenance. A synthetic session's plan is its views (its
    plan event; the views stored when it has none), without darks."""
    row = store.journal.session()
    kind = store.kind
    done = store.completed_event_ids()
    frames = store.frames()
    darks = store.darks()
    if kind == "synthetic":  # the sweep stored with it holds only the HIL poses: not its plan
        views = synthetic_planned_views(store)
        n_planned = len(frames) if views is None else views
        stored = len({fr.event_id for fr in frames} & done)
        counts = {"planned_frames": n_planned, "planned_darks": 0, "frames": len(frames), "darks": len(darks),
                  "frames_planned_stored": min(stored, n_planned), "missing": max(0, n_planned - stored)}
    else:
        planned = store.sweep.expand(store.rig)
        planned_frames = {e.event_id for e in planned if e.kind == "frame"}
        planned_darks = {e.event_id for e in planned if e.kind == "dark"}
        counts = {
            "planned_frames": len(planned_frames), "planned_darks": len(planned_darks), "frames": len(frames),
            "darks": len(done & planned_darks) + len({d.dark_id for d in darks} - planned_darks),
            "frames_planned_stored": len(planned_frames & done), "missing": len(planned_frames - done),
        }
    total_bytes = sum(f.bytes for fr in frames for f in fr.files.values())
    total_bytes += sum(f.bytes for d in darks for f in d.files.values())
    return {
        "session_id": store.session_id,
        "path": str(store.path),
        "kind": kind,
        "satellite": store.sweep.satellite,
        "build": store.sweep.build,
        "state": row["state"],
        "created": row["created"],
        "updated": row["updated"],
        "planned_frames": counts["planned_frames"],
        "planned_darks": counts["planned_darks"],
        "frames": counts["frames"],
        "darks": counts["darks"],
        "frames_planned_stored": counts["frames_planned_stored"],
        "skipped": len(store.skipped_event_ids()),
        "missing": counts["missing"],
        "faults": store.journal.query("SELECT COUNT(*) AS n FROM events WHERE kind = 'fault'")[0]["n"],
        "bytes": total_bytes,
        "rig_digest": store.rig_digest,
        "software_version": store.software_version,
    }
