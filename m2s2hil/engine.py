"""The capture engine: runs a :class:`~m2s2hil.plan.Sweep` on a :class:`~m2s2hil.rig.Rig`
into a :class:`~m2s2hil.store.SessionStore`.

Use::

    engine = Engine(rig, store, sweep, policy=FaultPolicy(), on_event=print)
    status = engine.run()            # blocking, in this thread; SessionFailed on failure
    # or
    engine.start()                   # in a daemon thread
    engine.pause(); engine.resume(); engine.abort()   # from any thread
    engine.status()                  # frozen EngineStatus snapshot
    unsubscribe = engine.subscribe(callback)          # typed events, in the engine thread
    listener = engine.listen()       # bounded queue of events for another thread (SSE)
    final = engine.wait()            # join the thread, final status

    engine = Engine.resume_session(rig, root, session_id)   # after a crash: skips what is stored

Constructor options: ``policy`` (:class:`~m2s2hil.faults.FaultPolicy`), ``on_event``
(a subscriber from the start), ``qc`` (``qc(processed_frame, event, meta) -> score``: the
capture-time QC hook, run in the processing stage; its result is ``meta["qc"]``, a failure is
``meta["qc_error"]``), ``process_depth``/``store_depth`` (queue bounds), ``store_workers`` (parallel writers),
continuous mode:
``speed_dps`` (override) or ``max_blur_px`` (ω limited so ω·t_exp stays under it at
``radius_px`` from the axis; default: the plan's ω), ``max_angle_error_deg``;
``retry_skipped`` (a resumed run retries earlier gaps), ``check_disk``, ``save_truth``,
``snap_timeout_s``.

Control: ``pause``/``abort`` are honoured at the next safe boundary (between captures; in
continuous mode between frames, stopping the turntable); ``resume``/``clear`` continue a
pause or a suspension. Illegal requests (e.g. ``resume`` while running, anything after the
end) raise :class:`~m2s2hil.engine_state.IllegalTransition` (a ``UsageError``: HTTP 409).
Final states: ``completed`` (gaps allowed, each recorded), ``aborted``, ``failed``.

What a run does, in the plan's order (``sweep.expand(rig.config)``):

- *dark* events: lens cap on (``rig.cap_lens``), N frames, master dark
  (``processing.dark.build_master_dark``), ``store.write_dark``; reused by every frame at
  that (exposure, gain) and retaken under a new id when the sensor temperature drifts
  beyond ``processing.dark_temperature_tolerance_c``.
- *frame* events, stop-and-go: lamps of the condition on (only when they change), tilt then
  turntable moved and verified against the read-back within the axis tolerance, settle and
  lamp warm-up waited (the warm-up overlaps the move), automatic exposure when the sweep
  asks for it (once per lighting condition, recorded as a journal event and reused on
  resume), one snap, then the frame goes down the pipeline.
- continuous mode: per pass (one lighting and tilt), the turntable turns at ω while the
  camera streams; the frame nearest each azimuth mark (by timestamp and read-back) is kept
  (:mod:`m2s2hil.continuous`); blur ω·t_exp is recorded per frame and per pass.
- pipeline (:mod:`m2s2hil.pipeline`): processing (dark subtraction + demosaicing with
  ``processing.pipeline.FrameProcessor``, then the QC hook) and storage run in their own
  threads behind bounded queues; results come back to the engine thread at safe
  boundaries.

Faults go through the :class:`~m2s2hil.faults.FaultPolicy`; every fault is recorded
(status, event bus, journal event ``fault``) and every capture given up is recorded with
``store.record_skip`` and its reason. Pause and abort are honoured between captures. Every
exit path (completion, abort, failure, Ctrl-C, even a failing teardown step) ends with lamps
off and motion stopped (:meth:`RigOps.make_safe`), and the original error is kept.

Frame metadata (``meta`` of each stored frame): ``exposure_s`` and ``gain`` as the camera
reported them, ``temperature_c``, ``pose`` (read-back of both axes), ``lamps_on``
(channels) and ``lamp_names``, ``timestamp`` (wall), ``clock_s`` (engine clock),
``host_wall``, ``device_timestamp_s``, ``host_time_s``, ``block_id``, ``dark_id`` and
``dark`` (its provenance), ``processing_method``, ``software_version``, ``rig_digest``,
``attempt`` (1 + failed tries of this capture),
``qc`` (the hook's result), ``saturated_fraction``, ``processing_warnings``; with auto
exposure ``auto_exposure``; in continuous mode ``continuous`` (angle at mid-exposure, its
error to the mark, measured speed, blur in degrees and pixels). On a simulated rig the
simulator's label map is stored with the frame as its ``truth_labels`` file
(``store.frame(id).files["truth_labels"]``, a checksummed PNG) and ``meta["truth"]`` holds
the class names and the simulator's pose.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from m2s2hil.atomic import check_free_space
from m2s2hil.autoexposure import ExposureResult, find_exposure
from m2s2hil.continuous import PassReport, blur_estimate, run_pass
from m2s2hil.drivers.errors import FrameIncomplete
from m2s2hil.engine_state import (
    Captured,
    EngineEvent,
    EngineStatus,
    EventBus,
    FaultInfo,
    FaultRecorded,
    FrameStored,
    IllegalTransition,
    Listener,
    Progress,
    RunState,
    SessionFinished,
    StateChanged,
    check_transition,
)
from m2s2hil.errors import M2S2Error, UsageError
from m2s2hil.faults import FaultPolicy, fault_class_of
from m2s2hil.pipeline import Pipeline, PipelineStats
from m2s2hil.plan import CaptureEvent, Sweep, dark_event, dark_event_id, estimate, estimate_continuous
from m2s2hil.rig import Rig
from m2s2hil.rig_ops import RigOps
from m2s2hil.store import SessionStore, estimate_session_bytes, software_version

log = logging.getLogger(__name__)

QcHook = Callable[[Any, CaptureEvent, dict], Any]
STATUS_FAULTS = 50  # faults listed in a status snapshot (all are in the journal and the events)
S = RunState


class SessionFailed(M2S2Error):
    """The session ended in ``failed``; ``cause`` is the original error, ``status`` the final status."""

    def __init__(self, status: EngineStatus, cause: BaseException | None) -> None:
        self.status = status
        self.cause = cause
        super().__init__(f"session {status.session_id} failed: {status.error}")


class _AbortRequested(BaseException):
    """Internal: unwinds the run loop to teardown after abort()."""


@dataclass
class _Captured:
    """What the camera thread hands to the processing stage."""

    data: np.ndarray
    meta: dict
    processor: Any
    truth: Any = None


@dataclass
class _Processed:
    raw: np.ndarray
    cube: np.ndarray | None
    preview: np.ndarray | None
    meta: dict
    truth: Any = None


@dataclass(frozen=True)
class _Dark:
    """A master dark and the id it is stored under."""

    dark_id: str
    master: Any  # processing.dark.MasterDark

    @property
    def temperature_c(self) -> float:
        return float(self.master.temperature_c)


@dataclass
class _RunStats:
    started_at: float = 0.0
    paused_s: float = 0.0
    paused_at: float | None = None
    blur_deg: list[float] = field(default_factory=list)
    passes: list[dict] = field(default_factory=list)


class Engine:
    """One session's capture run (see the module docstring)."""

    def __init__(
        self,
        rig: Rig,
        store: SessionStore,
        sweep: Sweep | None = None,
        *,
        policy: FaultPolicy | None = None,
        on_event: Callable[[EngineEvent], None] | None = None,
        qc: QcHook | None = None,
        process_depth: int = 4,
        store_depth: int = 4,
        store_workers: int = 2,
        speed_dps: float | None = None,
        max_blur_px: float | None = None,
        max_angle_error_deg: float | None = None,
        radius_px: float = 400.0,
        retry_skipped: bool = True,
        check_disk: bool = True,
        save_truth: bool = True,
        snap_timeout_s: float | None = None,
        processor_factory: Callable[..., Any] | None = None,
    ) -> None:
        self.rig = rig
        self.store = store
        self.sweep = sweep if sweep is not None else store.sweep
        if self.sweep.model_dump_json() != store.sweep.model_dump_json():
            raise UsageError(f"the sweep differs from the one session {store.session_id} was created with")
        self.policy = policy or FaultPolicy()
        self.qc = qc
        self.clock = rig.clock
        self.ops = RigOps(rig)
        self.bus = EventBus()
        if on_event is not None:
            self.bus.subscribe(on_event)
        self.events: list[CaptureEvent] = self.sweep.expand(rig.config)
        self._by_id = {e.event_id: e for e in self.events}
        self.speed_dps = speed_dps
        self.max_blur_px = max_blur_px
        self.max_angle_error_deg = max_angle_error_deg
        self.radius_px = radius_px
        self.check_disk = check_disk
        self.save_truth = save_truth and rig.simulated
        cam_timeout = rig.config.camera.timeout_s
        self.snap_timeout_s = cam_timeout if snap_timeout_s is None else snap_timeout_s
        self._processor_factory = processor_factory
        self._pipeline = Pipeline(self._process, self._store, process_depth=process_depth,
                                  store_depth=store_depth, store_workers=store_workers,
                                  name=f"engine-{store.session_id}")

        done = store.completed_event_ids() & set(self._by_id)
        skipped_before = store.skipped_event_ids() & set(self._by_id)
        self._done: set[str] = set(done)
        self._skipped: set[str] = set() if retry_skipped else set(skipped_before)
        self._done_before = len(done)
        self._inflight: dict[str, CaptureEvent] = {}
        self._requeue: list[CaptureEvent] = []
        self._cursor = 0
        self._pipe_failures: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)

        self._lock = threading.RLock()
        self._cond = threading.Condition(self._lock)
        self._state = S.IDLE
        self._pause_reason: str | None = None
        self._finishing = False
        self._error: BaseException | None = None
        self._error_text: str | None = None
        self._faults: list[FaultInfo] = []
        self._cur: dict[str, Any] = {}
        self._last_event: CaptureEvent | None = None
        self._efficiency: float | None = None
        self._thread: threading.Thread | None = None
        self._stats = _RunStats()
        self._darks: dict[str, _Dark] = {}
        self._dark_alias: dict[str, str] = {}  # planned dark id -> id of a retaken dark
        self._processors: dict[str | None, Any] = {}
        self._auto: dict[str, ExposureResult] = {}
        self._cam_setting: tuple[float, float] | None = None
        self._version = software_version()
        self._eta_basis: float | None = None
        self._eta_cache: tuple[int, float | None] = (-1, None)
        self._stored_this_run: set[str] = set()
        self._lower_bound_s: float | None = None
        self._ended_at: float | None = None
        self._attempt = 1

    # ------------------------------------------------------------------ public API
    @property
    def session_id(self) -> str:
        return self.store.session_id

    @property
    def state(self) -> RunState:
        with self._lock:
            return self._state

    def subscribe(self, callback: Callable[[EngineEvent], None]) -> Callable[[], None]:
        """Call ``callback(event)`` for every engine event (in the engine thread); returns unsubscribe."""
        return self.bus.subscribe(callback)

    def listen(self, maxsize: int = 1000) -> Listener:
        """A bounded queue of events for a consumer in another thread (e.g. an SSE stream)."""
        return self.bus.listen(maxsize)

    def pause(self) -> None:
        """Ask the run to park at the next safe boundary (lamps off, motion stopped)."""
        self._request(S.PAUSING, "pause", reason="operator")

    def resume(self) -> None:
        """Continue a paused run (also clears a suspension, e.g. after freeing disk space)."""
        self._request(S.RUNNING, "resume")

    clear = resume

    def abort(self) -> None:
        """End the run at the next safe boundary; the session is marked ``aborted``."""
        self._request(S.ABORTING, "abort", reason="operator")

    def start(self) -> threading.Thread:
        """Run in a daemon thread; follow it with :meth:`status`, events and :meth:`wait`.

        The engine is ``running`` when this returns, so pause/abort may follow at once.
        """
        with self._lock:
            self._set_state(S.RUNNING, "start")
            self._thread = threading.Thread(target=self._run_quietly, name=f"engine-{self.session_id}",
                                            daemon=True)
        self._thread.start()
        return self._thread

    def wait(self, timeout: float | None = None) -> EngineStatus:
        """Wait (real time) for a run started with :meth:`start`; returns the status then."""
        if self._thread is not None:
            self._thread.join(timeout)
        return self.status()

    def run(self) -> EngineStatus:
        """Run the session to the end in this thread.

        Returns the final status when the run completed or was aborted; raises
        :class:`SessionFailed` (with the original error as ``cause``) when it failed.
        A Ctrl-C aborts the run cleanly and is re-raised afterwards.
        """
        with self._lock:
            self._set_state(S.RUNNING, "run")
        return self._run_body()

    def _run_body(self) -> EngineStatus:
        interrupted: BaseException | None = None
        error: BaseException | None = None
        try:
            self._setup()
            self._main_loop()
        except _AbortRequested:
            pass
        except KeyboardInterrupt as exc:
            interrupted = exc
            with self._lock:
                if self._state is not S.ABORTING:
                    self._set_state(S.ABORTING, "interrupted")
        except BaseException as exc:
            error = exc
        final = self._teardown(error)
        if interrupted is not None:
            raise interrupted
        if final.state is S.FAILED:
            raise SessionFailed(final, self._error) from self._error
        return final

    def status(self) -> EngineStatus:
        with self._lock:
            total = len(self.events)
            done = len(self._done)
            skipped = len(self._skipped - self._done)
            progress = (done + skipped) / total if total else 1.0
            pose = self.ops.pose()
            return EngineStatus(
                state=self._state,
                session_id=self.session_id,
                done=done,
                total=total,
                skipped=skipped,
                progress=progress,
                eta_s=self._eta(),
                elapsed_s=self._elapsed(),
                lighting=self._cur.get("lighting"),
                elevation=self._cur.get("elevation"),
                tilt_deg=pose["tilt"],
                azimuth_deg=pose["turntable"],
                lamps_on=tuple(sorted(self.ops.lit)),
                last_frame_index=self._last_event.index if self._last_event else None,
                last_event_id=self._last_event.event_id if self._last_event else None,
                faults=tuple(self._faults[-STATUS_FAULTS:]),
                fault_count=len(self._faults),
                pause_reason=self._pause_reason if self._state in (S.PAUSING, S.PAUSED) else None,
                error=self._error_text,
                efficiency=self._efficiency,
                mode=self.sweep.mode,
            )

    def pipeline_stats(self) -> PipelineStats:
        return self._pipeline.stats()

    @classmethod
    def resume_session(cls, rig: Rig, root: str | Path, session_id: str, *, allow_rig_change: bool = False,
                       **kwargs: Any) -> Engine:
        """Reopen a session and build an engine that captures only what is not stored yet."""
        store = SessionStore.open(root, session_id, clock=rig.clock)
        if store.rig_digest != rig.config.digest and not allow_rig_change:
            store.close()
            raise UsageError(
                f"session {session_id} was captured with a different rig configuration "
                f"(digest {store.rig_digest[:12]}…, this rig {rig.config.digest[:12]}…); "
                "pass allow_rig_change to resume anyway"
            )
        return cls(rig, store, store.sweep, **kwargs)

    # ------------------------------------------------------------------ control internals
    def _request(self, target: RunState, action: str, reason: str | None = None) -> None:
        with self._lock:
            if self._state.terminal:
                raise IllegalTransition(self._state, target, action)
            if self._finishing and target is not S.ABORTING:
                raise IllegalTransition(self._state, target, f"{action} (the session is finishing)")
            if self._finishing:
                return  # abort while finishing: the run is already on its way out
            if target is S.RUNNING and self._state is not S.PAUSED:
                # IDLE -> RUNNING is run()'s transition, not resume()'s
                raise IllegalTransition(self._state, target, action)
            self._set_state(target, action, reason)
            if target is S.PAUSING:
                self._pause_reason = reason
            self._cond.notify_all()

    def _set_state(self, new: RunState, action: str, reason: str | None = None) -> None:
        """Caller holds the lock."""
        old = self._state
        check_transition(old, new, action)
        self._state = new
        self._publish(StateChanged, old=old, new=new, reason=reason)
        if new is S.RUNNING and old is S.IDLE:
            self._stats.started_at = self.clock.monotonic()

    def _publish(self, cls: type[EngineEvent], **fields: Any) -> None:
        ev = cls(seq=self.bus.next_seq(), time_s=self.clock.monotonic(), wall=self.clock.wall(), **fields)
        self.bus.publish(ev)

    def _run_quietly(self) -> None:
        try:
            self._run_body()
        except SessionFailed:
            pass  # kept in status().error and the SessionFinished event
        except BaseException:
            log.exception("engine thread for %s ended with an error", self.session_id)

    def _elapsed(self) -> float:
        st = self._stats
        if not st.started_at:
            return 0.0
        end = self._ended_at if self._ended_at is not None else self.clock.monotonic()
        paused = st.paused_s + ((end - st.paused_at) if st.paused_at is not None else 0.0)
        return max(0.0, end - st.started_at - paused)

    # ------------------------------------------------------------------ ETA
    def _remaining_events(self) -> list[CaptureEvent]:
        gone = self._done | self._skipped
        return [e for e in self.events if e.event_id not in gone]

    def _eta(self) -> float | None:
        if self._state.terminal:
            return 0.0 if self._state is S.COMPLETED else None
        n = len(self._done) + len(self._skipped)
        if self._eta_cache[0] == n:
            return self._eta_cache[1]
        rem = self._remaining_events()
        est = estimate(rem, self.rig.config).total_s if rem else 0.0
        if self._eta_basis is None:
            self._eta_basis = est
        ratio = 1.0
        planned_done = self._eta_basis - est
        elapsed = self._elapsed()
        if planned_done > 1.0 and elapsed > 0:
            ratio = min(3.0, max(0.5, elapsed / planned_done))
        eta = est * ratio
        self._eta_cache = (n, eta)
        return eta

    # ------------------------------------------------------------------ run phases
    def _setup(self) -> None:
        pending = [e for e in self.events if e.event_id not in self._done and e.event_id not in self._skipped]
        if self.check_disk and pending:
            total = estimate_session_bytes(self.sweep, self.rig.config)
            need = int(total * len(pending) / max(1, len(self.events)))
            check_free_space(self.store.path, need)
        self._restore_auto_exposure()
        self.rig.mount(self.sweep.satellite, self.sweep.build)
        with self._lock:
            self._eta_basis = None
            self._eta()
        self.store.set_state("running")
        self.store.record_event("run_started", {
            "pending": len(pending), "done_before": self._done_before, "mode": self.sweep.mode,
            "policy": self.policy.model_dump(mode="json"), "software_version": self._version,
            "rig_digest": self.rig.config.digest, "clock_s": self.clock.monotonic(),
        })
        self._pipeline.start()

    def _main_loop(self) -> None:
        while True:
            self._boundary()
            unit = self._next_unit()
            if unit:
                self._execute(unit)
                continue
            if self._pipeline.in_flight:
                self._pipeline.drain()
                continue
            with self._lock:
                if self._requeue or self._state is not S.RUNNING:
                    continue
                self._finishing = True
            self._handle_outcomes()  # nothing can be in flight; consume any last outcome
            if self._requeue:
                with self._lock:
                    self._finishing = False
                continue
            return

    def _teardown(self, error: BaseException | None) -> EngineStatus:
        """Safe state first, then the captured frames to disk, then the session record."""
        report = self.ops.make_safe()
        with contextlib.suppress(Exception):
            self.rig.camera.stop_stream()
        for exc in report.errors:
            self._note_fault(exc, "teardown", None)
        unsafe: str | None = None
        if not report.safe:
            last = "; ".join(str(e) for e in report.errors[-3:])
            unsafe = f"rig NOT in a safe state after teardown: {last}"
            log.error(unsafe)
            if error is not None:
                error.add_note(unsafe)
            else:
                error = RuntimeError(unsafe)
        # Frames already captured are worth keeping whatever ended the run.
        try:
            self._pipeline.drain(timeout=120)
            self._pipeline.stop()
            self._handle_outcomes(final=True)
        except BaseException as exc:  # a failing store must not hide the first error
            if error is None:
                error = exc
            else:
                error.add_note(f"while storing the last frames: {exc!r}")
        with self._lock:
            self._finishing = True
            self._ended_at = self.clock.monotonic()
            if error is not None:
                final = S.FAILED
                self._error = error
                self._error_text = f"{type(error).__name__}: {error}"
                if unsafe and unsafe not in self._error_text:
                    self._error_text += f" ({unsafe})"
            elif self._state is S.ABORTING:
                final = S.ABORTED
            else:
                final = S.COMPLETED
        self._efficiency = self._compute_efficiency() if final is S.COMPLETED else None
        summary = self._summary(final)
        try:
            self.store.record_event("run_finished", summary)
            if final is S.COMPLETED:
                self.store.complete("completed")
            else:
                self.store.set_state(final.value)
        except BaseException as exc:
            log.error("could not record the end of session %s: %s", self.session_id, exc)
            if final is not S.FAILED:
                final = S.FAILED
                self._error = exc
                self._error_text = f"{type(exc).__name__}: {exc}"
        with self._lock:
            self._set_state(final, "finish", reason=self._error_text)
            status = self.status()
        self._publish(SessionFinished, state=final, session_id=self.session_id, done=status.done,
                      total=status.total, skipped=status.skipped, duration_s=status.elapsed_s,
                      efficiency=self._efficiency, error=self._error_text)
        self.bus.close()
        return status

    def _compute_efficiency(self) -> float | None:
        """Plan lower bound / active duration (engine clock). For a resumed or gappy run the
        bound covers only the events stored in this run (stop-and-go model)."""
        elapsed = self._elapsed()
        if elapsed <= 0:
            return None
        if self._stored_this_run >= set(self._by_id):
            if self.sweep.mode == "continuous":
                lower = self._continuous_estimate().lower_bound_s
            else:
                lower = estimate(self.events, self.rig.config).lower_bound_s
        else:
            ran = [e for e in self.events if e.event_id in self._stored_this_run]
            lower = estimate(ran, self.rig.config).lower_bound_s
        self._lower_bound_s = lower
        return lower / elapsed

    def _summary(self, final: RunState) -> dict:
        st = self._pipeline.stats()
        out: dict[str, Any] = {
            "state": final.value,
            "duration_s": self._elapsed(),
            "done": len(self._done),
            "total": len(self.events),
            "skipped": sorted(self._skipped - self._done),
            "lower_bound_s": self._lower_bound_s,
            "efficiency": self._efficiency,
            "faults": len(self._faults),
            "error": self._error_text,
            "mode": self.sweep.mode,
            "pipeline": {
                "max_in_flight": st.max_in_flight, "bound": st.bound, "blocked_s": st.blocked_s,
                "blocked_count": st.blocked_count, "process_s": st.process_s, "store_s": st.store_s,
            },
        }
        if self._stats.blur_deg:
            out["blur_deg"] = {"mean": float(np.mean(self._stats.blur_deg)),
                               "max": float(np.max(self._stats.blur_deg))}
            out["passes"] = self._stats.passes
        if self._auto:
            out["auto_exposure"] = {c: r.exposure_s for c, r in self._auto.items()}
        qc_summary = getattr(self.qc, "summary", None)
        if callable(qc_summary):  # the QC hook keeps the distribution of its scores
            out["qc"] = qc_summary()
        return out

    # ------------------------------------------------------------------ scheduling
    def _next_unit(self) -> list[CaptureEvent]:
        with self._lock:
            if self._requeue:
                self._requeue.sort(key=lambda e: e.index)
                first = self._requeue.pop(0)
            else:
                first = None
                while self._cursor < len(self.events):
                    ev = self.events[self._cursor]
                    self._cursor += 1
                    if self._is_pending(ev):
                        first = ev
                        break
            if first is None:
                return []
            if self.sweep.mode != "continuous" or first.kind != "frame":
                return [first]
            # Continuous: the whole pass that this event belongs to, whatever is still to do.
            unit = [first]
            for ev in list(self._requeue):
                if ev.kind == "frame" and ev.pass_index == first.pass_index:
                    unit.append(ev)
                    self._requeue.remove(ev)
            while self._cursor < len(self.events):
                ev = self.events[self._cursor]
                if ev.kind != "frame" or ev.pass_index != first.pass_index:
                    break
                self._cursor += 1
                if self._is_pending(ev):
                    unit.append(ev)
            return sorted(unit, key=lambda e: e.index)

    def _is_pending(self, ev: CaptureEvent) -> bool:
        i = ev.event_id
        return i not in self._done and i not in self._skipped and i not in self._inflight

    # ------------------------------------------------------------------ boundaries
    def _boundary(self) -> None:
        self._handle_outcomes()
        with self._lock:
            state = self._state
        if state is S.ABORTING:
            raise _AbortRequested
        if state is S.PAUSING:
            self._park()

    def _stop_if_aborting(self) -> None:
        with self._lock:
            if self._state is S.ABORTING:
                raise _AbortRequested

    def _park(self, reason: str | None = None) -> None:
        """Go to ``paused`` (lamps off, motion stopped) and wait for resume or abort."""
        with self._lock:
            if self._state is S.RUNNING:
                self._set_state(S.PAUSING, "suspend", reason)
                self._pause_reason = reason
            elif self._state is S.ABORTING:
                raise _AbortRequested
        self._pipeline.drain()
        self._handle_outcomes(parking=True)
        report = self.ops.make_safe()
        for exc in report.errors:
            self._note_fault(exc, "teardown", None)
        if not report.safe:
            raise RuntimeError("cannot park the rig safely: " + "; ".join(str(e) for e in report.errors[-3:]))
        self._cam_setting = None
        with contextlib.suppress(Exception):
            self.store.set_state("paused")
        with self._lock:
            if self._state is S.PAUSING:
                self._set_state(S.PAUSED, "park", self._pause_reason)
                self._stats.paused_at = self.clock.monotonic()
            while self._state is S.PAUSED:
                self._cond.wait()
            if self._stats.paused_at is not None:
                self._stats.paused_s += self.clock.monotonic() - self._stats.paused_at
                self._stats.paused_at = None
            state = self._state
        if state is S.ABORTING:
            raise _AbortRequested
        self.ops.invalidate()
        with contextlib.suppress(Exception):
            self.store.set_state("running")
        self.store.record_event("resumed", {"clock_s": self.clock.monotonic()})

    # ------------------------------------------------------------------ faults
    def _note_fault(self, exc: BaseException, action: str, ev: CaptureEvent | None,
                    attempt: int = 1) -> FaultInfo:
        info = FaultInfo(
            time_s=self.clock.monotonic(), fault_class=fault_class_of(exc), action=action,
            message=f"{type(exc).__name__}: {exc}", event_id=ev.event_id if ev else None, attempt=attempt,
            device=getattr(exc, "device", None),
        )
        with self._lock:
            self._faults.append(info)
        log.warning("fault %s on %s (attempt %d): %s -> %s", info.fault_class, info.event_id, attempt,
                    info.message, action)
        self._publish(FaultRecorded, fault=info)
        try:
            self.store.record_event("fault", {
                "fault_class": info.fault_class, "action": action, "message": info.message,
                "event_id": info.event_id, "attempt": attempt, "device": info.device, "clock_s": info.time_s,
            })
        except Exception as rec_exc:  # e.g. a full disk: the fault is still in status and events
            log.error("could not journal fault: %s", rec_exc)
        return info

    def _execute(self, unit: list[CaptureEvent]) -> None:
        """Capture one unit (an event, or a continuous pass) under the fault policy."""
        failures: collections.Counter = collections.Counter()
        while True:
            todo = [e for e in unit if self._is_pending(e)]
            if not todo:
                return
            self._stop_if_aborting()
            try:
                self._attempt = sum(failures.values()) + 1
                self._capture(todo)
                # A pass cut short by a pause leaves marks to do: back in the queue.
                with self._lock:
                    self._requeue.extend(e for e in todo if self._is_pending(e) and e not in self._requeue)
                return
            except Exception as exc:
                err: Exception = exc
            # Faults: loop while the policy's recovery itself fails.
            while True:
                fc = fault_class_of(err)
                failures[fc] += 1
                decision = self.policy.decide(fc, failures[fc])
                action = decision.action
                if decision.retries:
                    action = ("home+" if decision.home else "") + action
                self._note_fault(err, action, todo[0], failures[fc])
                self._forget_after(err)
                with contextlib.suppress(Exception):
                    self.rig.camera.stop_stream()
                # An abort (e.g. an emergency stop that caused this very fault) wins over any
                # recovery: never re-home, move or relight after it was asked for.
                self._stop_if_aborting()
                if decision.retries:
                    try:
                        if decision.reconnect:
                            self.ops.reconnect(getattr(err, "device", None))
                        if decision.home:
                            self.ops.home(getattr(err, "device", None))
                        self.clock.sleep(decision.delay_s)
                    except Exception as rexc:
                        err = rexc
                        continue
                    break
                if decision.action == "skip":
                    for ev in todo:
                        self._skip(ev, err, fc)
                    return
                if decision.action == "suspend":
                    self._park(reason=f"{fc}: {err}")
                    failures.clear()
                    break
                raise err

    def _forget_after(self, err: BaseException) -> None:
        """After a fault, stop trusting what we know about the device that failed (all of
        them if it is not known): its state is re-commanded and re-verified next time."""
        roles = {r for r, _ in self.ops.devices_named(getattr(err, "device", None))}
        known = bool(roles)
        self.ops.invalidate(lamps=not known or "lights" in roles,
                            pose=not known or bool(roles & {"turntable", "tilt"}))
        self._cam_setting = None

    def _skip(self, ev: CaptureEvent, err: BaseException, fc: str) -> None:
        reason = f"{type(err).__name__}: {err}"
        self.store.record_skip(ev, reason, fc)
        with self._lock:
            self._skipped.add(ev.event_id)
        self._publish_progress()

    def _handle_outcomes(self, *, parking: bool = False, final: bool = False) -> None:
        """Consume the pipeline's results; a batch with a suspending fault parks once, after
        every outcome of the batch is accounted for (so none is acted on after a resume)."""
        suspend: str | None = None
        for o in self._pipeline.results():
            ev: CaptureEvent = o.key
            with self._lock:
                self._inflight.pop(ev.event_id, None)
            if o.ok:
                rec = o.result
                with self._lock:
                    self._done.add(ev.event_id)
                    self._stored_this_run.add(ev.event_id)
                    self._last_event = ev
                self._publish(
                    FrameStored, event_id=ev.event_id, index=ev.index, lighting=ev.lighting,
                    elevation=ev.elevation, azimuth_deg=ev.nominal_azimuth_deg,
                    exposure_s=rec.meta.get("exposure_s") if rec else None,
                    path=rec.files["raw"].path if rec and "raw" in rec.files else None,
                    qc_score=_qc_number(rec.meta.get("qc")) if rec else None,
                )
                self._publish_progress()
                continue
            err = o.error
            assert err is not None
            fc = fault_class_of(err)
            self._pipe_failures[ev.event_id][fc] += 1
            n = self._pipe_failures[ev.event_id][fc]
            decision = self.policy.decide(fc, n)
            self._note_fault(err, f"{decision.action} ({o.stage})", ev, n)
            if isinstance(err, (KeyboardInterrupt, SystemExit)):
                raise err
            if decision.action == "skip":
                self._skip(ev, err, fc)
            elif decision.action == "abort":
                raise err
            else:  # retry / reconnect / suspend: capture it again
                with self._lock:
                    self._requeue.append(ev)
                if decision.action == "suspend":
                    suspend = suspend or f"{fc}: {err}"
                elif decision.retries and decision.delay_s and not final:
                    self.clock.sleep(decision.delay_s)
        if suspend is not None and not parking and not final:
            self._park(reason=suspend)

    def _publish_progress(self) -> None:
        s = self.status()
        self._publish(Progress, done=s.done, total=s.total, skipped=s.skipped, progress=s.progress,
                      eta_s=s.eta_s, elapsed_s=s.elapsed_s)

    # ------------------------------------------------------------------ captures
    def _capture(self, todo: list[CaptureEvent]) -> None:
        first = todo[0]
        if first.kind == "dark":
            self._capture_dark(first)
        elif self.sweep.mode == "continuous":
            self._capture_pass(todo)
        else:
            self._capture_frame(first)

    def _set_condition(self, ev: CaptureEvent) -> None:
        assert ev.lighting is not None
        with self._lock:
            self._cur.update(lighting=ev.lighting, elevation=ev.elevation)
        self.ops.set_lamps(frozenset(self.rig.config.lamp_channels(ev.lighting)))

    def _configure(self, exposure_s: float, gain: float) -> None:
        if self._cam_setting != (exposure_s, gain):
            self.rig.camera.configure(exposure_s=exposure_s, gain=gain)
            self._cam_setting = (exposure_s, gain)

    def _snap(self, exposure_s: float) -> Any:
        return self.rig.camera.snap(timeout=exposure_s + self.snap_timeout_s)

    def _capture_frame(self, ev: CaptureEvent) -> None:
        assert ev.azimuth_deg is not None and ev.tilt_deg is not None
        self._set_condition(ev)
        moved = self.ops.move_pose(ev.azimuth_deg, ev.tilt_deg)
        self.ops.wait_ready(self.clock.monotonic() + self.ops.settle_s(moved, ev.settle_s))
        exposure, auto = self._exposure(ev)
        dark = self._dark_for(exposure, ev.gain)
        self._configure(exposure, ev.gain)
        t_clock, t_wall = self.clock.monotonic(), self.clock.wall()
        frame = self._snap(exposure)
        truth = self._truth()
        dark = self._check_dark_temperature(dark, exposure, ev.gain, frame.temperature_c)
        meta = self._frame_meta(ev, frame, exposure, dark, t_clock, t_wall)
        if auto is not None:
            meta["auto_exposure"] = auto.to_dict()
        self._submit(ev, frame.data, meta, dark, truth)

    def _submit(self, ev: CaptureEvent, data: np.ndarray, meta: dict, dark: Any, truth: Any) -> None:
        processor = self._processor(dark)
        with self._lock:
            self._inflight[ev.event_id] = ev
        self._pipeline.submit(ev, _Captured(data, meta, processor, truth))
        self._publish(Captured, event_id=ev.event_id, index=ev.index, lighting=ev.lighting,
                      elevation=ev.elevation, azimuth_deg=meta["pose"]["turntable_deg"],
                      tilt_deg=meta["pose"]["tilt_deg"], exposure_s=meta["exposure_s"])

    def _frame_meta(self, ev: CaptureEvent, frame: Any, exposure: float, dark: Any, t_clock: float,
                    t_wall: float) -> dict:
        pose = self.ops.pose()
        return {
            "exposure_s": float(frame.exposure_s or exposure),
            "planned_exposure_s": ev.exposure_s,
            "gain": float(frame.gain),
            "temperature_c": float(frame.temperature_c),
            "pose": {"turntable_deg": pose["turntable"], "tilt_deg": pose["tilt"]},
            "lamps_on": sorted(self.ops.lit),
            "lamp_names": self.ops.lamp_names(),
            "lamp_on_s": self.ops.lamp_ages(),
            "timestamp": t_wall,  # the engine clock's wall time (synthetic on a virtual clock)
            "host_wall": time.time(),  # the computer's own wall time, for provenance
            "clock_s": t_clock,
            "host_time_s": float(frame.host_time_s),
            "device_timestamp_s": float(frame.timestamp_s),
            "block_id": int(frame.block_id),
            "pixel_format": frame.pixel_format,
            "dark_id": dark.dark_id if dark is not None else None,
            "dark": dark.master.provenance() if dark is not None else None,
            "processing_method": self.sweep.processing,
            "software_version": self._version,
            "rig_digest": self.rig.config.digest,
            "mode": self.sweep.mode,
            "attempt": self._attempt,
            "simulated": bool(self.rig.simulated),
        }

    def _truth(self) -> Any:
        if not self.save_truth:
            return None
        src = self.rig.extras.get("frame_source")
        if src is None:
            return None
        t = src.truth()
        labels = getattr(t, "labels", None)
        if labels is None:
            return None
        return {"labels": np.array(labels, copy=True), "class_names": list(getattr(t, "class_names", [])),
                "azimuth_deg": float(getattr(t, "azimuth_deg", math.nan)),
                "tilt_deg": float(getattr(t, "tilt_deg", math.nan))}

    # ------------------------------------------------------------------ exposure and darks
    def _restore_auto_exposure(self) -> None:
        if not self.sweep.auto_exposure:
            return
        for rec in self.store.events():
            if rec.get("kind") == "auto_exposure":
                p = rec.get("payload") or {}
                try:
                    self._auto[p["lighting"]] = ExposureResult(
                        float(p["exposure_s"]), float(p["level_dn"]), int(p["frames"]),
                        tuple(tuple(h) for h in p.get("history", [])), bool(p["converged"]), p.get("limited"),
                    )
                except (KeyError, TypeError, ValueError):
                    log.warning("ignoring a malformed auto_exposure record: %r", p)

    def _exposure(self, ev: CaptureEvent) -> tuple[float, ExposureResult | None]:
        if not self.sweep.auto_exposure:
            return ev.exposure_s, None
        assert ev.lighting is not None
        res = self._auto.get(ev.lighting)
        if res is None:
            res = self._meter(ev)
            self._auto[ev.lighting] = res
            self.store.record_event("auto_exposure", {"lighting": ev.lighting, "event_id": ev.event_id,
                                                      **res.to_dict()})
        return res.exposure_s, res

    def _meter(self, ev: CaptureEvent) -> ExposureResult:
        ae = self.sweep.exposure
        model = self.rig.config.camera.model

        def measure(t: float) -> np.ndarray:
            t = round(t, 6)
            self._configure(t, ev.gain)
            return self._snap(t).data

        res = find_exposure(
            measure, full_scale=model.full_scale, start_s=ev.exposure_s, min_s=ae.min_s, max_s=ae.max_s,
            # aim a little under the limit and accept the first frame within ~8 % below it
            limit=ae.target_fraction, aim=ae.target_fraction * 0.967, accept_low=ae.target_fraction * 0.922,
            percentile=ae.percentile, max_frames=ae.max_iterations,
        )
        return ExposureResult(round(res.exposure_s, 6), res.level, res.frames, res.history, res.converged,
                              res.limited)

    def _dark_for(self, exposure_s: float, gain: float) -> _Dark | None:
        if self.sweep.dark.frames <= 0:
            return None
        did = dark_event_id(exposure_s, gain)
        did = self._dark_alias.get(did, did)
        if did in self._darks:
            return self._darks[did]
        rec = self.store.dark_for(exposure_s, gain)
        if rec is not None:
            return self._load_dark(rec)
        return self._capture_dark(dark_event(exposure_s, gain, self.sweep.dark.frames))

    def _load_dark(self, rec: Any) -> _Dark:
        from m2s2hil.processing.dark import MasterDark

        m = rec.meta
        # The store keeps masters as float32 TIFFs; ours are whole DN (rounded at build time).
        data = np.clip(np.rint(self.store.load_dark(rec.dark_id)), 0, 65535).astype(np.uint16)
        master = MasterDark(
            data=data, created=str(m.get("created", "")),
            camera_serial=str(m.get("camera_serial", "unknown")), n_frames=rec.n_frames,
            exposure_s=rec.exposure_s, gain=rec.gain, temperature_c=float(m.get("temperature_c", math.nan)),
            reduce=rec.reduce,
        )
        dark = self._darks[rec.dark_id] = _Dark(rec.dark_id, master)
        self._dark_alias[dark_event_id(rec.exposure_s, rec.gain)] = rec.dark_id
        return dark

    def _capture_dark(self, ev: CaptureEvent) -> _Dark:
        from m2s2hil.processing.dark import build_master_dark

        if ev.event_id in self.store.completed_event_ids():
            rec = next(d for d in self.store.darks() if d.dark_id == ev.event_id)
            return self._load_dark(rec)
        cam = self.rig.camera
        self.rig.cap_lens(True)
        self.ops.lens_capped = True
        try:
            self._configure(ev.exposure_s, ev.gain)
            frames = [self._snap(ev.exposure_s) for _ in range(ev.n_frames)]
        finally:
            self.rig.cap_lens(False)
            self.ops.lens_capped = False
        master = build_master_dark(
            [f.data for f in frames], reduce=self.sweep.dark.reduce, exposure_s=ev.exposure_s, gain=ev.gain,
            temperature_c=[f.temperature_c for f in frames], camera=getattr(cam, "serial", None) or cam.name,
            tolerance_c=self.rig.config.processing.dark_temperature_tolerance_c,
        )
        del frames
        meta = {**master.provenance(), "clock_s": self.clock.monotonic()}
        self.store.write_dark(ev, master.data, meta=meta)
        dark = self._darks[ev.event_id] = _Dark(ev.event_id, master)
        base = dark_event_id(ev.exposure_s, ev.gain)
        if ev.event_id != base:
            self._dark_alias[base] = ev.event_id
        if ev.event_id in self._by_id:  # a planned dark (not one taken for auto exposure or drift)
            with self._lock:
                self._done.add(ev.event_id)
                self._stored_this_run.add(ev.event_id)
                self._last_event = ev
            self._publish_progress()
        return dark

    def _check_dark_temperature(self, dark: _Dark | None, exposure_s: float, gain: float,
                                temperature_c: float) -> _Dark | None:
        if dark is None:
            return None
        tol = self.rig.config.processing.dark_temperature_tolerance_c
        if abs(dark.temperature_c - temperature_c) <= tol or math.isnan(dark.temperature_c):
            return dark
        base = dark_event_id(exposure_s, gain)
        n = sum(1 for d in self._darks if d.startswith(base))
        ev = dark_event(exposure_s, gain, self.sweep.dark.frames).model_copy(
            update={"event_id": f"{base}/t{n}"})
        log.info("sensor at %.1f °C, dark %s at %.1f °C: retaking", temperature_c, dark.dark_id,
                 dark.temperature_c)
        return self._capture_dark(ev)

    def _processor(self, dark: _Dark | None) -> Any:
        key = dark.dark_id if dark is not None else None
        proc = self._processors.get(key)
        if proc is None:
            factory = self._processor_factory
            if factory is None:
                from m2s2hil.processing.pipeline import FrameProcessor as factory
            kw: dict[str, Any] = {"dark": dark.master if dark is not None else None}
            if self.rig.calibration is not None:  # crosstalk, white reference, real layout
                kw["calibration"] = self.rig.calibration
            proc = factory(self.sweep.processing, self.rig.config.camera.model, **kw)
            self._processors[key] = proc
        return proc

    # ------------------------------------------------------------------ continuous mode
    def _capture_pass(self, todo: list[CaptureEvent]) -> None:
        first = todo[0]
        assert first.tilt_deg is not None and first.lighting is not None
        self._set_condition(first)
        moved = ["tilt"] if self.ops.move("tilt", first.tilt_deg) else []
        exposure, auto = self._exposure_for_pass(first)
        dark = self._dark_for(exposure, first.gain)
        speed = self._omega(first.lighting, exposure)
        self._configure(exposure, first.gain)
        blur = blur_estimate(speed, exposure, self.radius_px)
        marks: dict[float, list[CaptureEvent]] = {}
        for ev in todo:
            assert ev.azimuth_deg is not None
            marks.setdefault(ev.azimuth_deg, []).append(ev)

        def on_match(match: Any, frame_info: list[dict]) -> None:
            evs = sorted(match.key, key=lambda e: e.frame)
            for ev, frame, extra in zip(evs, match.frames, match.extras, strict=False):
                meta = self._frame_meta(ev, frame, exposure, dark, extra["clock_s"], extra["wall"])
                meta["pose"] = {"turntable_deg": extra["angle_deg"], "tilt_deg": self.ops.pose()["tilt"],
                                "turntable_source": "interpolated read-back at mid-exposure"}
                meta["continuous"] = {
                    "mark_deg": match.mark_deg, "angle_deg": extra["angle_deg"],
                    "error_deg": extra["angle_deg"] - match.mark_deg, "speed_dps": extra["speed_dps"],
                    "commanded_speed_dps": speed, **blur.to_dict(),
                }
                if auto is not None:
                    meta["auto_exposure"] = auto.to_dict()
                self._stats.blur_deg.append(blur.deg)
                self._submit(ev, frame.data, meta, dark, extra.get("truth"))

        def should_stop() -> bool:
            with self._lock:
                return self._state is not S.RUNNING

        self.ops.wait_ready(self.clock.monotonic() + self.ops.settle_s(moved, first.settle_s))
        report: PassReport = run_pass(
            self.rig, self.ops, marks=[(a, evs) for a, evs in marks.items()], speed_dps=speed,
            exposure_s=exposure, k=self.sweep.frames_per_pose, window_deg=self._match_window(speed, exposure),
            on_match=on_match, should_stop=should_stop, on_frame=self._continuous_extra,
            frame_timeout_s=exposure + self.snap_timeout_s,
        )
        info = {"pass_index": first.pass_index, "lighting": first.lighting, "elevation": first.elevation,
                "exposure_s": exposure, **report.to_dict(), **blur.to_dict()}
        self._stats.passes.append(info)
        self.store.record_event("continuous_pass", info)
        if report.stopped_early:
            return  # pause/abort: the boundary handles it; what is left stays pending
        missing = [ev for _, evs in report.missing for ev in evs]
        if missing:
            raise FrameIncomplete(
                f"no frame matched to {len(report.missing)} azimuth mark(s) "
                f"({', '.join(f'{a:g}' for a, _ in report.missing[:5])} deg); "
                f"{report.dropped} frame(s) dropped in the pass",
                device=getattr(self.rig.camera, "name", "camera"), command="continuous pass",
            )

    def _continuous_estimate(self) -> Any:
        """The plan's continuous model at this engine's blur limit (or speed override)."""
        blur = self.max_blur_px
        if self.speed_dps is not None:
            # ω = speed for the shortest exposure (exactly, when all conditions share it)
            t = min(self.sweep.exposure_for(c) for c in self.sweep.lighting)
            blur = self.radius_px * math.radians(self.speed_dps * t)
        return estimate_continuous(self.sweep, self.rig.config, radius_px=self.radius_px, max_blur_px=blur)

    def _omega(self, lighting: str, exposure_s: float) -> float:
        if self.speed_dps is not None:
            return self.speed_dps
        omega = self._continuous_estimate().omega_dps[lighting]
        if self.max_blur_px is not None:  # auto exposure may have changed t_exp
            omega = min(omega, math.degrees(self.max_blur_px / self.radius_px) / exposure_s)
        return omega

    def _match_window(self, speed: float, exposure_s: float) -> float:
        """Largest accepted |angle - mark|: 1.5 frame spacings (one dropped frame at a mark is
        tolerated, a longer gap makes the mark missing), unless set explicitly."""
        if self.max_angle_error_deg is not None:
            return self.max_angle_error_deg
        period = max(1.0 / self.rig.config.camera.model.max_fps, exposure_s)
        return min(self.sweep.azimuth_step_deg / 2, max(0.1, 1.5 * speed * period))

    def _continuous_extra(self, frame: Any) -> dict:
        return {"clock_s": self.clock.monotonic(), "wall": self.clock.wall(), "truth": self._truth()}

    def _exposure_for_pass(self, ev: CaptureEvent) -> tuple[float, ExposureResult | None]:
        if not self.sweep.auto_exposure or ev.lighting in self._auto:
            return self._exposure(ev)
        assert ev.azimuth_deg is not None
        self.ops.move("turntable", ev.azimuth_deg)  # meter at the pass's first mark
        self.ops.wait_ready(self.clock.monotonic())
        return self._exposure(ev)

    # ------------------------------------------------------------------ pipeline stages
    def _process(self, ev: CaptureEvent, cap: _Captured) -> _Processed:
        meta = dict(cap.meta)
        pf = cap.processor.process(cap.data)
        cube = np.array(pf.cube, copy=True)  # the processor may reuse its output buffers
        sat = getattr(pf, "saturated_mask", None)
        meta["saturated_fraction"] = float(np.mean(sat)) if sat is not None else None
        meta["processing_warnings"] = [str(w) for w in getattr(pf, "warnings", ())]
        calibration = (getattr(pf, "info", None) or {}).get("calibration")
        if calibration is not None:
            meta["calibration"] = calibration
        if self.qc is not None:
            try:
                meta["qc"] = _jsonable(self.qc(pf, ev, meta))
            except Exception as exc:  # a QC bug must not lose the frame; it is recorded
                log.exception("QC hook failed on %s", ev.event_id)
                meta["qc"] = None
                meta["qc_error"] = f"{type(exc).__name__}: {exc}"
        preview = _preview(cube, self.rig.config.camera.model.bands_nm)
        return _Processed(cap.data, cube, preview, meta, cap.truth)

    def _store(self, ev: CaptureEvent, p: _Processed) -> Any:
        if p.truth is None:
            return self.store.write_frame(ev, p.raw, p.cube, p.preview, p.meta)
        # Simulation: the label map is stored as the frame's "truth_labels" file (checksummed
        # and committed with it); the rest of the truth that is small goes into the metadata.
        meta = {**p.meta, "truth": {k: v for k, v in p.truth.items() if k != "labels"}}
        return self.store.write_frame(ev, p.raw, p.cube, p.preview, meta,
                                      extra={"truth_labels": p.truth["labels"]})


