"""Sessions into the queue: new ones from a sweep, existing ones from disk (resumption), and
the operator's resume or abort of a session that is only on disk.

Admission checks a plan against the rig and the disk (:mod:`.admission`), refuses while
the daemon shuts down (:class:`Conflict`) and when ``queue_limit`` sessions already wait
(:class:`QueueFull`); a session from disk must not be live here already and must have been
captured on this rig (its digest). Check-then-create is serialised by one lock, taken
before the queue's (see :mod:`.manager` for the order).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING

from m2s2hil.engine.build import RigChanged, check_rig_digest
from m2s2hil.plan import Sweep
from m2s2hil.store.session import SessionStore

from . import listing
from .admission import check_room, check_sweep
from .engine_requests import Action
from .errors import Conflict, QueueFull
from .hold import QueueHold
from .jobqueue import Job, JobQueue
from .status import RESUMABLE_BY_HAND, TERMINAL

if TYPE_CHECKING:
    from .manager import SessionManager

log = logging.getLogger(__name__)


class Submissions:
    """Creates and requeues sessions for :class:`~.manager.SessionManager`, whose queue,
    condition and hold it shares."""

    def __init__(self, sessions: SessionManager, queue: JobQueue, cond: threading.Condition,
                 hold: QueueHold) -> None:
        self._sessions = sessions
        self._queue = queue  # changed under cond
        self._cond = cond
        self._hold = hold
        self._lock = threading.Lock()  # serialises check-then-create of new sessions

    def submit(self, sweep: Sweep) -> Job:
        """Check the plan against the rig and the disk, create the session and queue it."""
        sessions = self._sessions
        cfg = sessions.rig.config
        planned, need = check_sweep(sweep, cfg, sessions.max_plan_frames, root=sessions.root)
        with self._lock:
            self._check_accepting()
            with self._cond:
                if self._would_wait() and self._queue.full(sessions.queue_limit):
                    raise QueueFull(
                        f"{len(self._queue)} session(s) already wait for the rig "
                        f"(limit {sessions.queue_limit}); "
                        "cancel one (POST /sessions/{id}/abort) or retry when the running one ends"
                    )
            check_room(sessions.root, need)
            store = SessionStore.create(sessions.root, sweep, cfg, clock=sessions.rig.clock)
            store.set_state("queued")
            store.record_event("queued", {"via": "api", "planned_events": planned})
            job = Job(store.session_id, store, resume=False, queued_at=time.time(), planned=planned)
            with self._cond:
                self._queue.add(job)
                sessions.reads.planned.set(job.session_id, planned)
                self._cond.notify_all()
        log.info("session %s queued (%d events)", job.session_id, job.planned)
        return job

    def requeue(self, session_id: str, *, reason: str, check_limit: bool = True) -> Job:
        """Queue a session from disk again (resumption): it will capture what it lacks."""
        sessions = self._sessions
        with self._lock:
            self._check_accepting()
            with self._cond:
                live = self._queue.get(session_id)
                if live is not None and not live.finished.is_set():
                    raise Conflict(f"session {session_id} is already {live.state} in this daemon")
                if check_limit and self._would_wait() and self._queue.full(sessions.queue_limit):
                    raise QueueFull(f"{len(self._queue)} session(s) already wait for the rig "
                                    f"(limit {sessions.queue_limit})")
            store = self._open(session_id)
            try:
                if store.kind == "synthetic":  # the engine would capture HIL frames into a render
                    raise Conflict(f"session {session_id} is a synthetic render: it is not resumed "
                                   "(render it again: POST /synthetic)")
                try:
                    check_rig_digest(store, sessions.rig.config)
                except RigChanged as exc:
                    raise Conflict(str(exc)) from None
                planned = sessions.reads.planned.of(store)
                was = store.state
                store.record_event("requeued", {"reason": reason, "was": was})
                store.set_state("queued")
            except BaseException:
                store.close()
                raise
            job = Job(session_id, store, resume=True, queued_at=time.time(), planned=planned)
            with self._cond:
                self._queue.add(job)
                self._cond.notify_all()
        log.info("session %s queued for resumption (%s; was %s)", session_id, reason, was)
        return job

    def control_stored(self, session_id: str, action: Action) -> dict:
        """pause / resume / abort a session that is on disk but not live in this daemon: resume
        requeues it, abort marks it aborted; :class:`Conflict` for anything else."""
        sessions = self._sessions
        info = sessions.reads.disk_status(session_id)
        state = info["state"]
        if action == "resume" and state == "estopped" and self._hold.reason == "emergency stop":
            raise Conflict(f"session {session_id} was stopped by the emergency stop, which is not cleared: "
                           "make the rig safe, clear it with POST /queue/release, then resume")
        if action == "resume" and state in RESUMABLE_BY_HAND:
            self.requeue(session_id, reason="resumed by the operator")
            return sessions.reads.status(session_id)
        if action == "abort" and state in RESUMABLE_BY_HAND:
            store = self._open(session_id)
            try:
                store.record_event("aborted", {"by": "operator", "was": state})
                store.set_state("aborted")
            finally:
                store.close()
            return sessions.reads.status(session_id)
        if state in TERMINAL:
            raise Conflict(f"session {session_id} is {state}: there is nothing to {action}")
        raise Conflict(f"session {session_id} is {state} and not running in this daemon: it cannot be "
                       f"{action}d" + ("; resume queues it again" if state in RESUMABLE_BY_HAND else ""))

    def _open(self, session_id: str) -> SessionStore:
        """Open for writing (owner lock held): the daemon requeues, aborts and resumes it."""
        sessions = self._sessions
        return listing.open_store(sessions.root, session_id, sessions.rig.clock, mode="write")

    def _would_wait(self) -> bool:
        return self._sessions.owner() is not None or bool(self._queue) or self._hold.reason is not None

    def _check_accepting(self) -> None:
        if self._sessions.closing:
            raise Conflict("the daemon is shutting down; no new sessions are accepted")
