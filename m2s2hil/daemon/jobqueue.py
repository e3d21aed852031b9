"""The sessions a daemon knows (:class:`Job`) and the first-in-first-out queue of those that
wait for the rig (:class:`JobQueue`)."""

from __future__ import annotations

import collections
import contextlib
import logging
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

from m2s2hil.engine.runner import Engine
from m2s2hil.store.session import SessionStore

if TYPE_CHECKING:
    from .estop import SafeCheck

log = logging.getLogger(__name__)

#: A job's life in this daemon (the session's own state is in its journal and its engine).
JobState = Literal["queued", "running", "finished", "cancelled"]


@dataclass(eq=False)
class Job:
    """A session this daemon process knows: queued, running, or finished since it started."""

    session_id: str
    store: SessionStore
    resume: bool
    queued_at: float
    planned: int
    state: JobState = "queued"
    engine: Engine | None = None
    run: int = 1  # which run of the session the engine is (1 + runs in the journal before it)
    error: str | None = None
    final_state: str | None = None  # completed / aborted / failed / cancelled, once finished
    shutdown_paused: bool = False  # parked by a daemon shutdown (not by an operator)
    finished: threading.Event = field(default_factory=threading.Event)
    # Reads of the store in progress, and whether it closes when the last of them ends: a job
    # retired while a request was reading it closed the store under that request.
    _readers: int = field(default=0, init=False, repr=False)
    _close_pending: bool = field(default=False, init=False, repr=False)
    _lease_lock: threading.Lock = field(default_factory=threading.Lock, init=False, repr=False)

    @contextlib.contextmanager
    def reading(self) -> Iterator[SessionStore | None]:
        """The store for one read, kept open until the read ends; None once it was retired."""
        with self._lease_lock:
            if self._close_pending:
                store = None
            else:
                self._readers += 1
                store = self.store
        try:
            yield store
        finally:
            if store is not None:
                with self._lease_lock:
                    self._readers -= 1
                    close = self._close_pending and self._readers == 0
                if close:
                    self._close_store()

    def retire_store(self) -> None:
        """Close the store now, or when the last read of it ends."""
        with self._lease_lock:
            self._close_pending = True
            close = self._readers == 0
        if close:
            self._close_store()

    def _close_store(self) -> None:
        with contextlib.suppress(Exception):
            self.store.close()

    def live_state(self) -> str | None:
        """The session's state as this daemon shows it (status and listing alike): an
        e-stopped session's engine ended ``aborted``, its journal says ``estopped``, and so
        do we. None when only the journal knows (a job cancelled, or finished without engine)."""
        if self.final_state == "estopped":
            return "estopped"
        if self.engine is not None:
            return self.engine.state.value
        return "queued" if self.state == "queued" else None

    def record_interruption(self, reason: str, check: SafeCheck) -> str:
        """Journal this session parked by a shutdown; it becomes ``interrupted`` (resumable)
        unless an operator had paused it before. Returns its state."""
        state = "paused"
        try:
            self.store.record_event("interrupted", {"reason": reason, "rig_safe": check.safe,
                                                    "lamps_on": check.lamps_on, "moving": check.moving})
            if self.shutdown_paused:  # an operator's earlier pause stays a pause
                self.store.set_state("interrupted")
                state = "interrupted"
        except Exception as exc:
            log.error("could not record the interruption of %s: %s", self.session_id, exc)
        log.info("session %s parked at a safe boundary and saved (%s)", self.session_id, state)
        return state

    def mark_finished(self, state: str) -> bool:
        """Record the session's end state (once); False when it was already finished."""
        if self.finished.is_set():
            return False
        self.state = "finished" if state != "cancelled" else "cancelled"
        self.final_state = state
        if self.error is None and self.engine is not None:
            self.error = self.engine.status().error
        self.finished.set()
        return True


class JobQueue:
    """The jobs by id (queued, running, or among the last finished) and the FIFO of those
    waiting for the rig.

    It takes no lock itself: the manager changes it and reads the FIFO under its own lock;
    looking a job up by id is one dict read and needs none."""

    def __init__(self) -> None:
        self.jobs: dict[str, Job] = {}
        self.waiting: collections.deque[Job] = collections.deque()
        self._finished_order: collections.deque[str] = collections.deque()

    def __len__(self) -> int:
        """Jobs waiting for the rig."""
        return len(self.waiting)

    def get(self, session_id: str) -> Job | None:
        return self.jobs.get(session_id)

    def add(self, job: Job) -> None:
        """Know the job and queue it last."""
        self.jobs[job.session_id] = job
        self.waiting.append(job)

    def pop_next(self) -> Job:
        return self.waiting.popleft()

    def put_back(self, job: Job) -> None:
        """Queue a job first again (it was taken but could not start)."""
        self.waiting.appendleft(job)

    def remove(self, job: Job) -> None:
        with contextlib.suppress(ValueError):
            self.waiting.remove(job)

    def full(self, limit: int) -> bool:
        return len(self.waiting) >= limit

    def position(self, job: Job) -> int | None:
        """1 for the next to start; None when the job does not wait."""
        try:
            return list(self.waiting).index(job) + 1
        except ValueError:
            return None

    def items(self) -> list[dict]:
        return [{"session_id": j.session_id, "position": i + 1, "resume": j.resume,
                 "queued_at": j.queued_at} for i, j in enumerate(self.waiting)]

    def retire(self, job: Job, keep: int) -> None:
        """Note a finished job; forget finished ones beyond the last ``keep`` (reads of those go
        to the journal on disk from then on)."""
        self._finished_order.append(job.session_id)
        while len(self._finished_order) > keep:
            old = self._finished_order.popleft()
            gone = self.jobs.get(old)
            if gone is not None and gone.finished.is_set():
                del self.jobs[old]
                # Its journal would stay open until the garbage collector found it (the soak
                # saw 48 open where 32 are kept): reads go to disk from now on.
                gone.retire_store()