def interrupted_sessions(root: str | Path) -> list[str]:
    """Sessions under ``root`` that a restarted daemon should resume: their journal says they
    were running or paused when the process ended (oldest first)."""
    from m2s2hil.store import list_sessions

    found = [s for s in list_sessions(root) if s.state in ("running", "paused")]
    return [s.session_id for s in sorted(found, key=lambda s: s.created or 0.0)]


def _qc_number(v: Any) -> float | None:
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        return float(v)
    if isinstance(v, dict):
        s = v.get("score")
        return float(s) if isinstance(s, (int, float)) else None
    return None


def _jsonable(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    return v


def _preview(cube: np.ndarray | None, bands_nm: tuple[float, ...]) -> np.ndarray | None:
    """An 8-bit RGB preview from the bands nearest 650/550/470 nm, stretched to the 99.5th percentile."""
    if cube is None or cube.ndim != 3:
        return None
    nm = np.asarray(bands_nm)
    idx = [int(np.argmin(np.abs(nm - t))) for t in (650.0, 550.0, 470.0)]
    bands_first = cube.shape[0] == len(nm)
    rgb = np.stack([cube[i] if bands_first else cube[..., i] for i in idx], axis=-1).astype(np.float32)
    hi = float(np.percentile(rgb[::4, ::4], 99.5)) or 1.0
    return np.clip(rgb * (255.0 / hi), 0, 255).astype(np.uint8)


__all__ = ["Engine", "EngineStatus", "FaultPolicy", "RunState", "SessionFailed", "interrupted_sessions"]
