"""One rig, one running session, a first-in-first-out queue of the others.

:class:`SessionManager` owns the opened :class:`~m2s2hil.rig.Rig` and the data root.
``submit(sweep)`` checks the plan against the rig, creates the session folder (state
``queued``) and queues it; a dispatcher thread starts the next session when the rig is
free, one :class:`~m2s2hil.engine.Engine` at a time. The queue is visible
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
until :meth:`release` (an operator should look at the rig first).

Hardware access from request threads: while an engine owns the rig, device state comes
from the engine's own read-back, never from a second conversation on the same serial
line; the emergency stop is the one exception (see :meth:`emergency_stop`).
"""

from __future__ import annotations

import collections
import contextlib
import fcntl
import json
import logging
import math
import os
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Literal

from m2s2hil.atomic import DiskFull, check_free_space
from m2s2hil.engine import Engine
from m2s2hil.engine_state import EngineEvent, IllegalTransition, RunState, SessionFinished
from m2s2hil.errors import UsageError
from m2s2hil.faults import FaultPolicy
from m2s2hil.plan import Sweep
from m2s2hil.processing.demosaic import check_method
from m2s2hil.rig import Rig
from m2s2hil.store import (
    SessionCorrupt,
    SessionNotFound,
    SessionStore,
    estimate_session_bytes,
    list_sessions,
)

from .metrics import Metrics

log = logging.getLogger(__name__)

#: Journal states of a session that was accepted or running when its daemon went away.
RESUMABLE = frozenset({"created", "queued", "running", "pausing", "interrupted"})
#: … and those an operator may resume by hand (a paused session is not resumed automatically).
RESUMABLE_BY_HAND = RESUMABLE | {"paused"}
TERMINAL = frozenset({"completed", "failed", "aborted", "cancelled"})
Action = Literal["pause", "resume", "abort"]
LOCK_NAME = ".m2s2hil-daemon.lock"
S = RunState


class UnknownSession(UsageError):
    """No such session under the data root (HTTP 404)."""


class Conflict(UsageError):
    """The request is well formed but the session's or the rig's state does not allow it (HTTP 409)."""


class QueueFull(UsageError):
    """Too many sessions already wait for the rig (HTTP 429)."""


class PlanTooLarge(UsageError):
    """A sweep with more frames than the daemon accepts (HTTP 422)."""


class RootLocked(UsageError):
    """Another daemon serves this data root."""


@dataclass(eq=False)
class Job:
    """A session this daemon process knows: queued, running, or finished since it started."""

    session_id: str
    store: SessionStore
    resume: bool
    queued_at: float
    planned: int
    state: Literal["queued", "running", "finished", "cancelled"] = "queued"
    engine: Engine | None = None
    run: int = 1  # which run of the session the engine is (1 + runs in the journal before it)
    error: str | None = None
    final_state: str | None = None  # completed / aborted / failed / cancelled, once finished
    shutdown_paused: bool = False  # parked by a daemon shutdown (not by an operator)
    finished: threading.Event = field(default_factory=threading.Event)


@dataclass(frozen=True)
class SafeCheck:
    safe: bool
    lamps_on: list[int]
    moving: dict[str, bool]
    errors: list[str]


