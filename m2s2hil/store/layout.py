"""Names in a session folder: the session id, the journal's file name, file names of events.

Layout of ``<root>/<session_id>/``::

    journal.sqlite            the journal (see m2s2hil.store.journal); the source of truth
    sweep.json, rig.json      human-readable copies of the plan and the rig
    frames/<event>.raw.tiff   raw mosaic, uint16, metadata JSON in ImageDescription
    frames/<event>.cube.tiff  processed cube (bands, H, W), float32, only when stored
    frames/<event>.preview.jpg  8-bit RGB quick-look (.png in legacy sessions)
    frames/<event>.<role>.png   a frame's extra file (e.g. ``truth_labels``; .tiff if not integer)
    darks/<dark>.tiff         master darks, uint16 (float32 in legacy sessions)
    quarantine/               files of captures a resume found damaged, moved aside
    manifest.json             every file with its sha256, written at completion

``<event>`` is the event id with ``/`` replaced by ``_`` (:func:`safe_name`).
"""

from __future__ import annotations

import re
import secrets
from datetime import UTC, datetime

from m2s2hil.errors import UsageError
from m2s2hil.plan import Sweep

JOURNAL = "journal.sqlite"
SESSION_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._+-]{0,127}$")


def check_session_id(session_id: str) -> str:
    """``session_id`` if it is a valid folder name (:data:`SESSION_ID_RE`), else UsageError."""
    if not SESSION_ID_RE.match(session_id):
        raise UsageError(f"invalid session id {session_id!r}: letters, digits, '.', '_', '+', '-' only")
    return session_id


def new_session_id(sweep: Sweep, wall: float) -> str:
    """``<UTC time>-<satellite>-<build>-<lighting…>-<4 hex>``: sorts by creation time."""
    ts = datetime.fromtimestamp(wall, UTC).strftime("%Y%m%dT%H%M%S")
    return f"{ts}-{sweep.satellite}-{sweep.build}-{'-'.join(sweep.lighting)}-{secrets.token_hex(2)}"


def created_from_id(session_id: str) -> float | None:
    """The creation time a generated id starts with (``20261124T214754-…``), for sorting."""
    try:
        return datetime.strptime(session_id[:15], "%Y%m%dT%H%M%S").replace(tzinfo=UTC).timestamp()
    except ValueError:
        return None


def safe_name(event_id: str) -> str:
    """An event id as a file name stem."""
    return re.sub(r"[^A-Za-z0-9._+-]", "_", event_id)
