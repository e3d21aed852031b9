"""Synthetic sessions through the daemon (``POST /synthetic``): the paper's synthetic domain of one
build (m2s2hil.twin.synth), rendered on a worker thread and watched like a capture session.

A render needs no rig (the twin's scene, not the devices), so it does not wait for the rig's
queue and runs beside a capture: one render at a time, first in first out, up to
``queue_limit`` waiting (:class:`QueueFull`, 429, beyond). :meth:`SynthJobs.submit` checks the
plan (catalog names, elevations, size, step, the frame limit, the disk) and creates the
session (kind ``synthetic``, state ``queued``) before it answers, so the client has its id,
its URL and the number of views at once.

Watched like a capture session, at the same URLs: :meth:`status` is the body of ``GET
/sessions/{id}`` (``mode`` = ``"synthetic"``, ``total`` = ``planned_frames`` = the views,
no darks), :meth:`events_since` feeds ``GET /sessions/{id}/events`` (``state``, ``frame``,
``progress``, ``finished``; ids ``1-<seq>``), and :meth:`control` answers ``POST
/sessions/{id}/abort`` (the render stops before its next view, what is stored is kept, the
session ends ``aborted``). Pause and resume are refused (409): a render holds nothing to park,
and a synthetic session is never resumed by the capture engine (render it again).

A daemon shutdown stops a render at its next view (state ``aborted``, reason in the journal's
``synthetic_stopped`` event). Jobs are kept in memory, the last ``keep_finished``; after that,
and after a restart, a synthetic session is read from its journal (:func:`disk_status`).
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import sqlite3
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from m2s2hil.config import RigConfig
from m2s2hil.errors import M2S2Error
from m2s2hil.plan import CaptureEvent
from m2s2hil.store.session import SessionStore
from m2s2hil.twin.synth import SynthPlan, SynthRun, end_reason, planned_views

from .admission import check_room
from .errors import Conflict, PlanTooLarge, QueueFull

if TYPE_CHECKING:
    from .manager import SessionManager

log = logging.getLogger(__name__)

#: Bytes a view needs on disk per pixel of its side²: thirteen 8-bit PNGs and the JPEG preview
#: (0.33 MB a 512² view measured, docs/benchmarks.md: 1.3 B/px; 3 leaves room for busier scenes).
BYTES_PER_PIXEL = 3
#: The daemon's frame limit counts a view as a frame up to this side (a superpixel cube of a 2048²
#: TOUCAN frame), a larger one as (side / 512)² frames: the render's cost grows with its pixels.
FRAME_SIDE = 512
HISTORY = 4096  # events kept per job for SSE reconnects (older ones: a ``gap`` message)


@dataclass(eq=False)
class SynthJob:
    """One synthetic session this daemon renders, rendered or refused to render."""

    session_id: str
    satellite: str
    build: str
    light: str
    planned: int
    run: SynthRun | None
    state: str = "queued"  # queued → running → completed | aborted | failed | cancelled
    done: int = 0
    created: float = field(default_factory=time.time)
    updated: float = field(default_factory=time.time)
    started: float | None = None
    last: CaptureEvent | None = None
    error: str | None = None
    cancel: threading.Event = field(default_factory=threading.Event)
    finished: threading.Event = field(default_factory=threading.Event)
    events: collections.deque[tuple[int, str, dict[str, Any]]] = field(
        default_factory=lambda: collections.deque(maxlen=HISTORY))
    seq: int = 0
    _events_lock: threading.Lock = field(default_factory=threading.Lock)

    def emit(self, kind: str, data: dict[str, Any]) -> None:
        """One event for the SSE stream (written by the worker, read by the streams' loop)."""
        with self._events_lock:
            self.seq += 1
            self.events.append((self.seq, kind, {**data, "session_id": self.session_id}))
            self.updated = time.time()

    def since(self, seq: int) -> list[tuple[int, str, dict[str, Any]]]:
        with self._events_lock:  # a deque must not change while it is copied
            return [e for e in self.events if e[0] > seq]


class SynthJobs:
    """The daemon's synthetic renders: a FIFO served by one worker thread, started on demand."""

    def __init__(self, manager: SessionManager, *, queue_limit: int = 16, keep_finished: int = 32) -> None:
        self._mg = manager
        self.queue_limit = queue_limit
        self.keep_finished = keep_finished
        self._lock = threading.Condition()
        self._waiting: collections.deque[SynthJob] = collections.deque()
        self._jobs: dict[str, SynthJob] = {}
        self._finished: collections.deque[str] = collections.deque()
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ submission
    def submit(self, plan: SynthPlan) -> SynthJob:
        """Check ``plan``, create its session and queue it; UsageError (422), PlanTooLarge (422),
        DiskFull (507), QueueFull (429), Conflict (409, the daemon shutting down)."""
        from m2s2hil.analysis.segmenters.rgb import band_colours, camera_weights
        from m2s2hil.twin.synth import GAMMA

        mg = self._mg
        if mg.closing:
            raise Conflict("the daemon is shutting down; no new sessions are accepted")
        cfg = mg.rig.config
        bands = cfg.camera.model.bands_nm
        with self._lock:
            if len(self._waiting) >= self.queue_limit:
                raise QueueFull(f"{len(self._waiting)} synthetic session(s) already wait to render "
                                f"(limit {self.queue_limit}); abort one or retry when the running one ends")
        # Checked and created outside the lock (files, catalog); the frame limit before any file.
        run = _checked_run(mg.root, cfg, plan, band_colours(bands, gamma=GAMMA), camera_weights(bands),
                           mg.max_plan_frames)
        job = SynthJob(run.session_id, run.build.satellite, run.build.key, run.light.key, run.total, run)
        run.store.record_event("queued", {"via": "api", "planned_events": run.total, "kind": "synthetic"})
        job.emit("state", {"new": "queued", "old": None})
        with self._lock:
            if mg.closing or len(self._waiting) >= self.queue_limit:  # changed while we created it
                run.discard()
                if mg.closing:
                    raise Conflict("the daemon is shutting down")
                raise QueueFull(f"{len(self._waiting)} synthetic session(s) already wait to render "
                                f"(limit {self.queue_limit})")
            self._jobs[job.session_id] = job
            self._waiting.append(job)
            if self._thread is None or not self._thread.is_alive():
                self._thread = threading.Thread(target=self._work, name="synthetic-renders", daemon=True)
                self._thread.start()
            self._lock.notify_all()
        mg.activity.record("session", f"synthetic session {job.session_id} queued ({job.planned} views of "
                           f"{job.satellite} {job.build})", session_id=job.session_id, state="queued")
        log.info("synthetic session %s queued (%d views)", job.session_id, job.planned)
        return job

    # ------------------------------------------------------------------ the worker
    def _work(self) -> None:
        while True:
            with self._lock:
                while not self._waiting:
                    if not self._lock.wait(timeout=5.0) and not self._waiting:
                        self._thread = None  # idle: a later submit starts another
                        return
                job = self._waiting.popleft()
            self._render(job)

    def _stop_reason(self, job: SynthJob) -> str | None:
        if job.cancel.is_set():
            return "aborted by the operator"
        if self._mg.closing:
            return "daemon shutdown"
        return None

    def _render(self, job: SynthJob) -> None:
        assert job.run is not None
        job.state, job.started = "running", time.time()
        job.emit("state", {"new": "running", "old": "queued"})
        self._mg.activity.record("session", f"synthetic session {job.session_id} started",
                                 session_id=job.session_id, state="running")

        def progress(done: int, total: int, ev: CaptureEvent) -> None:
            job.done, job.last = done, ev
            job.emit("frame", {"event_id": ev.event_id, "index": ev.index, "elevation": ev.elevation,
                               "tilt_deg": ev.tilt_deg, "azimuth_deg": ev.nominal_azimuth_deg})
            job.emit("progress", {"done": done, "total": total, "progress": done / total if total else 1.0,
                                  "eta_s": self._eta(job)})

        state, views = "failed", 0
        try:
            res = job.run.run(progress=progress, stop=lambda: self._stop_reason(job))
            state, views = res.state, res.views
        except Exception as exc:  # the session is marked failed by the run; the daemon goes on
            job.error = f"{type(exc).__name__}: {exc}"
            log.error("synthetic session %s failed: %s", job.session_id, job.error)
        job.run = None  # its store is closed; reads go to the journal
        self._finish(job, state, views)

    def _eta(self, job: SynthJob) -> float | None:
        if job.started is None or not job.done:
            return None
        return (time.time() - job.started) / job.done * (job.planned - job.done)

    def _finish(self, job: SynthJob, state: str, views: int) -> None:
        with self._lock:
            job.state = state
            job.emit("finished", {"state": state, "views": views, "planned": job.planned, "error": job.error,
                                  "elapsed_s": (time.time() - job.started) if job.started else 0.0})
            job.finished.set()
            self._finished.append(job.session_id)
            while len(self._finished) > self.keep_finished:
                self._jobs.pop(self._finished.popleft(), None)
            self._lock.notify_all()
        self._mg.activity.record("session", f"synthetic session {job.session_id} {state} ({views} of "
                                 f"{job.planned} views)" + (f": {job.error}" if job.error else ""),
                                 level="error" if state == "failed" else "info", session_id=job.session_id,
                                 state=state)

    # ------------------------------------------------------------------ reads and control
    def job(self, session_id: str) -> SynthJob | None:
        return self._jobs.get(session_id)

    def status(self, session_id: str) -> dict[str, Any] | None:
        """The status of a synthetic session this daemon knows (None otherwise)."""
        job = self._jobs.get(session_id)
        if job is None:
            return None
        with self._lock:
            pos = next((i + 1 for i, j in enumerate(self._waiting) if j is job), None)
        ev = job.last
        state = "aborting" if job.state == "running" and job.cancel.is_set() else job.state
        elapsed = None if job.started is None else time.time() - job.started
        return {
            "session_id": job.session_id, "state": state, "live": True, "queue_position": pos,
            "resumable": False, "satellite": job.satellite, "build": job.build, "mode": "synthetic",
            "lighting": job.light, "done": job.done, "total": job.planned, "planned_frames": job.planned,
            "planned_darks": 0, "skipped": 0, "progress": job.done / job.planned if job.planned else 1.0,
            "eta_s": 0.0 if state == "completed" else self._eta(job), "elapsed_s": elapsed,
            "elevation": ev.elevation if ev else None, "tilt_deg": ev.tilt_deg if ev else None,
            "azimuth_deg": ev.nominal_azimuth_deg if ev else None,
            "last_frame_index": ev.index if ev else None, "last_event_id": ev.event_id if ev else None,
            "error": job.error, "created": job.created, "updated": job.updated,
        }

    def events_since(self, session_id: str, seq: int) -> tuple[list[tuple[int, str, dict[str, Any]]], bool]:
        """(events after ``seq``, finished) of a known job."""
        job = self._jobs.get(session_id)
        if job is None:  # forgotten meanwhile (beyond keep_finished): it has ended
            return [], True
        done = job.finished.is_set()  # read first: a last event appended after it is seen next time
        return job.since(seq), done

    def control(self, session_id: str, action: str) -> dict[str, Any] | None:
        """``abort`` a known job (queued: cancelled at once; running: stops before the next view);
        pause and resume: :class:`Conflict`. None when the session is not a synthetic one this
        daemon knows (the caller then asks :func:`control_stored`)."""
        job = self._jobs.get(session_id)
        if job is None:
            return None
        if action != "abort":
            raise Conflict(f"session {session_id} is a synthetic render: it cannot be {action}d "
                           "(abort stops it, keeping the views stored)")
        if job.finished.is_set():
            raise Conflict(f"session {session_id} is {job.state}: there is nothing to abort")
        cancelled = False
        with self._lock:
            if job in self._waiting:
                self._waiting.remove(job)
                cancelled = True
        if cancelled:
            assert job.run is not None
            run, job.run = job.run, None
            with contextlib.suppress(Exception):
                run.store.record_event("cancelled", {"by": "operator"})
            run.discard()
            self._finish(job, "cancelled", 0)
        else:
            job.cancel.set()
        return self.status(session_id)


def _checked_run(root: Path, cfg: RigConfig, plan: SynthPlan, lights: np.ndarray, weights: np.ndarray,
                 max_views: int) -> SynthRun:
    """The plan's views counted and the disk checked before the session is created."""
    from m2s2hil.twin.synth import count_views

    views = count_views(cfg, plan)  # UsageError on bad names, sizes and steps
    frames = math.ceil(views * max(1.0, (plan.size / FRAME_SIDE) ** 2))
    if frames > max_views:
        raise PlanTooLarge(f"the render asks for {views} views of {plan.size}² ({frames} frames of "
                           f"{FRAME_SIDE}²); this daemon accepts at most {max_views} per session (raise "
                           "azimuth_step_deg, name fewer tilts or lower the size)")
    check_room(root, views * plan.size * plan.size * BYTES_PER_PIXEL)
    return SynthRun(root, cfg, plan, lights, weights)


def disk_status(root: Path, session_id: str) -> dict[str, Any] | None:
    """The status of a synthetic session from its journal (no job of this daemon renders it);
    None when it is not a synthetic session (or there is none: the caller's read says so)."""
    try:
        store = SessionStore.open(root, session_id)
    except (M2S2Error, OSError, sqlite3.Error):  # none, damaged, unreadable: the session reads say so
        return None
    with store:
        if store.kind != "synthetic":
            return None
        row = store.journal.session()
        done = len(store.completed_event_ids())
        total = planned_views(store) or done
        ended = end_reason(store)
        error = None if ended is None else ended[1] if ended[0] == "failed" else f"stopped: {ended[1]}"
        state = row["state"]
        return {
            "session_id": session_id, "state": state, "live": False, "queue_position": None,
            "resumable": False,
            "satellite": store.sweep.satellite, "build": store.sweep.build, "mode": "synthetic",
            "done": done, "total": total, "planned_frames": total, "planned_darks": 0, "skipped": 0,
            "progress": done / total if total else 1.0, "eta_s": 0.0 if state == "completed" else None,
            "error": error, "created": row["created"], "updated": row["updated"],
        }


def control_stored(root: Path, session_id: str, action: str) -> dict[str, Any] | None:
    """pause / resume / abort a synthetic session only on disk (left ``running`` or ``queued``
    by a daemon that went away): abort marks it aborted; pause and resume are refused, so the
    capture engine never resumes a render. None when it is not a synthetic session."""
    st = disk_status(root, session_id)
    if st is None:
        return None
    if action != "abort":
        raise Conflict(f"session {session_id} is a synthetic render ({st['state']}): it cannot be {action}d; "
                       "render it again (POST /synthetic)")
    if st["state"] not in ("created", "queued", "running"):
        raise Conflict(f"session {session_id} is {st['state']}: there is nothing to abort")
    try:
        with SessionStore.open(root, session_id, mode="write") as store:
            store.record_event("aborted", {"by": "operator", "was": st["state"]})
            store.set_state("aborted")
    except Exception as exc:  # another process renders it (its owner lock), or the disk refused
        raise Conflict(f"session {session_id} cannot be aborted here: {exc}") from None
    return disk_status(root, session_id)
