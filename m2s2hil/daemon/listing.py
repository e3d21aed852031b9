"""What the API lists and serves from the session store on disk: sessions, frames, frame
files and a journal replayed as events. Functions here read; they change nothing, but for
:func:`end_killed_renders`, which a daemon start with resumption runs first, on the renders a
killed process left unfinished (their own end: a render is not resumed)."""

from __future__ import annotations

import contextlib
import json
import logging
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any, Literal

from m2s2hil.drivers.clock import Clock
from m2s2hil.errors import M2S2Error
from m2s2hil.store.catalogue import list_sessions
from m2s2hil.store.errors import SessionCorrupt, SessionNotFound
from m2s2hil.store.owner_lock import SessionLocked
from m2s2hil.store.records import frame_record
from m2s2hil.store.session import SessionStore
from m2s2hil.twin.synth import STOPPED_EVENT, planned_views

from .errors import Conflict, UnknownSession
from .jobqueue import Job

log = logging.getLogger(__name__)


def open_store(root: Path, session_id: str, clock: Clock,
               mode: Literal["read", "write"] = "read") -> SessionStore:
    """Open a stored session (the caller closes it); :class:`UnknownSession` when there is none."""
    try:
        return SessionStore.open(root, session_id, clock=clock, mode=mode)
    except SessionNotFound:
        raise UnknownSession(f"no session {session_id!r}") from None


@contextlib.contextmanager
def stored(root: Path, session_id: str, clock: Clock) -> Iterator[SessionStore]:
    """A stored session opened for one request; :class:`Conflict` when it cannot be read."""
    try:
        store = open_store(root, session_id, clock)
    except SessionCorrupt as exc:
        raise Conflict(f"session {session_id} cannot be read: {exc}") from None
    try:
        yield store
    finally:
        store.close()


class PlannedCounts:
    """Events each session's plan holds, expanded once per session (plans do not change)."""

    def __init__(self) -> None:
        self._n: dict[str, int] = {}
        self._frames: dict[str, int] = {}  # of those, the lit frames (the rest are master darks)

    def set(self, session_id: str, n: int) -> None:
        self._n[session_id] = n

    def _expand(self, store: SessionStore) -> None:
        if store.kind == "synthetic":  # its plan is its views; its sweep holds only the HIL poses
            views = planned_views(store)
            n = views if views is not None else len(store.completed_event_ids())
            self._n[store.session_id] = self._frames[store.session_id] = n
            return
        events = store.sweep.expand(store.rig)
        self._n[store.session_id] = len(events)
        self._frames[store.session_id] = sum(1 for e in events if e.kind == "frame")

    def of(self, store: SessionStore) -> int:
        sid = store.session_id
        if sid not in self._n:
            self._expand(store)
        return self._n[sid]

    def frames_known(self, session_id: str) -> int | None:
        """The plan's lit frames if its plan was expanded already (e.g. by :meth:`of`)."""
        return self._frames.get(session_id)

    def frames(self, store: SessionStore) -> int:
        """The plan's lit frames: ``total`` counts the master darks too (36 frames + 1 dark = 37)."""
        sid = store.session_id
        if sid not in self._frames:
            self._expand(store)
        return self._frames[sid]


def session_rows(root: Path, jobs: Mapping[str, Job], *, state: str | None = None,
                 satellite: str | None = None, build: str | None = None) -> list[dict]:
    """Sessions under the data root, newest first, filtered; the state of a session this daemon
    runs or queues is the live one."""
    rows: list[dict] = []
    for info in list_sessions(root):
        job = jobs.get(info.session_id)
        st = (job.live_state() if job is not None else None) or info.state  # as its status says
        rows.append({"session_id": info.session_id, "state": st, "satellite": info.satellite,
                     "build": info.build, "created": info.created, "updated": info.updated,
                     "frames": info.frames, "error": info.error})
    if state:
        rows = [r for r in rows if r["state"] == state]
    if satellite:
        rows = [r for r in rows if (r["satellite"] or "").lower() == satellite.lower()]
    if build:
        rows = [r for r in rows if (r["build"] or "").lower() == build.lower()]
    return rows


def frame_page(store: SessionStore, *, offset: int = 0, limit: int = 50) -> tuple[list[Any], int]:
    """One page of the session's frame records in plan order, and how many there are."""
    total = store.journal.query("SELECT COUNT(*) AS n FROM frames")[0]["n"]
    rows = store.journal.query("SELECT * FROM frames ORDER BY idx LIMIT ? OFFSET ?", (limit, offset))
    return [frame_record(r) for r in rows], int(total)


def frame_bytes(store: SessionStore, session_id: str, n: int,
                role: Literal["raw", "preview"]) -> tuple[bytes, str]:
    """The checked bytes of frame ``n``'s raw or preview file, and its path in the session."""
    rows = store.journal.query("SELECT * FROM frames WHERE idx = ?", (n,))
    if not rows:
        raise UnknownSession(f"session {session_id} has no frame {n} (frames are numbered by their "
                             "index in the plan; GET /sessions/{id}/frames lists them)")
    rec = frame_record(rows[0])
    f = rec.files.get(role)
    if f is None:
        raise UnknownSession(f"frame {n} of session {session_id} has no {role} file")
    base = store.path.resolve()
    if not (base / f.path).resolve().is_relative_to(base):
        raise SessionCorrupt(f"journal of {session_id} names a file outside its folder")
    return store.read_file(f, check=True), f.path