def lock_data_root(root: str | Path) -> IO[str]:
    """An exclusive lock on the data root for the daemon's lifetime (released when the returned
    file is closed or the process ends): two daemons must not write one root."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    f = open(root / LOCK_NAME, "a+")  # noqa: SIM115  (held for the daemon's life)
    try:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.close()
        raise RootLocked(f"another m2s2hil daemon is serving {root}") from None
    f.seek(0)
    f.truncate()
    f.write(f"{os.getpid()}\n")
    f.flush()
    return f


def planned_frame_count(sweep: Sweep) -> float:
    """Frames a sweep asks for, without expanding it (inf when absurdly many)."""
    ratio = 360.0 / sweep.azimuth_step_deg
    if not math.isfinite(ratio) or ratio > 1e9:
        return math.inf
    n_az = math.ceil(ratio - 1e-9)
    return float(len(sweep.lighting) * len(sweep.tilts) * n_az * sweep.frames_per_pose)


class SessionManager:
    def __init__(
        self,
        rig: Rig,
        root: str | Path,
        *,
        queue_limit: int = 16,
        max_plan_frames: int = 20_000,
        policy: FaultPolicy | None = None,
        engine_options: dict[str, Any] | None = None,
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
        self.engine_options = dict(engine_options or {})
        self.metrics = metrics or Metrics()
        self.keep_finished = keep_finished
        self.estop_grace_s = estop_grace_s
        self.estop_timeout_s = estop_timeout_s
        self.started_at = time.time()

        self._lock = threading.RLock()
        self._cond = threading.Condition(self._lock)
        self._submit_lock = threading.Lock()  # serialises check-then-create of new sessions
        self._hw = threading.Lock()  # request threads' own device conversations
        self._queue: collections.deque[Job] = collections.deque()
        self._jobs: dict[str, Job] = {}
        self._finished_order: collections.deque[str] = collections.deque()
        self._current: Job | None = None
        self._held: str | None = None
        self._closing = False
        self._thread: threading.Thread | None = None
        self._planned_cache: dict[str, int] = {}
        self._lockfile: IO[str] | None = root_lock  # from lock_data_root(), or taken by start()
        self._shutdown_reason: str | None = None
        self._closed: dict | None = None

        self.metrics.gauge("m2s2hil_queue_depth", "Items waiting: sessions for the rig, frames in the "
                           "running session's processing pipeline.", self._queue_gauges)
        self.metrics.gauge("m2s2hil_sessions_running", "Sessions owning the rig (0 or 1).",
                           lambda: {(): 1.0 if self.running_id() else 0.0})
        self.metrics.gauge("m2s2hil_queue_held", "1 while the queue is held (emergency stop, failure).",
                           lambda: {(): 1.0 if self._held else 0.0})

    # ================================================================== lifecycle
    def start(self, *, resume_interrupted: bool = False) -> list[str]:
        """Lock the data root, optionally queue the sessions the journals show as interrupted
        (those that were running first, then those that were waiting, oldest first), and start
        dispatching. Returns the ids queued for resumption."""
        self.root.mkdir(parents=True, exist_ok=True)
        self._lock_root()
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
            self._engine_request(job.engine, "pause")

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
                self._engine_request(job.engine, "abort")
        else:
            self.request_shutdown(reason)
            reason = self._shutdown_reason or reason
            job = self._current
        report: dict[str, Any] = {"session_id": None, "session_state": None}
        if job is not None and job.engine is not None:
            eng = job.engine
            deadline = time.monotonic() + timeout
            while time.monotonic() < deadline:
                st = eng.state
                if st.terminal or st is RunState.PAUSED:
                    break
                time.sleep(0.02)
            st = eng.state
            if not (st.terminal or st is RunState.PAUSED):
                log.error("session %s did not reach a safe boundary within %.0f s: aborting it",
                          job.session_id, timeout)
                self._engine_request(eng, "abort")
                eng.wait(timeout=30)
                st = eng.state
            report.update(session_id=job.session_id, session_state=st.value)
        if self._thread is not None:
            self._thread.join(timeout=5)
        with self._hw:
            errors = [f"{type(e).__name__}: {e}" for e in self.rig.safe()]
        check = self.check_safe()
        errors += check.errors
        report.update(rig_safe=check.safe, lamps_on=check.lamps_on, moving=check.moving, errors=errors)
        if job is not None and job.engine is not None and report["session_state"] == "paused":
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
        if check.safe:
            log.info("rig left safe: lamps off, motion stopped")
        else:
            log.error("rig NOT confirmed safe: lamps on %s, moving %s, errors %s", check.lamps_on,
                      check.moving, errors)
        self._unlock_root()
        self._closed = report
        return report

    def _lock_root(self) -> None:
        if self._lockfile is None:
            self._lockfile = lock_data_root(self.root)

    def _unlock_root(self) -> None:
        if self._lockfile is not None:
            with contextlib.suppress(OSError):
                fcntl.flock(self._lockfile.fileno(), fcntl.LOCK_UN)
            self._lockfile.close()
            self._lockfile = None

    # ================================================================== dispatching
    def _dispatch(self) -> None:
        while True:
            with self._cond:
                while True:
                    if self._closing:
                        return
                    cur = self._current
                    if cur is not None and cur.engine is not None and not cur.finished.is_set():
                        thread = getattr(cur.engine, "_thread", None)
                        if thread is not None and not thread.is_alive() and cur.engine.state.terminal:
                            self._finish(cur, cur.engine.state.value)  # finished without its event
                            continue
                    if self._current is None and self._queue and not self._held:
                        job = self._queue.popleft()
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
        engine = Engine(self.rig, job.store, policy=self.policy, **self.engine_options)
        engine.subscribe(self.metrics.observe)
        engine.subscribe(lambda ev, job=job: self._on_event(job, ev))
        with self._cond:
            if self._held or self._closing:  # an emergency stop or a shutdown came in meanwhile
                self._queue.appendleft(job)
                self._current = None
                self._cond.notify_all()
                return
            job.engine = engine
            job.run = runs + 1
            job.state = "running"
            with self._hw:
                engine.start()
        log.info("session %s started (run %d, %d planned events)", job.session_id, job.run, job.planned)

    def _on_event(self, job: Job, ev: EngineEvent) -> None:
        if isinstance(ev, SessionFinished):
            with self._cond:
                self._finish(job, ev.state.value)
                if ev.state is RunState.FAILED and not self._held:
                    self._held = f"session {job.session_id} failed: {ev.error}"
                    log.error("queue held: %s", self._held)

    def _finish(self, job: Job, state: str) -> None:
        """Caller holds the lock."""
        if job.finished.is_set():
            return
        job.state = "finished" if state != "cancelled" else "cancelled"
        job.final_state = state
        if job.error is None and job.engine is not None:
            job.error = job.engine.status().error
        job.finished.set()
        if self._current is job:
            self._current = None
        self._finished_order.append(job.session_id)
        while len(self._finished_order) > self.keep_finished:
            old = self._finished_order.popleft()
            gone = self._jobs.get(old)
            if gone is not None and gone.finished.is_set():
                del self._jobs[old]  # reads go to the journal on disk from now on
        self._cond.notify_all()

    # ================================================================== submission
    def submit(self, sweep: Sweep) -> Job:
        """Check the plan against the rig and the disk, create the session and queue it."""
        n = planned_frame_count(sweep)
        if n > self.max_plan_frames:
            shown = "too many" if math.isinf(n) else f"{int(n)}"
            raise PlanTooLarge(
                f"the sweep asks for {shown} frames; this daemon accepts at most {self.max_plan_frames} "
                "per session (raise azimuth_step_deg, or lower frames_per_pose, lighting or tilts)"
            )
        try:
            check_method(sweep.processing)
        except UsageError as exc:
            raise UsageError(f"body.processing: {exc}") from None
        cfg = self.rig.config
        events = sweep.expand(cfg)  # PlanError (422) when the rig cannot do it
        need = estimate_session_bytes(sweep, cfg)
        with self._submit_lock:
            self._check_accepting()
            with self._lock:
                if self._would_wait() and len(self._queue) >= self.queue_limit:
                    raise QueueFull(
                        f"{len(self._queue)} session(s) already wait for the rig (limit {self.queue_limit}); "
                        "cancel one (POST /sessions/{id}/abort) or retry when the running one ends"
                    )
            self.root.mkdir(parents=True, exist_ok=True)
            try:
                check_free_space(self.root, need)
            except DiskFull as exc:
                raise DiskFull("the data root", needed=exc.needed, free=exc.free) from None
            store = SessionStore.create(self.root, sweep, cfg, clock=self.rig.clock)
            store.set_state("queued")
            store.record_event("queued", {"via": "api", "planned_events": len(events)})
            job = Job(store.session_id, store, resume=False, queued_at=time.time(), planned=len(events))
            with self._cond:
                self._jobs[job.session_id] = job
                self._queue.append(job)
                self._planned_cache[job.session_id] = len(events)
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
                live = self._jobs.get(session_id)
                if live is not None and not live.finished.is_set():
                    raise Conflict(f"session {session_id} is already {live.state} in this daemon")
                if check_limit and self._would_wait() and len(self._queue) >= self.queue_limit:
                    raise QueueFull(f"{len(self._queue)} session(s) already wait for the rig "
                                    f"(limit {self.queue_limit})")
            store = self._open(session_id)
            try:
                if store.rig_digest != self.rig.config.digest:
                    raise Conflict(
                        f"session {session_id} was captured with a different rig configuration "
                        f"(digest {store.rig_digest[:12]}…, this rig {self.rig.config.digest[:12]}…); "
                        "resume it with the rig it was started on"
                    )
                planned = self._planned(store)
                was = store.state
                store.record_event("requeued", {"reason": reason, "was": was})
                store.set_state("queued")
            except BaseException:
                store.close()
                raise
            job = Job(session_id, store, resume=True, queued_at=time.time(), planned=planned)
            with self._cond:
                self._jobs[session_id] = job
                self._queue.append(job)
                self._cond.notify_all()
        log.info("session %s queued for resumption (%s; was %s)", session_id, reason, was)
        return job

    # ================================================================== control
    def control(self, session_id: str, action: Action) -> dict:
        """pause / resume / abort a session; see the module docstring for what conflicts get."""
        with self._lock:
            job = self._jobs.get(session_id)
            if job is not None and job.state == "queued":
                if action == "abort":
                    self._cancel(job)
                    return self.status(session_id)
                pos = self._position(job)
                raise Conflict(
                    f"session {session_id} is queued (position {pos}), not running: it cannot be "
                    f"{action}d; abort cancels it"
                )
        if job is not None and job.engine is not None and not job.finished.is_set():
            self._engine_request(job.engine, action, raise_errors=True)
            return self.status(session_id)
        if job is not None:
            state = self.status(session_id)["state"]
            raise Conflict(f"session {session_id} is {state}: there is nothing to {action}")
        info = self._disk_status(session_id)
        state = info["state"]
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

    def _cancel(self, job: Job) -> None:
        """Caller holds the lock."""
        with contextlib.suppress(ValueError):
            self._queue.remove(job)
        try:
            job.store.record_event("cancelled", {"by": "operator"})
            job.store.set_state("cancelled")
        except Exception as exc:
            log.error("could not record the cancellation of %s: %s", job.session_id, exc)
        self._finish(job, "cancelled")
        log.info("session %s cancelled while queued", job.session_id)

    def _engine_request(self, engine: Engine, action: Action, *, raise_errors: bool = False) -> None:
        """pause/resume/abort an engine; an engine that is still starting (idle) gets a moment."""
        deadline = time.monotonic() + 2.0
        while True:
            try:
                getattr(engine, action)()
                return
            except IllegalTransition:
                if engine.state is RunState.IDLE and time.monotonic() < deadline:
                    time.sleep(0.01)
                    continue
                if raise_errors:
                    raise
                return

    def hold(self, reason: str) -> None:
        """Hold the queue: the running session goes on, no queued one starts (e.g. while an
        operator swaps the mockup) until :meth:`release`."""
        with self._cond:
            self._held = reason
            self._cond.notify_all()
        log.info("queue held: %s", reason)

    def release(self) -> str | None:
        """Release a held queue; returns the reason it was held."""
        with self._cond:
            was, self._held = self._held, None
            self._cond.notify_all()
        if was:
            log.info("queue released (was held: %s)", was)
        return was

    # ================================================================== emergency stop
    def emergency_stop(self) -> dict:
        """Lamps off and motion stopped now, whatever runs.

        Order: hold the queue; switch every lamp off (the relay driver serialises its own
        I/O, so this is safe beside the engine thread); ask the running session to abort;
        give it ``estop_grace_s`` to reach its own teardown (which stops motion too), then
        stop the axes from this thread anyway (a move is not waited out); once the engine
        has ended, make safe again and read the devices back to confirm."""
        t0 = time.monotonic()
        self.metrics.count_estop()
        with self._cond:
            self._held = "emergency stop"
            job = self._current
            self._cond.notify_all()
        log.warning("EMERGENCY STOP requested%s", f" (session {job.session_id} running)" if job else "")
        errors: list[str] = []
        try:
            self.rig.lights.set(())
        except Exception as exc:
            errors.append(f"lamps off: {type(exc).__name__}: {exc}")
        eng = job.engine if job is not None else None
        if eng is not None and not eng.state.terminal:
            self._engine_request(eng, "abort")
            if not _wait_terminal(eng, self.estop_grace_s):
                errors += [f"{type(e).__name__}: {e}" for e in self.rig.safe()]
                if not _wait_terminal(eng, self.estop_timeout_s):
                    errors.append(f"session {job.session_id} did not end within {self.estop_timeout_s:g} s")
        with self._hw:
            errors += [f"{type(e).__name__}: {e}" for e in self.rig.safe()]
        check = self.check_safe()
        errors += check.errors
        if check.safe:
            log.warning("emergency stop done: lamps off, motion stopped")
        else:
            log.error("emergency stop could NOT confirm a safe rig: %s", errors)
        return {
            "safe": check.safe, "lamps_on": check.lamps_on, "moving": check.moving,
            "session_id": job.session_id if job else None,
            "session_state": eng.state.value if eng is not None else None,
            "held": self._held or "emergency stop", "errors": errors,
            "elapsed_s": time.monotonic() - t0,
        }

    def check_safe(self) -> SafeCheck:
        """Read the devices back: which lamps are on, which axis moves."""
        errors: list[str] = []
        lamps: list[int] = []
        moving: dict[str, bool] = {}
        try:
            lamps = sorted(self.rig.lights.state())
        except Exception as exc:
            errors.append(f"lamps read-back: {type(exc).__name__}: {exc}")
        for role, ax in (("turntable", self.rig.turntable), ("tilt", self.rig.tilt)):
            try:
                moving[role] = bool(ax.is_moving())
            except Exception as exc:
                errors.append(f"{role} read-back: {type(exc).__name__}: {exc}")
        safe = not errors and not lamps and not any(moving.values())
        return SafeCheck(safe, lamps, moving, errors)

    # ================================================================== queries
    def running_id(self) -> str | None:
        cur = self._current
        return cur.session_id if cur is not None and cur.engine is not None else None

    @property
    def held(self) -> str | None:
        return self._held

    def queue(self) -> dict:
        with self._lock:
            items = [{"session_id": j.session_id, "position": i + 1, "resume": j.resume,
                      "queued_at": j.queued_at} for i, j in enumerate(self._queue)]
            return {"running": self.running_id(), "held": self._held, "limit": self.queue_limit,
                    "items": items}

    def _queue_gauges(self) -> dict[tuple[tuple[str, str], ...], float]:
        cur = self._current
        pipe = 0.0
        if cur is not None and cur.engine is not None and not cur.finished.is_set():
            with contextlib.suppress(Exception):
                pipe = float(cur.engine.pipeline_stats().in_flight)
        return {(("queue", "sessions"),): float(len(self._queue)), (("queue", "pipeline"),): pipe}

    def _position(self, job: Job) -> int | None:
        try:
            return list(self._queue).index(job) + 1
        except ValueError:
            return None

    def job(self, session_id: str) -> Job | None:
        return self._jobs.get(session_id)

    def status(self, session_id: str) -> dict:
        """A status snapshot (the body of ``GET /sessions/{id}``)."""
        job = self._jobs.get(session_id)
        if job is None:
            return self._disk_status(session_id)
        if job.engine is not None:
            st = job.engine.status().to_dict()
            out = {k: st[k] for k in (
                "done", "total", "skipped", "progress", "eta_s", "elapsed_s", "lighting", "elevation",
                "tilt_deg", "azimuth_deg", "last_frame_index", "last_event_id", "pause_reason", "error",
                "efficiency", "mode")}
            out.update(session_id=session_id, state=st["state"], live=True, queue_position=None,
                       lamps_on=list(st["lamps_on"]), faults=list(st["faults"])[-50:],
                       satellite=job.store.sweep.satellite, build=job.store.sweep.build,
                       created=job.store.created, resumable=False)
            return out
        # queued or cancelled before running
        with self._lock:
            pos = self._position(job)
        done = len(job.store.completed_event_ids())
        return {
            "session_id": session_id, "state": job.final_state or "queued",
            "live": True, "queue_position": pos, "resumable": False, "satellite": job.store.sweep.satellite,
            "build": job.store.sweep.build, "mode": job.store.sweep.mode, "done": done, "total": job.planned,
            "progress": done / job.planned if job.planned else 1.0, "created": job.store.created,
            "error": job.error,
        }

    def _open(self, session_id: str) -> SessionStore:
        try:
            return SessionStore.open(self.root, session_id, clock=self.rig.clock)
        except SessionNotFound:
            raise UnknownSession(f"no session {session_id!r}") from None

    def _planned(self, store: SessionStore) -> int:
        sid = store.session_id
        n = self._planned_cache.get(sid)
        if n is None:
            n = len(store.sweep.expand(store.rig))
            self._planned_cache[sid] = n
        return n

    def _disk_status(self, session_id: str) -> dict:
        try:
            store = self._open(session_id)
        except SessionCorrupt as exc:
            return {"session_id": session_id, "state": "corrupt", "live": False, "error": str(exc)}
        try:
            row = store.journal.session()
            planned = self._planned(store)
            done = len(store.completed_event_ids())
            skipped = len(store.skipped_event_ids())
            faults: list[dict] = []
            error = None
            last_finish: dict = {}
            for e in store.events():
                p = e.get("payload") or {}
                if e["kind"] == "fault":
                    faults.append({"time_s": float(p.get("clock_s") or 0.0),
                                   "fault_class": str(p.get("fault_class", "other")),
                                   "action": str(p.get("action", "")), "message": str(p.get("message", "")),
                                   "event_id": p.get("event_id"), "attempt": int(p.get("attempt") or 1),
                                   "device": p.get("device")})
                elif e["kind"] == "run_finished":
                    last_finish = p
                    error = p.get("error")
            state = row["state"]
            return {
                "session_id": session_id, "state": state, "live": False, "queue_position": None,
                "resumable": state in RESUMABLE_BY_HAND, "satellite": store.sweep.satellite,
                "build": store.sweep.build, "mode": store.sweep.mode, "done": done, "total": planned,
                "skipped": skipped, "progress": (done + skipped) / planned if planned else 1.0,
                "elapsed_s": last_finish.get("duration_s"), "efficiency": last_finish.get("efficiency"),
                "faults": faults[-50:], "error": error, "created": row["created"], "updated": row["updated"],
                "eta_s": 0.0 if state == "completed" else None,
            }
        finally:
            store.close()

    def sessions(self, *, state: str | None = None, satellite: str | None = None, build: str | None = None,
             offset: int = 0, limit: int = 50) -> tuple[list[dict], int]:
        """Sessions under the data root, newest first, with this daemon's live view on top."""
        rows: list[dict] = []
        for info in list_sessions(self.root):
            job = self._jobs.get(info.session_id)
            st = info.state
            if job is not None:
                if job.engine is not None:
                    st = job.engine.state.value
                elif job.state == "queued":
                    st = "queued"
            rows.append({"session_id": info.session_id, "state": st, "satellite": info.satellite,
                         "build": info.build, "created": info.created, "updated": info.updated,
                         "frames": info.frames, "error": info.error})
        if state:
            rows = [r for r in rows if r["state"] == state]
        if satellite:
            rows = [r for r in rows if (r["satellite"] or "").lower() == satellite.lower()]
        if build:
            rows = [r for r in rows if (r["build"] or "").lower() == build.lower()]
        total = len(rows)
        page = []
        for r in rows[offset:offset + limit]:
            try:
                page.append(self.status(r["session_id"]))
            except UnknownSession:  # removed meanwhile
                continue
        return page, total

    # ------------------------------------------------------------------ frames
    @contextlib.contextmanager
    def reading(self, session_id: str) -> Iterator[SessionStore]:
        """The session's store for reading: the live one, or one opened for this request."""
        job = self._jobs.get(session_id)
        if job is not None:
            yield job.store
            return
        try:
            store = self._open(session_id)
        except SessionCorrupt as exc:
            raise Conflict(f"session {session_id} cannot be read: {exc}") from None
        try:
            yield store
        finally:
            store.close()

    def frames(self, session_id: str, *, offset: int = 0, limit: int = 50) -> tuple[list[Any], int]:
        with self.reading(session_id) as store:
            total = store.journal.query("SELECT COUNT(*) AS n FROM frames")[0]["n"]
            rows = store.journal.query("SELECT * FROM frames ORDER BY idx LIMIT ? OFFSET ?", (limit, offset))
            return [SessionStore._frame_record(r) for r in rows], int(total)

    def frame_file(self, session_id: str, n: int, role: Literal["raw", "preview"]) -> bytes:
        with self.reading(session_id) as store:
            rows = store.journal.query("SELECT * FROM frames WHERE idx = ?", (n,))
            if not rows:
                raise UnknownSession(f"session {session_id} has no frame {n} (frames are numbered by their "
                                     "index in the plan; GET /sessions/{id}/frames lists them)")
            rec = SessionStore._frame_record(rows[0])
            f = rec.files.get(role)
            if f is None:
                raise UnknownSession(f"frame {n} of session {session_id} has no {role} file")
            base = store.path.resolve()
            if not (base / f.path).resolve().is_relative_to(base):
                raise SessionCorrupt(f"journal of {session_id} names a file outside its folder")
            return store.read_file(f, check=True)

    # ------------------------------------------------------------------ events
    def journal_events(self, session_id: str) -> tuple[str, list[dict]]:
        """(state, events) replayed from the journal for a session no engine here knows."""
        with self.reading(session_id) as store:
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
            state = store.state
        return state, [{"kind": k, "wall": t, **d} for t, _, k, d in items]

    # ------------------------------------------------------------------ rig
    def rig_state(self) -> dict:
        """Each device's state and health. While a session owns the rig the values are the
        engine's own read-back (health ``busy``): two threads on one serial line would
        corrupt each other's conversation."""
        cfg = self.rig.config
        cur = self._current
        eng = cur.engine if cur is not None and cur.engine is not None and not cur.finished.is_set() else None
        devices: list[dict] = []
        faults_by_dev: collections.Counter = collections.Counter()
        if eng is not None:
            st = eng.status()
            for f in st.faults:
                faults_by_dev[f.device or "?"] += 1
        with self._hw:
            for name, dev in cfg.devices.items():
                roles = [r for r, ax in cfg.axes.items() if ax.device == name]
                kind = "motion" if roles else "relay"
                entry: dict[str, Any] = {
                    "name": name, "kind": kind, "protocol": dev.protocol, "port": dev.port, "health": "ok",
                    "state": {}, "error": None, "recent_faults": faults_by_dev.get(name, 0)}
                if eng is not None:
                    entry["health"] = "busy"
                    if kind == "motion":
                        entry["state"] = {f"{r}_deg": (st.azimuth_deg if r == "turntable" else st.tilt_deg)
                                          for r in roles}
                    else:
                        entry["state"] = {"lamps_on": list(st.lamps_on)}
                else:
                    try:
                        if kind == "motion":
                            for r in roles:
                                ax = self.rig.turntable if r == "turntable" else self.rig.tilt
                                entry["state"][f"{r}_deg"] = float(ax.position())
                                entry["state"][f"{r}_moving"] = bool(ax.is_moving())
                        else:
                            on = sorted(self.rig.lights.state())
                            names = {lc.channel: n for n, lc in cfg.lamps.items()}
                            entry["state"] = {"lamps_on": on,
                                              "lamp_names": [names.get(c, f"ch{c}") for c in on]}
                    except Exception as exc:
                        entry["health"] = "error"
                        entry["error"] = f"{type(exc).__name__}: {exc}"
                devices.append(entry)
            cam: dict[str, Any] = {"name": "camera", "kind": "camera", "protocol": "u3v",
                                   "port": cfg.camera.port, "health": "ok", "state": {}, "error": None,
                                   "recent_faults": faults_by_dev.get("camera", 0)}
            model = cfg.camera.model
            cam["state"] = {"model": model.name, "width": model.width, "height": model.height}
            if eng is not None:
                cam["health"] = "busy"
            else:
                try:
                    cam["state"]["temperature_c"] = float(self.rig.camera.temperature_c())
                except Exception as exc:
                    cam["health"] = "error"
                    cam["error"] = f"{type(exc).__name__}: {exc}"
            devices.append(cam)
        return {"name": cfg.rig.name, "simulated": bool(self.rig.simulated), "digest": cfg.digest,
                "session_id": cur.session_id if eng is not None else None, "held": self._held,
                "devices": devices}


def _wait_terminal(engine: Engine, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while not engine.state.terminal:
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.01)
    return True
