"""One rig, one running session, a first-in-first-out queue of the others.

:class:`SessionManager` owns the opened :class:`~m2s2hil.rig.opened.Rig` and the data root.
``submissions.submit(sweep)`` (:class:`~.submission.Submissions`) checks the plan
against the rig, creates the session folder (state ``queued``) and queues it; a dispatcher
thread starts the next session when the rig is free, one
:class:`~m2s2hil.engine.runner.Engine` at a time, built by
:func:`~m2s2hil.engine.build.build_run` exactly as ``capture`` builds its run (so daemon
sessions get the same processing and capture-time QC). The queue is visible
(:meth:`queue`) and cancellable (``control(id, "abort")`` on a queued session).

Conflicts and what they get (the API maps these to HTTP codes):

- a session submitted while another runs waits in the queue (``queued``, with its
  position); when ``queue_limit`` sessions already wait: :class:`QueueFull` (429);
- pause / resume on a queued or finished session, or a transition the engine's state
  does not allow: :class:`Conflict` / ``IllegalTransition`` (409);
- abort on a queued session cancels it (state ``cancelled``);
- resume on a session that is on disk but not live (interrupted by a shutdown or a
  crash) queues it again; it captures only what is not stored yet.

After an emergency stop or a failed session the queue is *held*: nothing else starts
until :meth:`release` (an operator should look at the rig first). A hold is written to the
data root before it is acknowledged and read back by :meth:`start`
(:mod:`m2s2hil.daemon.hold`): a restart, a crash or a power loss does not release it.

Hardware access from request threads goes through :attr:`SessionManager.guard`
(:class:`~.rig_guard.RigGuard`: manual access, the rig's state, the emergency stop); reads
for clients through :attr:`SessionManager.reads` (:class:`~.reads.SessionReads`: status,
listings, frames, journals).

The manager coordinates; the parts live beside it: the queue entries in :mod:`.jobqueue`,
submission, requeueing and control of stored sessions in :mod:`.submission`, plan
checks in :mod:`.admission`, status snapshots in :mod:`.status`, listings and frame
files in :mod:`.listing`, the device view in :mod:`.rigstate`, the emergency stop's device
side and the safety check in :mod:`.estop`, engine requests in :mod:`.engine_requests`, the
durable hold in :mod:`.hold`, the data-root lock in :mod:`.rootlock`. Locks, always taken in
this order: the submission lock → the hold's file lock → ``_lock`` (= ``_cond``, :attr:`lock`) →
``guard.hw``.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from pathlib import Path
from typing import IO, Any

from m2s2hil.analysis.qc import capture_qc_hook
from m2s2hil.engine.build import build_run
from m2s2hil.engine.fault_policy import FaultPolicy
from m2s2hil.engine.options import EngineOptions
from m2s2hil.engine.state import EngineEvent, RunState, SessionFinished
from m2s2hil.rig.opened import Rig

from . import listing
from .activity import ActivityLog
from .busy import BusyActions
from .engine_requests import Action, request, wait_safe_boundary
from .errors import Conflict, HoldNotSaved
from .export_jobs import ExportJobs
from .hold import QueueHold
from .jobqueue import Job, JobQueue
from .prometheus import Metrics
from .reads import SessionReads
from .rig_guard import RigGuard
from .rootlock import lock_data_root, unlock_data_root
from .submission import Submissions

log = logging.getLogger(__name__)
S = RunState


class SessionManager:
    def __init__(
        self,
        rig: Rig,
        root: str | Path,
        *,
        queue_limit: int = 16,
        max_plan_frames: int = 20_000,
        policy: FaultPolicy | None = None,
        engine_options: EngineOptions | None = None,
        metrics: Metrics | None = None,
        keep_finished: int = 32,
        estop_grace_s: float = 0.5,
        estop_timeout_s: float = 30.0,
        root_lock: IO[str] | None = None,
        home_deferred: bool = False,
    ) -> None:
        self.rig = rig
        self.root = Path(root)
        self.queue_limit = queue_limit
        self.max_plan_frames = max_plan_frames
        self.policy = policy
        self.engine_options = engine_options
        self.metrics = metrics or Metrics()
        self.keep_finished = keep_finished
        self.started_at = time.time()

        self._lock = threading.RLock()
        self._cond = threading.Condition(self._lock)
        self._queue = JobQueue()  # changed under _lock
        self._current: Job | None = None
        self._hold = QueueHold(self.root, self._cond)  # in memory and on the data root
        self._closing = False
        self._thread: threading.Thread | None = None
        self._lockfile: IO[str] | None = root_lock  # from lock_data_root(), or taken by start()
        self._shutdown_reason: str | None = None
        self._closed: dict | None = None
        #: The rig opened under a hold, its axes with switches not homed: done before the first session.
        self._home_deferred = home_deferred
        #: What happened, who did it and from where: faults, retries, state changes, operator actions.
        self.activity = ActivityLog()
        #: Long operator actions running now (a snapshot, darks, an export…): each once at a time.
        self.busy = BusyActions()
        #: Exports run as jobs, followed by polling (``POST /sessions/{id}/export/jobs``).
        self.exports = ExportJobs(self)
        #: The rig's door for request threads and the emergency stop.
        self.guard = RigGuard(self, estop_grace_s=estop_grace_s, estop_timeout_s=estop_timeout_s)
        #: Status, listings, frames and journals for the clients.
        self.reads = SessionReads(self)
        #: New sessions and sessions from disk into the queue, checked first.
        self.submissions = Submissions(self, self._queue, self._cond, self._hold)

        self.metrics.gauge("m2s2hil_queue_depth", "Items waiting: sessions for the rig, frames in the "
                           "running session's processing pipeline.", self._queue_gauges)
        self.metrics.gauge("m2s2hil_sessions_running", "Sessions owning the rig (0 or 1).",
                           lambda: {(): 1.0 if self.running_id() else 0.0})
        self.metrics.gauge("m2s2hil_queue_held", "1 while the queue is held (emergency stop, failure).",
                           lambda: {(): 1.0 if self._hold.reason else 0.0})

    # ================================================================== lifecycle
    def start(self, *, resume_interrupted: bool = False) -> list[str]:
        """Lock the data root, optionally queue the sessions the journals show as interrupted
        (those that were running first, then those that were waiting, oldest first), and start
        dispatching. Returns the ids queued for resumption."""
        self.root.mkdir(parents=True, exist_ok=True)
        if self._lockfile is None:
            self._lockfile = lock_data_root(self.root)
        self._hold.restore()  # before anything is queued or dispatched
        resumed: list[str] = []
        if resume_interrupted:
            ended = listing.end_killed_renders(self.root)  # a render is never resumed: its end
            if ended:
                log.info("ended %d render(s) a killed process left: %s", len(ended), ", ".join(ended))
            for sid in listing.interrupted_sessions(self.root):
                try:
                    self.submissions.requeue(sid, reason="daemon start", check_limit=False)
                    resumed.append(sid)
                except Exception as exc:  # one unusable session must not keep the daemon down
                    log.error("cannot resume session %s: %s", sid, exc)
            if resumed:
                log.info("resuming %d interrupted session(s): %s", len(resumed), ", ".join(resumed))
        self._thread = threading.Thread(target=self._dispatch, name="session-dispatcher", daemon=True)
        self._thread.start()
        return resumed

    def request_shutdown(self, reason: str = "shutdown") -> None:
        """Non-blocking first step of a shutdown (e.g. from a signal handler): stop starting
        sessions and ask the running one to pause at its next safe boundary."""
        with self._cond:
            if self._closing:
                return
            self._closing = True
            self._shutdown_reason = reason
            job = self._current
            self._cond.notify_all()
        log.info("%s: no new sessions start; pausing the running one at a safe boundary", reason)
        if job is not None and job.engine is not None and job.engine.state in (S.IDLE, S.RUNNING):
            job.shutdown_paused = True
            request(job.engine, "pause")

    def close(self, *, reason: str = "shutdown", timeout: float = 120.0, abort: bool = False) -> dict:
        """Stop: pause (or with ``abort`` abort) the running session at a safe boundary, mark it
        ``interrupted`` in its journal, leave the rig safe and verify it. Queued sessions keep
        their ``queued`` state on disk (a restart with resumption picks them up). Idempotent."""
        with self._lock:
            if self._closed is not None:
                return self._closed
            self._closed = {}
        if abort:
            with self._cond:
                self._closing = True
                job = self._current
                self._cond.notify_all()
            if job is not None and job.engine is not None:
                request(job.engine, "abort")
        else:
            self.request_shutdown(reason)
            reason = self._shutdown_reason or reason
            job = self._current
        report: dict[str, Any] = {"session_id": None, "session_state": None}
        if job is not None and job.engine is not None:
            eng = job.engine
            st = wait_safe_boundary(eng, timeout)
            if not (st.terminal or st is RunState.PAUSED):
                log.error("session %s did not reach a safe boundary within %.0f s: aborting it",
                          job.session_id, timeout)
                request(eng, "abort")
                eng.wait(timeout=30)
                st = eng.state
            report.update(session_id=job.session_id, session_state=st.value)
        if self._thread is not None:
            self._thread.join(timeout=5)
        check, errors = self.guard.park()
        report.update(rig_safe=check.safe, lamps_on=check.lamps_on, moving=check.moving, errors=errors)
        if job is not None and job.engine is not None and report["session_state"] == "paused":
            report["session_state"] = job.record_interruption(reason, check)
        if check.safe:
            log.info("rig left safe: lamps off, motion stopped")
        else:
            log.error("rig NOT confirmed safe: lamps on %s, moving %s, errors %s", check.lamps_on,
                      check.moving, errors)
        for j in list(self._queue.jobs.values()):  # their owner locks go with the daemon
            with contextlib.suppress(Exception):
                j.store.close()
        if self._lockfile is not None:
            unlock_data_root(self._lockfile)
            self._lockfile = None
        self._closed = report
        return report

    # ================================================================== dispatching
    def _dispatch(self) -> None:
        while True:
            with self._cond:
                while True:
                    if self._closing:
                        return
                    cur = self._current
                    eng = cur.engine if cur is not None and not cur.finished.is_set() else None
                    if cur is not None and eng is not None and not eng.alive and eng.state.terminal:
                        self._finish(cur, eng.state.value)  # finished without its event
                        continue
                    if self._current is None and self._queue and not self._hold.reason:
                        job = self._queue.pop_next()
                        self._current = job
                        break
                    self._cond.wait(timeout=1.0)
            try:
                self._launch(job)
            except Exception as exc:
                log.exception("session %s could not start", job.session_id)
                with contextlib.suppress(Exception):
                    job.store.record_event("start_failed", {"error": f"{type(exc).__name__}: {exc}"})
                    job.store.set_state("failed")
                self.activity.record("session", f"session {job.session_id} could not start: "
                                     f"{type(exc).__name__}: {exc}", level="error", session_id=job.session_id,
                                     state="failed")
                with self._cond:
                    job.error = f"{type(exc).__name__}: {exc}"
                    self._finish(job, "failed")

    def _launch(self, job: Job) -> None:
        if self._home_deferred:  # released since the daemon started held: now the axes may move
            self.guard.home_switched_axes()
            self._home_deferred = False
        runs = sum(1 for e in job.store.events() if e.get("kind") == "run_started")
        # The same builder as `capture`: processing, capture-time QC, the fault policy, the rig check.
        engine = build_run(self.rig, store=job.store, options=self.engine_options, policy=self.policy,
                           qc=capture_qc_hook())  # a fresh hook per run: it keeps the run's scores
        engine.subscribe(self.metrics.observe)
        engine.subscribe(lambda ev, sid=job.session_id: self.activity.observe(sid, ev))
        engine.subscribe(lambda ev, job=job: self._on_event(job, ev))
        with self._cond:
            if self._hold.reason or self._closing:  # an emergency stop or a shutdown came in meanwhile
                self._queue.put_back(job)
                self._current = None
                self._cond.notify_all()
                return
            job.engine = engine
            job.run = runs + 1
            job.state = "running"
            self.guard.start_engine(engine)
        log.info("session %s started (run %d, %d planned events)", job.session_id, job.run, job.planned)
        self.activity.record("session", f"session {job.session_id} started (run {job.run}, {job.planned} "
                             "planned events)", session_id=job.session_id, state="running", run=job.run)

    def _on_event(self, job: Job, ev: EngineEvent) -> None:
        if not isinstance(ev, SessionFinished):
            return
        if ev.state is RunState.FAILED:  # held (and on disk) before anyone sees it finished
            with self._cond:
                held = not self._hold.reason
                if held:
                    self._hold.set_now(f"session {job.session_id} failed: {ev.error}")
            if held:
                log.error("queue held: %s", self._hold.reason)
                self.activity.record("queue", f"queue held: {self._hold.reason}", level="error",
                                     session_id=job.session_id)
                try:
                    self.save_hold()
                except HoldNotSaved as exc:
                    log.error("%s", exc)
        with self._cond:
            self._finish(job, ev.state.value)

    def _finish(self, job: Job, state: str) -> None:
        """Caller holds the lock."""
        if not job.mark_finished(state):
            return
        with contextlib.suppress(Exception):
            job.store.release_ownership()  # readable still; a resume (here or elsewhere) may own it
        if self._current is job:
            self._current = None
        self._queue.retire(job, self.keep_finished)
        self._cond.notify_all()

    # ================================================================== control
    def control(self, session_id: str, action: Action) -> dict:
        """pause / resume / abort a session; see the module docstring for what conflicts get."""
        with self._lock:
            job = self._queue.get(session_id)
            if job is not None and job.state == "queued":
                if action == "abort":
                    self._cancel(job)
                    return self.reads.status(session_id)
                pos = self._queue.position(job)
                raise Conflict(
                    f"session {session_id} is queued (position {pos}), not running: it cannot be "
                    f"{action}d; abort cancels it"
                )
        if job is not None and job.engine is not None and not job.finished.is_set():
            request(job.engine, action, raise_errors=True)
            return self.reads.status(session_id)
        if job is not None and not (action == "resume" and job.finished.is_set()):
            state = self.reads.status(session_id)["state"]
            raise Conflict(f"session {session_id} is {state}: there is nothing to {action}")
        return self.submissions.control_stored(session_id, action)

    def confirm_lens(self, session_id: str, capped: bool) -> dict:
        """The operator's lens cap on (``capped``) or off, for a running session parked for it
        (a real rig's darks, :mod:`m2s2hil.engine.darks`); Conflict / IllegalTransition (409)
        when it does not wait for exactly that."""
        job = self._queue.get(session_id)
        if job is None or job.engine is None or job.finished.is_set():
            state = self.reads.status(session_id)["state"]  # UnknownSession (404) when there is none
            raise Conflict(f"session {session_id} is {state}, not running here: it waits for no lens cap")
        job.engine.confirm_lens(capped)
        return self.reads.status(session_id)

    def _cancel(self, job: Job) -> None:
        """Caller holds the lock."""
        self._queue.remove(job)
        try:
            job.store.record_event("cancelled", {"by": "operator"})
            job.store.set_state("cancelled")
        except Exception as exc:
            log.error("could not record the cancellation of %s: %s", job.session_id, exc)
        self._finish(job, "cancelled")
        log.info("session %s cancelled while queued", job.session_id)
        self.activity.record("session", f"session {job.session_id} cancelled while queued",
                             session_id=job.session_id, state="cancelled")

    def hold(self, reason: str) -> None:
        """Hold the queue: the running session goes on, no queued one starts (e.g. while an
        operator swaps the mockup) until :meth:`release`. Returns once the hold is on disk;
        :class:`HoldNotSaved` when it could not be written (it holds in this process anyway)."""
        with self._cond:
            self._hold.set_now(reason)
        log.info("queue held: %s", reason)
        self.activity.record("queue", f"queue held: {reason}", level="warning")
        self.save_hold()

    def release(self) -> str | None:
        """Release a held queue; returns the reason it was held. When the hold file cannot be
        removed (:class:`HoldNotSaved`) the queue stays held."""
        was = self._hold.release()
        if was:
            log.info("queue released (was held: %s)", was)
            self.activity.record("queue", f"queue released (was held: {was})")
        return was

    def hold_at_once(self, reason: str) -> Job | None:
        """Hold in memory now (the emergency stop's first step), then :meth:`save_hold`;
        returns the session that owns the rig at that moment."""
        with self._cond:
            self._hold.set_now(reason)
            return self._current

    def save_hold(self) -> None:
        """Write the hold as it is now to the data root; :class:`HoldNotSaved`."""
        self._hold.save()

    # ================================================================== queries
    def running_id(self) -> str | None:
        cur = self._current
        return cur.session_id if cur is not None and cur.engine is not None else None

    @property
    def held(self) -> str | None:
        return self._hold.reason

    def queue(self) -> dict:
        with self._lock:
            running, held, items = self.running_id(), self._hold.reason, self._queue.items()
            cur = self._current
            starting = cur.session_id if cur is not None and running is None else None
            # between the queue and the engine's start a session is neither queued nor running:
            # "starting", never "idle" (the console said "rig idle" there)
            rig = ("running" if running else "starting" if starting else "held" if held
                   else "queued" if items else "idle")
            return {"running": running, "held": held, "limit": self.queue_limit, "items": items,
                    "rig": rig, "starting": starting}

    def _queue_gauges(self) -> dict[tuple[tuple[str, str], ...], float]:
        cur = self._current
        pipe = 0.0
        if cur is not None and cur.engine is not None and not cur.finished.is_set():
            with contextlib.suppress(Exception):
                pipe = float(cur.engine.pipeline_stats().in_flight)
        return {(("queue", "sessions"),): float(len(self._queue)), (("queue", "pipeline"),): pipe}

    def job(self, session_id: str) -> Job | None:
        return self._queue.get(session_id)

    def position(self, job: Job) -> int | None:
        """1 for the next to start; None when the job does not wait."""
        with self._lock:
            return self._queue.position(job)

    def known_jobs(self) -> dict[str, Job]:
        """The jobs this daemon knows, by id (queued, running, or among the last finished)."""
        return self._queue.jobs

    def owner(self) -> Job | None:
        """The session that owns the rig (starting, running or paused), if any."""
        return self._current

    @property
    def lock(self) -> threading.RLock:
        """The queue's lock; the rig guard takes it before its device lock."""
        return self._lock

    def check_rig_free(self, what: str) -> None:
        """:class:`Conflict` unless the rig is free for ``what``; caller holds :attr:`lock`."""
        cur = self._current
        if cur is not None:
            raise Conflict(f"{what} is refused while session {cur.session_id} owns the rig "
                           f"({cur.state}); pause does not release it: abort the session or wait "
                           "for it to end")
        if self._closing:
            raise Conflict("the daemon is shutting down")

    @property
    def closing(self) -> bool:
        """True once a shutdown began: no new session is accepted or started."""
        return self._closing