def journal_events(store: SessionStore) -> tuple[str, list[dict]]:
    """(state, events) replayed from the journal, in time order (frames before other events
    of the same instant)."""
    items: list[tuple[float, int, str, dict]] = []
    for r in store.journal.query("SELECT * FROM frames ORDER BY seq"):
        meta = json.loads(r["meta"])
        ev = meta.get("event") or {}
        files = json.loads(r["files"])
        items.append((r["time"], 0, "frame", {
            "event_id": r["event_id"], "index": r["idx"], "lighting": ev.get("lighting"),
            "elevation": ev.get("elevation"), "azimuth_deg": ev.get("nominal_azimuth_deg"),
            "exposure_s": meta.get("exposure_s"), "path": (files.get("raw") or {}).get("path"),
        }))
    for e in store.events():
        p = e.get("payload") or {}
        if e["kind"] == "fault":
            items.append((e["time"], 1, "fault", {"fault": p}))
        elif e["kind"] in ("run_started", "resumed"):
            items.append((e["time"], 1, "state", {"new": "running", "reason": e["kind"]}))
        elif e["kind"] in ("interrupted", "cancelled", "aborted", "run_finished"):
            state = p.get("state") or e["kind"]
            items.append((e["time"], 1, "finished" if e["kind"] == "run_finished" else "state",
                          {"new": state, **({"summary": p} if e["kind"] == "run_finished" else p)}))
    items.sort(key=lambda t: (t[0], t[1]))
    return store.state, [{"kind": k, "wall": t, **d} for t, _, k, d in items]



#: Journal states a daemon start resumes a capture from.
RESUMABLE = frozenset({"running", "pausing", "interrupted", "created", "queued"})
#: Journal states of a render that had not ended when its process went away.
UNFINISHED_RENDER = frozenset({"created", "queued", "running"})
KILLED_RENDER_REASON = "its process ended before the render finished (found at daemon start)"


def interrupted_sessions(root: Path) -> list[str]:
    """The sessions a daemon start resumes, in order: those that were running, then those that
    were waiting, oldest first in each. Captures only: a synthetic session is never handed to
    the capture engine (it has no sweep to capture, and the engine would write HIL frames into
    it); one a killed process left unfinished is ended by :func:`end_killed_renders` instead.
    Reads only."""
    infos = list(reversed(list_sessions(root)))  # oldest first
    hil = [i for i in infos if i.state not in RESUMABLE or _kind(root, i.session_id) != "synthetic"]
    first = [i.session_id for i in hil if i.state in ("running", "pausing", "interrupted")]
    return first + [i.session_id for i in hil if i.state in ("created", "queued")]


def end_killed_renders(root: Path) -> list[str]:
    """End every synthetic session a killed process left unfinished (:func:`end_killed_render`);
    returns the ids ended."""
    return [i.session_id for i in list_sessions(root)
            if i.state in UNFINISHED_RENDER and _kind(root, i.session_id) == "synthetic"
            and end_killed_render(root, i.session_id)]


def _kind(root: Path, session_id: str) -> str | None:
    """A session's kind, or None when it cannot be read (the resumption says why)."""
    try:
        with SessionStore.open(root, session_id) as store:
            return store.kind
    except (M2S2Error, OSError):
        return None


def end_killed_render(root: Path, session_id: str) -> bool:
    """End a synthetic session a killed process left ``created``/``queued``/``running``: its
    views are checked (a damaged one goes to ``quarantine/``, as a resume does), the manifest
    written and the session marked ``aborted``, the reason in a ``synthetic_stopped`` event, as
    a render stopped by a daemon shutdown. A render cannot be resumed (render it again), so this
    is its end. Left alone while another process holds it (a ``m2s2hil synth`` still rendering
    on this data root); False then, or when it cannot be opened."""
    try:
        store = SessionStore.open(root, session_id, mode="write")
    except SessionLocked:
        return False
    except (M2S2Error, OSError) as exc:
        log.error("synthetic session %s was left unfinished and cannot be ended: %s", session_id, exc)
        return False
    with store:
        if store.kind != "synthetic" or store.state not in UNFINISHED_RENDER:
            return False  # changed since it was listed
        was = store.state
        lost = store.check_stored()
        views = len(store.completed_event_ids())
        store.record_event(STOPPED_EVENT, {"reason": KILLED_RENDER_REASON, "was": was, "views": views,
                                           "of": planned_views(store), "quarantined": len(lost)})
        store.complete("aborted")
    log.warning("synthetic session %s was %s when its process ended: marked aborted, %d view(s) kept",
                session_id, was, views)
    return True
