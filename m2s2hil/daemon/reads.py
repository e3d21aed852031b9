"""What the daemon reads for its clients: a session's status, the session list, frames and
their files, a journal's events. A session this daemon knows (queued, running, or among the
last finished) is read live; any other from its folder, opened for the one request."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any, Literal

from m2s2hil.store.session import SessionStore

from . import listing
from .errors import UnknownSession
from .status import disk_status, engine_status, queued_status

if TYPE_CHECKING:
    from .manager import SessionManager


class SessionReads:
    def __init__(self, sessions: SessionManager) -> None:
        self._sessions = sessions
        self.planned = listing.PlannedCounts()  # planned events per session, computed once

    def status(self, session_id: str) -> dict:
        """A status snapshot (the body of ``GET /sessions/{id}``); :class:`UnknownSession`."""
        sessions = self._sessions
        job = sessions.job(session_id)
        if job is None:
            return self.disk_status(session_id)
        if job.engine is not None:
            return self._with_frames(engine_status(job, job.engine), job.store)
        return self._with_frames(queued_status(job, sessions.position(job)), job.store)  # or cancelled

    def _with_frames(self, st: dict, store: SessionStore) -> dict:
        """``total`` counts captures (lit frames and master darks); say how many of each."""
        try:
            frames = self.planned.frames(store)
        except Exception:  # a plan this rig cannot expand: the counts stay unknown
            return st
        st["planned_frames"] = frames
        st["planned_darks"] = max(0, int(st.get("total") or 0) - frames)
        return st

    def disk_status(self, session_id: str) -> dict:
        """The status from the session's journal, whatever this daemon knows of it."""
        st = disk_status(self._sessions.root, session_id, self._sessions.rig.clock, self.planned)
        frames = self.planned.frames_known(session_id)  # expanded by disk_status with the total
        if frames is not None and "total" in st:
            st["planned_frames"], st["planned_darks"] = frames, max(0, int(st["total"]) - frames)
        return st

    def sessions(self, *, state: str | None = None, satellite: str | None = None, build: str | None = None,
                 offset: int = 0, limit: int = 50) -> tuple[list[dict], int]:
        """Sessions under the data root, newest first, with this daemon's live view on top."""
        rows = listing.session_rows(self._sessions.root, self._sessions.known_jobs(), state=state,
                                    satellite=satellite, build=build)
        page = []
        for r in rows[offset:offset + limit]:
            try:
                page.append(self.status(r["session_id"]))
            except UnknownSession:  # removed meanwhile
                continue
        return page, len(rows)

    @contextlib.contextmanager
    def reading(self, session_id: str) -> Iterator[SessionStore]:
        """The session's store for reading: the live one, or one opened for this request."""
        job = self._sessions.job(session_id)
        if job is not None:
            with job.reading() as live:
                if live is not None:
                    yield live
                    return
        with listing.stored(self._sessions.root, session_id, self._sessions.rig.clock) as store:
            yield store

    def frames(self, session_id: str, *, offset: int = 0, limit: int = 50) -> tuple[list[Any], int]:
        with self.reading(session_id) as store:
            return listing.frame_page(store, offset=offset, limit=limit)

    def frame_file(self, session_id: str, n: int, role: Literal["raw", "preview"]) -> tuple[bytes, str]:
        with self.reading(session_id) as store:
            return listing.frame_bytes(store, session_id, n, role)

    def journal_events(self, session_id: str) -> tuple[str, list[dict]]:
        """(state, events) replayed from the journal for a session no engine here knows."""
        with self.reading(session_id) as store:
            return listing.journal_events(store)
