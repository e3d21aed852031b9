"""One rig, one running session, a first-in-first-out queue of the others.

:class:`SessionManager` owns the opened :class:`~m2s2hil.rig.opened.Rig` and the data root.
``submit(sweep)`` checks the plan against the rig, creates the session folder (state
``queued``) and queues it; a dispatcher thread starts the next session when the rig is
free, one :class:`~m2s2hil.engine.runner.Engine` at a time, built by
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

Hardware access from request threads: while an engine owns the rig, device state comes
from the engine's own read-back, never from a second conversation on the same serial
line; the emergency stop is the one exception (see :meth:`emergency_stop`).

The manager coordinates; the parts live beside it: the queue entries in :mod:`.queue`,
plan checks in :mod:`.admission`, status snapshots in :mod:`.status`, listings and frame
files in :mod:`.listing`, the device view in :mod:`.rigstate`, the emergency stop and the
safety check in :mod:`.estop`, engine requests in :mod:`.engine_requests`, the data-root
lock in :mod:`.rootlock`. Locks, always taken in this order: ``_submit_lock`` →
``_hold_lock`` → ``_lock`` (= ``_cond``) → ``_hw``.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any, Literal

from m2s2hil.analysis.qc import capture_qc_hook
from m2s2hil.daemon.hold import HoldFile, HoldNotSaved
from m2s2hil.engine.build import RigChanged, build_run, check_rig_digest
from m2s2hil.engine.fault_policy import FaultPolicy
from m2s2hil.engine.options import EngineOptions
from m2s2hil.engine.state import EngineEvent, RunState, SessionFinished
from m2s2hil.plan import Sweep
from m2s2hil.rig.opened import Rig
from m2s2hil.store.catalogue import list_sessions
from m2s2hil.store.session import SessionStore

from . import estop, listing
from .admission import check_room, check_sweep
from .engine_requests import Action, request, wait_safe_boundary
from .errors import Conflict, QueueFull, UnknownSession
from .estop import SafeCheck, make_safe
from .jobqueue import Job, JobQueue
from .prometheus import Metrics
from .rigstate import device_states
from .rootlock import lock_data_root, unlock_data_root
from .status import RESUMABLE_BY_HAND, TERMINAL, disk_status, engine_status, queued_status

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
    ) -> None:
        self.rig = rig
        self.root = Path(root)
        self.queue_limit = queue_limit
        self.max_plan_frames = max_plan_frames
        self.policy = policy
        self.engine_options = engine_options
        self.metrics = metrics or Metrics()
        self.keep_finished = keep_finished
        self.estop_grace_s = estop_grace_s
        self.estop_timeout_s = estop_timeout_s
        self.started_at = time.time()

        self._lock = threading.RLock()
        self._cond = threading.Condition(self._lock)
        self._submit_lock = threading.Lock()  # serialises check-then-create of new sessions
        self._hw = threading.Lock()  # request threads' own device conversations
        self._queue = JobQueue()  # changed under _lock
        self._current: Job | None = None
        self._held: str | None = None  # why the queue is held (None: not held)
        self._held_since: float | None = None
        self._hold_gen = 0  # counts holds set, so a release cannot clear one it did not see
        self._hold_file = HoldFile(self.root)
        self._hold_lock = threading.Lock()  # one writer of the hold file at a time
        self._closing = False
        self._thread: threading.Thread | None = None
        self._planned = listing.PlannedCounts()
        self._lockfile: IO[str] | None = root_lock  # from lock_data_root(), or taken by start()
        self._shutdown_reason: str | None = None
        self._closed: dict | None = None
        #: Called with the rig, holding the device lock, just before a session's engine starts.
        self.before_session: list[Callable[[Rig], None]] = []

        self.metrics.gauge("m2s2hil_queue_depth", "Items waiting: sessions for the rig, frames in the "
                           "running session's processing pipeline.", self._queue_gauges)
        self.metrics.gauge("m2s2hil_sessions_running", "Sessions owning the rig (0 or 1).",
                           lambda: {(): 1.0 if self.running_id() else 0.0})
        self.metrics.gauge("m2s2hil_queue_held", "1 while the queue is held (emergency stop, failure).",
                           lambda: {(): 1.0 if self._held else 0.0})

    @property
    def _jobs(self) -> dict[str, Job]:
        """The jobs this daemon knows, by id (tests clear it to make reads go to disk)."""
        return self._queue.jobs

    # ================================================================== lifecycle
    def start(self, *, resume_interrupted: bool = False) -> list[str]:
        """Lock the data root, optionally queue the sessions the journals show as interrupted
        (those that were running first, then those that were waiting, oldest first), and start
        dispatching. Returns the ids queued for resumption."""
        self.root.mkdir(parents=True, exist_ok=True)
        if self._lockfile is None:
            self._lockfile = lock_data_root(self.root)
        self._restore_hold()  # before anything is queued or dispatched
        resumed: list[str] = []
        if resume_interrupted:
            infos = list(reversed(list_sessions(self.root)))  # oldest first
            first = [i for i in infos if i.state in ("running", "pausing", "interrupted")]
            then = [i for i in infos if i.state in ("created", "queued")]
            for info in first + then:
                try:
                    self._enqueue_existing(info.session_id, reason="daemon start", check_limit=False)
                    resumed.append(info.session_id)
                except Exception as exc:  # one unusable session must not keep the daemon down
                    log.error("cannot resume session %s: %s", info.session_id, exc)
            if resumed:
                log.info("resuming %d interrupted session(s): %s", len(resumed), ", ".join(resumed))
        self._thread = threading.Thread(target=self._dispatch, name="session-dispatcher", daemon=True)
        self._thread.start()
        return resumed

    def _restore_hold(self) -> None:
        """Take over the hold a previous daemon left on the data root, and say so."""
        saved = self._hold_file.load()
        if saved is None:
            return
        with self._cond:
            self._held, self._held_since = saved.reason, saved.since
            self._hold_gen += 1
        if saved.damaged:
            log.error("rig HELD (fail safe): the hold file %s is damaged (%s); no session starts until "
                      "an operator releases it (POST /queue/release)", self._hold_file.path, saved.damaged)
        else:
            log.warning("rig HELD since %s: %s; no session starts until an operator releases it "
                        "(POST /queue/release)", saved.since_iso, saved.reason)

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
        with self._hw:
            errors = make_safe(self.rig)
        check = self.check_safe()
        errors += check.errors
        report.update(rig_safe=check.safe, lamps_on=check.lamps_on, moving=check.moving, errors=errors)
        if job is not None and job.engine is not None and report["session_state"] == "paused":
            self._record_interruption(job, reason, check, report)
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

    def _record_interruption(self, job: Job, reason: str, check: SafeCheck, report: dict[str, Any]) -> None:
        """Journal a session parked by a shutdown; it becomes ``interrupted`` (resumable) unless
        an operator had paused it before."""
        try:
            job.store.record_event("interrupted", {"reason": reason, "rig_safe": check.safe,
                                                   "lamps_on": check.lamps_on, "moving": check.moving})
            if job.shutdown_paused:  # an operator's earlier pause stays a pause
                job.store.set_state("interrupted")
                report["session_state"] = "interrupted"
        except Exception as exc:
            log.error("could not record the interruption of %s: %s", job.session_id, exc)
        log.info("session %s parked at a safe boundary and saved (%s)", job.session_id,
                 report["session_state"])

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
                    if self._current is None and self._queue and not self._held:
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
                with self._cond:
                    job.error = f"{type(exc).__name__}: {exc}"
                    self._finish(job, "failed")

    def _launch(self, job: Job) -> None:
        runs = sum(1 for e in job.store.events() if e.get("kind") == "run_started")
        # The same builder as `capture`: processing, capture-time QC, the fault policy, the rig check.
        engine = build_run(self.rig, store=job.store, options=self.engine_options, policy=self.policy,
                           qc=capture_qc_hook())  # a fresh hook per run: it keeps the run's scores
        engine.subscribe(self.metrics.observe)
        engine.subscribe(lambda ev, job=job: self._on_event(job, ev))
        with self._cond:
            if self._held or self._closing:  # an emergency stop or a shutdown came in meanwhile
                self._queue.put_back(job)
                self._current = None
                self._cond.notify_all()
                return
            job.engine = engine
            job.run = runs + 1
            job.state = "running"
            with self._hw:
                for hook in self.before_session:  # e.g. the console's live view stops streaming
                    try:
                        hook(self.rig)
                    except Exception as exc:
                        log.warning("before-session hook failed: %s", exc)
                engine.start()
        log.info("session %s started (run %d, %d planned events)", job.session_id, job.run, job.planned)

    def _on_event(self, job: Job, ev: EngineEvent) -> None:
        if isinstance(ev, SessionFinished):
            with self._cond:
                self._finish(job, ev.state.value)
                held = ev.state is RunState.FAILED and not self._held
                if held:  # in the same locked step as _finish: nothing may start in between
                    self._hold_now(f"session {job.session_id} failed: {ev.error}")
                    log.error("queue held: %s", self._held)
            if held:
                try:
                    self._save_hold()
                except HoldNotSaved as exc:
                    log.error("%s", exc)

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

    # ================================================================== submission
    def submit(self, sweep: Sweep) -> Job:
        """Check the plan against the rig and the disk, create the session and queue it."""
        cfg = self.rig.config
        planned, need = check_sweep(sweep, cfg, self.max_plan_frames, root=self.root)
        with self._submit_lock:
            self._check_accepting()
            with self._lock:
                if self._would_wait() and self._queue.full(self.queue_limit):
                    raise QueueFull(
                        f"{len(self._queue)} session(s) already wait for the rig (limit {self.queue_limit}); "
                        "cancel one (POST /sessions/{id}/abort) or retry when the running one ends"
                    )
            check_room(self.root, need)
            store = SessionStore.create(self.root, sweep, cfg, clock=self.rig.clock)
            store.set_state("queued")
            store.record_event("queued", {"via": "api", "planned_events": planned})
            job = Job(store.session_id, store, resume=False, queued_at=time.time(), planned=planned)
            with self._cond:
                self._queue.add(job)
                self._planned.set(job.session_id, planned)
                self._cond.notify_all()
        log.info("session %s queued (%d events)", job.session_id, job.planned)
        return job

    def _would_wait(self) -> bool:
        return self._current is not None or bool(self._queue) or self._held is not None

    def _check_accepting(self) -> None:
        if self._closing:
            raise Conflict("the daemon is shutting down; no new sessions are accepted")

    def _enqueue_existing(self, session_id: str, *, reason: str, check_limit: bool = True) -> Job:
        """Queue a session from disk again (resumption): it will capture what it lacks."""
        with self._submit_lock:
            self._check_accepting()
            with self._lock:
                live = self._queue.get(session_id)
                if live is not None and not live.finished.is_set():
                    raise Conflict(f"session {session_id} is already {live.state} in this daemon")
                if check_limit and self._would_wait() and self._queue.full(self.queue_limit):
                    raise QueueFull(f"{len(self._queue)} session(s) already wait for the rig "
                                    f"(limit {self.queue_limit})")
            store = self._open(session_id)
            try:
                try:
                    check_rig_digest(store, self.rig.config)
                except RigChanged as exc:
                    raise Conflict(str(exc)) from None
                planned = self._planned.of(store)
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

    # ================================================================== control
    def control(self, session_id: str, action: Action) -> dict:
        """pause / resume / abort a session; see the module docstring for what conflicts get."""
        with self._lock:
            job = self._queue.get(session_id)
            if job is not None and job.state == "queued":
                if action == "abort":
                    self._cancel(job)
                    return self.status(session_id)
                pos = self._queue.position(job)
                raise Conflict(
                    f"session {session_id} is queued (position {pos}), not running: it cannot be "
                    f"{action}d; abort cancels it"
                )
        if job is not None and job.engine is not None and not job.finished.is_set():
            request(job.engine, action, raise_errors=True)
            return self.status(session_id)
        if job is not None and not (action == "resume" and job.finished.is_set()):
            state = self.status(session_id)["state"]
            raise Conflict(f"session {session_id} is {state}: there is nothing to {action}")
        info = self._disk_status(session_id)
        state = info["state"]
        if action == "resume" and state == "estopped" and self._held == "emergency stop":
            raise Conflict(f"session {session_id} was stopped by the emergency stop, which is not cleared: "
                           "make the rig safe, clear it with POST /queue/release, then resume")
        if action == "resume" and state in RESUMABLE_BY_HAND:
            self._enqueue_existing(session_id, reason="resumed by the operator")
            return self.status(session_id)
        if action == "abort" and state in RESUMABLE_BY_HAND:
            store = self._open(session_id)
            try:
                store.record_event("aborted", {"by": "operator", "was": state})
                store.set_state("aborted")
            finally:
                store.close()
            return self.status(session_id)
        if state in TERMINAL:
            raise Conflict(f"session {session_id} is {state}: there is nothing to {action}")
        raise Conflict(f"session {session_id} is {state} and not running in this daemon: it cannot be "
                       f"{action}d" + ("; resume queues it again" if state in RESUMABLE_BY_HAND else ""))

    def confirm_lens(self, session_id: str, capped: bool) -> dict:
        """The operator's lens cap on (``capped``) or off, for a running session parked for it
        (a real rig's darks, :mod:`m2s2hil.engine.darks`); Conflict / IllegalTransition (409)
        when it does not wait for exactly that."""
        job = self._queue.get(session_id)
        if job is None or job.engine is None or job.finished.is_set():
            state = self.status(session_id)["state"]  # UnknownSession (404) when there is none
            raise Conflict(f"session {session_id} is {state}, not running here: it waits for no lens cap")
        job.engine.confirm_lens(capped)
        return self.status(session_id)

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

    def hold(self, reason: str) -> None:
        """Hold the queue: the running session goes on, no queued one starts (e.g. while an
        operator swaps the mockup) until :meth:`release`. Returns once the hold is on disk;
        :class:`HoldNotSaved` when it could not be written (it holds in this process anyway)."""
        with self._cond:
            self._hold_now(reason)
        log.info("queue held: %s", reason)
        self._save_hold()

    def release(self) -> str | None:
        """Release a held queue; returns the reason it was held. The hold file goes first:
        when it cannot be removed (:class:`HoldNotSaved`) the queue stays held."""
        with self._hold_lock:
            with self._lock:
                gen, was = self._hold_gen, self._held
            self._hold_file.clear()
            with self._cond:
                if self._hold_gen == gen:  # no new hold (an emergency stop) came in meanwhile
                    self._held = self._held_since = None
                    self._cond.notify_all()
        if was:
            log.info("queue released (was held: %s)", was)
        return was

    def _hold_now(self, reason: str) -> None:
        """Hold in memory at once (nothing is dispatched from here on); caller holds ``_cond``
        and then calls :meth:`_save_hold`."""
        self._held, self._held_since = reason, time.time()
        self._hold_gen += 1
        self._cond.notify_all()

    def _save_hold(self) -> None:
        """Make the hold file say what memory says. Serialised, and it reads memory once it
        has the file: whatever order holds and releases come in, the last writer is right."""
        with self._hold_lock:
            with self._lock:
                reason, since = self._held, self._held_since
            if reason is None:
                self._hold_file.clear()
            else:
                self._hold_file.save(reason, since)

    # ================================================================== emergency stop
    def emergency_stop(self) -> dict:
        """Lamps off and motion stopped now, whatever runs.

        Order: hold the queue; switch every lamp off (the relay driver serialises its own
        I/O, so this is safe beside the engine thread); write the hold to the data root (it
        outlives this daemon; an error doing so is reported, the stop goes on); ask the running
        session to abort;
        give it ``estop_grace_s`` to reach its own teardown (which stops motion too), then
        stop the axes from this thread anyway (a move is not waited out); once the engine
        has ended, make safe again and read the devices back to confirm (see
        :func:`.estop.stop_rig`)."""
        t0 = time.monotonic()
        self.metrics.count_estop()
        with self._cond:
            self._hold_now("emergency stop")
            job = self._current
        log.warning("EMERGENCY STOP requested%s", f" (session {job.session_id} running)" if job else "")
        errors = estop.lamps_off(self.rig)
        try:
            self._save_hold()
        except HoldNotSaved as exc:
            log.error("%s", exc)
            errors.append(str(exc))
        check, stop_errors = estop.stop_rig(self.rig, self._hw, job, grace_s=self.estop_grace_s,
                                            timeout_s=self.estop_timeout_s)
        errors += stop_errors
        eng = job.engine if job is not None else None
        if job is not None and eng is not None and eng.state is RunState.ABORTED:
            job.finished.wait(5.0)  # its run has given the session's owner lock back
            if self._mark_estopped(job.session_id, check):
                job.final_state = "estopped"  # what its status says from now on, as the journal does
        return {
            "safe": check.safe, "lamps_on": check.lamps_on, "moving": check.moving,
            "session_id": job.session_id if job else None,
            "session_state": eng.state.value if eng is not None else None,
            "held": self._held or "emergency stop", "errors": errors,
            "elapsed_s": time.monotonic() - t0,
        }

    def _mark_estopped(self, session_id: str, check: SafeCheck) -> bool:
        """``estopped``, not ``aborted``: the operator did not give the capture up, so it may be
        resumed once the stop is cleared (POST /queue/release), never before. False when the
        journal could not be written (the session then stays ``aborted``)."""
        try:
            store = self._open(session_id)
            try:
                store.record_event("estopped", {"rig_safe": check.safe, "lamps_on": check.lamps_on})
                store.set_state("estopped")
            finally:
                store.close()
        except Exception as exc:
            log.error("could not mark session %s as e-stopped: %s", session_id, exc)
            return False
        return True

    def check_safe(self) -> SafeCheck:
        """Read the devices back: which lamps are on, which axis moves."""
        return estop.check_safe(self.rig)

    @contextlib.contextmanager
    def manual_access(self, what: str = "manual control") -> Iterator[Rig]:
        """The rig for one short conversation from a request thread (jog, lamps, a live-view
        frame, a calibration capture); :class:`Conflict` while a session owns it (running,
        paused or starting). Holding ``_hw`` keeps the dispatcher from starting a session
        meanwhile; the emergency stop still switches the lamps off without it."""
        with self._lock:
            cur = self._current
            if cur is not None:
                raise Conflict(f"{what} is refused while session {cur.session_id} owns the rig "
                               f"({cur.state}); pause does not release it: abort the session or wait "
                               "for it to end")
            if self._closing:
                raise Conflict("the daemon is shutting down")
            self._hw.acquire()
        try:
            yield self.rig
        finally:
            self._hw.release()

    # ================================================================== queries
    def running_id(self) -> str | None:
        cur = self._current
        return cur.session_id if cur is not None and cur.engine is not None else None

    @property
    def held(self) -> str | None:
        return self._held

    def queue(self) -> dict:
        with self._lock:
            return {"running": self.running_id(), "held": self._held, "limit": self.queue_limit,
                    "items": self._queue.items()}

    def _queue_gauges(self) -> dict[tuple[tuple[str, str], ...], float]:
        cur = self._current
        pipe = 0.0
        if cur is not None and cur.engine is not None and not cur.finished.is_set():
            with contextlib.suppress(Exception):
                pipe = float(cur.engine.pipeline_stats().in_flight)
        return {(("queue", "sessions"),): float(len(self._queue)), (("queue", "pipeline"),): pipe}

    def job(self, session_id: str) -> Job | None:
        return self._queue.get(session_id)

    def status(self, session_id: str) -> dict:
        """A status snapshot (the body of ``GET /sessions/{id}``)."""
        job = self._queue.get(session_id)
        if job is None:
            return self._disk_status(session_id)
        if job.engine is not None:
            return engine_status(job, job.engine)
        # queued or cancelled before running
        with self._lock:
            pos = self._queue.position(job)
        return queued_status(job, pos)

    def _open(self, session_id: str) -> SessionStore:
        """Open for writing (owner lock held): the daemon requeues, aborts and resumes it."""
        return listing.open_store(self.root, session_id, self.rig.clock, mode="write")

    def _disk_status(self, session_id: str) -> dict:
        return disk_status(self.root, session_id, self.rig.clock, self._planned)

    def sessions(self, *, state: str | None = None, satellite: str | None = None, build: str | None = None,
             offset: int = 0, limit: int = 50) -> tuple[list[dict], int]:
        """Sessions under the data root, newest first, with this daemon's live view on top."""
        rows = listing.session_rows(self.root, self._queue.jobs, state=state, satellite=satellite,
                                    build=build)
        page = []
        for r in rows[offset:offset + limit]:
            try:
                page.append(self.status(r["session_id"]))
            except UnknownSession:  # removed meanwhile
                continue
        return page, len(rows)

    # ------------------------------------------------------------------ frames
    @contextlib.contextmanager
    def reading(self, session_id: str) -> Iterator[SessionStore]:
        """The session's store for reading: the live one, or one opened for this request."""
        job = self._queue.get(session_id)
        if job is not None:
            yield job.store
            return
        with listing.stored(self.root, session_id, self.rig.clock) as store:
            yield store

    def frames(self, session_id: str, *, offset: int = 0, limit: int = 50) -> tuple[list[Any], int]:
        with self.reading(session_id) as store:
            return listing.frame_page(store, offset=offset, limit=limit)

    def frame_file(self, session_id: str, n: int, role: Literal["raw", "preview"]) -> tuple[bytes, str]:
        with self.reading(session_id) as store:
            return listing.frame_bytes(store, session_id, n, role)

    # ------------------------------------------------------------------ events
    def journal_events(self, session_id: str) -> tuple[str, list[dict]]:
        """(state, events) replayed from the journal for a session no engine here knows."""
        with self.reading(session_id) as store:
            return listing.journal_events(store)

    # ------------------------------------------------------------------ rig
    def rig_state(self) -> dict:
        """Each device's state and health (see :mod:`.rigstate`): the engine's read-back while
        a session owns the rig."""
        cfg = self.rig.config
        cur = self._current
        eng = cur.engine if cur is not None and cur.engine is not None and not cur.finished.is_set() else None
        devices = device_states(self.rig, self._hw, eng)
        return {"name": cfg.rig.name, "simulated": bool(self.rig.simulated), "digest": cfg.digest,
                "session_id": cur.session_id if eng is not None else None, "held": self._held,
                "devices": devices}
