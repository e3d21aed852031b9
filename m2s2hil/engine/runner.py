"""The capture engine: runs a :class:`~m2s2hil.plan.Sweep` on a :class:`~m2s2hil.rig.opened.Rig`
into a :class:`~m2s2hil.store.session.SessionStore`.

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

Constructor options: ``policy`` (:class:`~m2s2hil.engine.fault_policy.FaultPolicy`), ``on_event``
(a subscriber from the start), ``qc`` (the capture-time QC hook, see
:mod:`m2s2hil.engine.frames`), ``process_depth``/``store_depth`` (queue bounds),
``store_workers`` (parallel writers), continuous mode (:mod:`m2s2hil.engine.continuous_steps`):
``speed_dps`` (override) or ``max_blur_px`` (ω limited so ω·t_exp stays under it at
``radius_px`` from the axis; default: the plan's ω), ``max_angle_error_deg``;
``retry_skipped`` (a resumed run retries earlier gaps), ``check_disk``, ``save_truth``,
``snap_timeout_s``, ``processor_factory``.

Control: ``pause``/``abort`` are honoured at the next safe boundary (between captures; in
continuous mode between frames, stopping the turntable); ``resume``/``clear`` continue a
pause or a suspension. Illegal requests (e.g. ``resume`` while running, anything after the
end) raise :class:`~m2s2hil.engine.state.IllegalTransition` (a ``UsageError``: HTTP 409).
Final states: ``completed`` (gaps allowed, each recorded), ``aborted``, ``failed``.

What a run does, in the plan's order (``sweep.expand(rig.config)``):

- *dark* events: master darks (:mod:`m2s2hil.engine.darks`: capture, reuse, retake on
  temperature drift).
- *frame* events, stop-and-go: lamps of the condition on (only when they change), tilt then
  turntable moved and verified against the read-back within the axis tolerance, settle and
  lamp warm-up waited (the warm-up overlaps the move), the exposure
  (:mod:`m2s2hil.engine.exposure`: automatic once per lighting condition when the sweep
  asks for it), one snap, then the frame goes down the pipeline.
- continuous mode: one pass per lighting and tilt (:mod:`m2s2hil.engine.continuous_steps`).
- pipeline (:mod:`m2s2hil.engine.pipeline`): processing and storage (:mod:`m2s2hil.engine.frames`,
  which also lists the frame metadata) run in their own threads behind bounded queues;
  results come back to the engine thread at safe boundaries.

Faults go through the :class:`~m2s2hil.engine.fault_policy.FaultPolicy`; every fault is recorded
(status, event bus, journal event ``fault``) and every capture given up is recorded with
``store.record_skip`` and its reason. Pause and abort are honoured between captures. Every
exit path (completion, abort, failure, Ctrl-C, even a failing teardown step) ends with lamps
off and motion stopped (:meth:`RigOps.make_safe`), and the original error is kept.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from m2s2hil.engine.continuous_steps import PassCapture, SpeedSettings
from m2s2hil.engine.darks import Dark, SessionDarks
from m2s2hil.engine.exposure import AutoExposure, CameraControl
from m2s2hil.engine.fault_policy import FaultPolicy, fault_class_of
from m2s2hil.engine.frames import CapturedFrame, FrameStages, QcHook, qc_number
from m2s2hil.engine.pipeline import Pipeline, PipelineStats
from m2s2hil.engine.state import (
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
from m2s2hil.plan import CaptureEvent, Sweep, estimate
from m2s2hil.rig.opened import Rig
from m2s2hil.rig.operations import RigOps
from m2s2hil.store.atomic import check_free_space
from m2s2hil.store.session import SessionStore, estimate_session_bytes, software_version

log = logging.getLogger(__name__)

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
class _RunStats:
    started_at: float = 0.0
    paused_s: float = 0.0
    paused_at: float | None = None


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
        self._version = software_version()
        # The helpers that hold the capture logic; each gets what it needs, nothing more.
        cam_timeout = rig.config.camera.timeout_s
        self._camera = CameraControl(rig, cam_timeout if snap_timeout_s is None else snap_timeout_s)
        self._exposure = AutoExposure(self.sweep, store, self._camera, rig.config.camera.model)
        self._darks = SessionDarks(rig, store, self.sweep, self.ops, self._camera, self._dark_stored)
        self._frames = FrameStages(rig, store, self.sweep, self.ops, qc=qc,
                                   save_truth=save_truth and rig.simulated,
                                   processor_factory=processor_factory, version=self._version)
        self._passes = PassCapture(rig, store, self.sweep, self.ops, camera=self._camera,
                                   exposure=self._exposure, darks=self._darks, frames=self._frames,
                                   set_condition=self._set_condition, submit=self._submit,
                                   should_stop=lambda: self.state is not S.RUNNING)
        self._pipeline = Pipeline(self._frames.process, self._frames.write, process_depth=process_depth,
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

    # Options held by the helpers that use them (one copy, still settable here).
    @property
    def qc(self) -> QcHook | None:
        return self._frames.qc

    @qc.setter
    def qc(self, hook: QcHook | None) -> None:
        self._frames.qc = hook

    @property
    def save_truth(self) -> bool:
        return self._frames.save_truth

    @save_truth.setter
    def save_truth(self, on: bool) -> None:
        self._frames.save_truth = on

    @property
    def snap_timeout_s(self) -> float:
        return self._camera.snap_timeout_s

    @snap_timeout_s.setter
    def snap_timeout_s(self, seconds: float) -> None:
        self._camera.snap_timeout_s = seconds

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
        self._exposure.restore()
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
                lower = self._speed_settings().estimate(self.sweep, self.rig.config).lower_bound_s
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
        if self._passes.blur_deg:
            out["blur_deg"] = {"mean": float(np.mean(self._passes.blur_deg)),
                               "max": float(np.max(self._passes.blur_deg))}
            out["passes"] = self._passes.passes
        if self._exposure.results:
            out["auto_exposure"] = {c: r.exposure_s for c, r in self._exposure.results.items()}
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
        self._camera.forget()
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
        self._camera.forget()

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
                    qc_score=qc_number(rec.meta.get("qc")) if rec else None,
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
            self._darks.capture(first)
        elif self.sweep.mode == "continuous":
            self._passes.capture(todo, self._speed_settings(), self._attempt)
        else:
            self._capture_frame(first)

    def _dark_stored(self, ev: CaptureEvent) -> None:
        if ev.event_id in self._by_id:  # a planned dark (not one taken for auto exposure or drift)
            with self._lock:
                self._done.add(ev.event_id)
                self._stored_this_run.add(ev.event_id)
                self._last_event = ev
            self._publish_progress()

    def _speed_settings(self) -> SpeedSettings:
        return SpeedSettings(self.speed_dps, self.max_blur_px, self.max_angle_error_deg, self.radius_px)

    def _set_condition(self, ev: CaptureEvent) -> None:
        assert ev.lighting is not None
        with self._lock:
            self._cur.update(lighting=ev.lighting, elevation=ev.elevation)
        self.ops.set_lamps(frozenset(self.rig.config.lamp_channels(ev.lighting)))

    def _capture_frame(self, ev: CaptureEvent) -> None:
        assert ev.azimuth_deg is not None and ev.tilt_deg is not None
        self._set_condition(ev)
        moved = self.ops.move_pose(ev.azimuth_deg, ev.tilt_deg)
        self.ops.wait_ready(self.clock.monotonic() + self.ops.settle_s(moved, ev.settle_s))
        exposure, auto = self._exposure.exposure(ev)
        dark = self._darks.for_setting(exposure, ev.gain)
        self._camera.configure(exposure, ev.gain)
        t_clock, t_wall = self.clock.monotonic(), self.clock.wall()
        frame = self._camera.snap(exposure)
        truth = self._frames.truth()
        dark = self._darks.check_temperature(dark, exposure, ev.gain, frame.temperature_c)
        meta = self._frames.meta(ev, frame, exposure, dark, t_clock, t_wall, self._attempt)
        if auto is not None:
            meta["auto_exposure"] = auto.to_dict()
        self._submit(ev, frame.data, meta, dark, truth)

    def _submit(self, ev: CaptureEvent, data: np.ndarray, meta: dict, dark: Dark | None, truth: Any) -> None:
        processor = self._frames.processor(dark)
        with self._lock:
            self._inflight[ev.event_id] = ev
        self._pipeline.submit(ev, CapturedFrame(data, meta, processor, truth))
        self._publish(Captured, event_id=ev.event_id, index=ev.index, lighting=ev.lighting,
                      elevation=ev.elevation, azimuth_deg=meta["pose"]["turntable_deg"],
                      tilt_deg=meta["pose"]["tilt_deg"], exposure_s=meta["exposure_s"])


def interrupted_sessions(root: str | Path) -> list[str]:
    """Sessions under ``root`` that a restarted daemon should resume: their journal says they
    were running or paused when the process ended (oldest first)."""
    from m2s2hil.store.session import list_sessions

    found = [s for s in list_sessions(root) if s.state in ("running", "paused")]
    return [s.session_id for s in sorted(found, key=lambda s: s.created or 0.0)]


__all__ = ["Engine", "EngineStatus", "FaultPolicy", "RunState", "SessionFailed", "interrupted_sessions"]
