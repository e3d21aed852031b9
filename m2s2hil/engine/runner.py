"""The capture runner: runs a :class:`~m2s2hil.plan.Sweep` on a :class:`~m2s2hil.rig.opened.Rig`
into a :class:`~m2s2hil.store.session.SessionStore`, driving a
:class:`~m2s2hil.engine.steps.CaptureSteps` implementation (the shape of pymmcore-plus's
``MDARunner`` driving a ``PMDAEngine``). Build one with :func:`m2s2hil.engine.build.build_run`.

Use::

    engine = Engine(rig, store, sweep, options=EngineOptions(), policy=FaultPolicy(), qc=hook,
                    on_event=print)
    status = engine.run()            # blocking, in this thread; SessionFailed on failure
    # or
    engine.start()                   # in a daemon thread
    engine.pause(); engine.resume(); engine.abort()   # from any thread
    engine.status()                  # frozen EngineStatus snapshot
    unsubscribe = engine.subscribe(callback)          # typed events, in the engine thread
    listener = engine.listen()       # bounded queue of events for another thread (SSE)
    final = engine.wait()            # join the thread, final status

The runner owns: the run states and their transitions, pause/abort honoured at safe
boundaries, the fault policy, the pipeline (processing and storage threads behind bounded
queues, :mod:`m2s2hil.engine.pipeline`, stages in :mod:`m2s2hil.engine.frames`), events and
status, the safe state on every exit path. The steps own how a unit of events is captured:
:class:`~m2s2hil.engine.stop_and_go.StopAndGoSteps` or
:class:`~m2s2hil.engine.continuous_steps.ContinuousSteps` by the sweep's mode. Tuning is
:class:`~m2s2hil.engine.options.EngineOptions`.

Control: ``pause``/``abort`` are honoured at the next safe boundary (between units; in
continuous mode between frames, stopping the turntable); ``resume`` continues a
pause or a suspension. On a real rig the run also parks for the operator's lens cap before
darks and after them (pause reason ``lens_cap: ...``, :mod:`m2s2hil.engine.darks`);
``confirm_lens`` continues it, ``resume`` does not. Illegal requests (e.g. ``resume`` while
running, anything after the end) raise :class:`~m2s2hil.engine.state.IllegalTransition` (a
``UsageError``: HTTP 409).
Final states (decided in :meth:`Engine._final_state`): ``completed`` (every planned event
stored), ``completed_with_gaps`` (the rest skipped, each recorded), ``aborted``, ``failed``
(also when not one frame was stored).

Faults go through the :class:`~m2s2hil.engine.fault_policy.FaultPolicy`; every fault is recorded
(status, event bus, journal event ``fault``) and every capture given up is recorded with
``store.record_skip`` and its reason. Every exit path (completion, abort, failure, Ctrl-C,
even a failing teardown step) ends with lamps off and motion stopped
(:meth:`RigOps.make_safe`), and the original error is kept.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from m2s2hil.engine.continuous_steps import ContinuousSteps
from m2s2hil.engine.darks import Dark, LensCycled, SessionDarks, lens_reason
from m2s2hil.engine.exposure import CameraControl, ExposureMeter
from m2s2hil.engine.fault_policy import FaultPolicy, device_of, fault_class_of
from m2s2hil.engine.frames import CapturedFrame, FrameStages, QcHook, qc_number
from m2s2hil.engine.options import EngineOptions
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
from m2s2hil.engine.steps import CaptureKit, CaptureSteps, RunHooks
from m2s2hil.engine.stop_and_go import StopAndGoSteps
from m2s2hil.errors import M2S2Error, UsageError
from m2s2hil.plan import CaptureEvent, Sweep, estimate
from m2s2hil.rig.opened import Rig
from m2s2hil.rig.operations import RigOps
from m2s2hil.store.atomic import DiskFull, check_free_space
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


@runtime_checkable
class SummarisingQc(Protocol):
    """A QC hook that also keeps the distribution of its scores (for the run summary)."""

    def summary(self) -> dict[str, Any]: ...


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
        options: EngineOptions | None = None,
        policy: FaultPolicy | None = None,
        qc: QcHook | None = None,
        on_event: Callable[[EngineEvent], None] | None = None,
    ) -> None:
        self.rig = rig
        self.store = store
        self.sweep = sweep if sweep is not None else store.sweep
        if self.sweep.model_dump_json() != store.sweep.model_dump_json():
            raise UsageError(f"the sweep differs from the one session {store.session_id} was created with")
        self.options = opts = options or EngineOptions()
        self.policy = policy or FaultPolicy()
        self.qc = qc
        self.clock = rig.clock
        self.ops = RigOps(rig)
        self.bus = EventBus()
        if on_event is not None:
            self.bus.subscribe(on_event)
        self.events: list[CaptureEvent] = self.sweep.expand(rig.config)
        self._by_id = {e.event_id: e for e in self.events}
        self._version = software_version()
        self.steps = self._make_steps(opts, qc)
        self._pipeline = Pipeline(self._frames.process, self._frames.write, process_depth=opts.process_depth,
                                  store_depth=opts.store_depth, store_workers=opts.store_workers,
                                  name=f"engine-{store.session_id}")

        # Resume trusts nothing unchecked: a stored capture whose files are missing or damaged
        # is moved aside (kept, journalled) and captured again in this run.
        if not store.writable:
            raise UsageError(f"session {store.session_id} is open for reading; a run needs it open for "
                             "writing (SessionStore.open(..., mode='write'))")
        self.quarantined = store.check_stored() if store.completed_event_ids() else []
        done = store.completed_event_ids() & set(self._by_id)
        skipped_before = store.skipped_event_ids() & set(self._by_id)
        self._done: set[str] = set(done)
        self._skipped: set[str] = set() if opts.retry_skipped else set(skipped_before)
        self._done_before = len(done)
        self._inflight: dict[str, CaptureEvent] = {}
        self._requeue: list[CaptureEvent] = []
        self._cursor = 0
        self._pipe_failures: collections.defaultdict[str, collections.Counter[str]] = (
            collections.defaultdict(collections.Counter))

        self._lock = threading.RLock()
        self._cond = threading.Condition(self._lock)
        self._state = S.IDLE
        self._pause_reason: str | None = None
        self._lens_wait: bool | None = None  # parked for the operator to cap (True) / uncap the lens
        # The operator confirmed the cap on (a real rig's; see darks). A run resumed after one
        # that ended capped (e.g. parked for the uncap) asks for it off before any lit frame.
        self._lens_on = rig.lens_needs_operator and _last_lens_capped(store)
        self._finishing = False
        self._error: BaseException | None = None
        self._error_text: str | None = None
        self._faults: list[FaultInfo] = []
        self._cur: dict[str, str | None] = {}
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
        self.rig_safe: bool | None = None  # set by teardown: lamps off and motion stopped at the end

    # ------------------------------------------------------------------ public API
    @property
    def session_id(self) -> str:
        return self.store.session_id

    @property
    def alive(self) -> bool:
        """True while a run started with :meth:`start` is still going in its thread."""
        return self._thread is not None and self._thread.is_alive()

    @property
    def state(self) -> RunState:
        with self._lock:
            return self._state

    def _make_steps(self, opts: EngineOptions, qc: QcHook | None) -> CaptureSteps:
        """The steps of the sweep's mode, with the helpers they share (the runner keeps the
        frame stages: they are its pipeline's stages)."""
        rig, store, sweep = self.rig, self.store, self.sweep
        snap_timeout = rig.config.camera.timeout_s if opts.snap_timeout_s is None else opts.snap_timeout_s
        camera = CameraControl(rig, snap_timeout)
        hooks = RunHooks(submit=self._submit, dark_stored=self._dark_stored, condition=self._condition,
                         should_stop=lambda: self.state is not S.RUNNING)
        self._frames = FrameStages(rig, store, sweep, self.ops, qc=qc,
                                   save_truth=opts.save_truth and rig.simulated,
                                   processor_factory=opts.processor_factory)
        kit = CaptureKit(
            rig=rig, store=store, sweep=sweep, ops=self.ops, camera=camera,
            exposure=ExposureMeter(sweep, store, camera, rig.config.camera.model),
            darks=SessionDarks(rig, store, sweep, self.ops, camera, hooks.dark_stored, self._operator_lens),
            frames=self._frames, hooks=hooks,
        )
        if sweep.mode == "continuous":
            return ContinuousSteps(kit, opts.continuous)
        return StopAndGoSteps(kit)

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
        """Continue a paused run (also clears a suspension, e.g. after freeing disk space);
        not one waiting for the lens cap (that needs :meth:`confirm_lens`)."""
        with self._lock:
            if self._state is S.PAUSED and self._lens_wait is not None:
                raise IllegalTransition(self._state, S.RUNNING, f"resume ({self._pause_reason}; the "
                                        "operator confirms it with confirm_lens / POST /sessions/{id}/lens)")
            self._request(S.RUNNING, "resume")

    @property
    def lens_wait(self) -> bool | None:
        """While parked for the operator: True waiting for the lens cap on, False for it off."""
        with self._lock:
            return self._lens_wait if self._state is S.PAUSED else None

    def confirm_lens(self, capped: bool) -> None:
        """The operator says the lens cap is on (``capped``) or off: continues a run parked for
        exactly that (IllegalTransition otherwise). Trusted: a real rig cannot check it."""
        with self._lock:
            if self._state is not S.PAUSED or self._lens_wait is not capped:
                want = ("nothing" if self._state is not S.PAUSED or self._lens_wait is None
                        else f"the lens cap {'on' if self._lens_wait else 'off'}")
                what = f"confirm the lens cap {'on' if capped else 'off'} (waiting for {want})"
                raise IllegalTransition(self._state, S.RUNNING, what)
            self._lens_on = capped
            self._set_state(S.RUNNING, "lens confirmed")
            self._cond.notify_all()

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
        if self.options.check_disk and pending:
            total = estimate_session_bytes(self.sweep, self.rig.config)
            need = int(total * len(pending) / max(1, len(self.events)))
            while True:  # too little disk to start: paused and resumable (exit 3), not failed
                try:
                    check_free_space(self.store.path, need)
                    break
                except DiskFull as exc:
                    self._note_fault(exc, "suspend", None)
                    self._park(reason=f"disk_full: {exc}")
        self.steps.setup()  # restores what an earlier run learnt, mounts the scene (once per run)
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
        self.steps.teardown()
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
                self._error = error
                self._error_text = f"{type(error).__name__}: {error}"
                if unsafe and unsafe not in self._error_text:
                    self._error_text += f" ({unsafe})"
            final = self._final_state(error)
        ended = final in (S.COMPLETED, S.COMPLETED_WITH_GAPS)
        self._efficiency = self._compute_efficiency() if ended else None
        summary = self._summary(final)
        summary["rig_safe"] = report.safe  # the rig's outcome, apart from the data's (state)
        self.rig_safe = report.safe
        try:
            self.store.record_event("run_finished", summary)
            if ended:
                self.store.complete(final.value)
            else:
                self.store.manifest(final.value)  # what is stored, whatever ended the run
                self.store.set_state(final.value)
        except BaseException as exc:
            log.error("could not record the end of session %s: %s", self.session_id, exc)
            if final is not S.FAILED:
                final = S.FAILED
                self._error = exc
                self._error_text = f"{type(exc).__name__}: {exc}"
            with contextlib.suppress(Exception):  # e.g. a stored file failed the final check
                self.store.set_state(S.FAILED.value)
        with self._lock:
            self._set_state(final, "finish", reason=self._error_text)
            status = self.status()
        self._publish(SessionFinished, state=final, session_id=self.session_id, done=status.done,
                      total=status.total, skipped=status.skipped, duration_s=status.elapsed_s,
                      efficiency=self._efficiency, error=self._error_text)
        self.bus.close()
        return status

    def _final_state(self, error: BaseException | None) -> RunState:
        """The state a run ends in (caller holds the lock): ``failed`` on an error (including a
        rig left unsafe, or no frame stored at all), ``aborted`` when asked to,
        ``completed_with_gaps`` when planned events are missing (each skip recorded), else
        ``completed``."""
        if error is not None:
            return S.FAILED
        if self._state is S.ABORTING:
            return S.ABORTED
        frames = {e.event_id for e in self.events if e.kind == "frame"}
        if frames and not frames & self._done:  # every frame given up: nothing useful stored
            self._error_text = (f"no frame stored: all {len(frames)} planned frame(s) were skipped "
                                f"({len(self._faults)} fault(s); see the journal's skips)")
            self._error = RuntimeError(self._error_text)
            return S.FAILED
        if self._by_id.keys() - self._done:
            return S.COMPLETED_WITH_GAPS  # each gap recorded with its reason; a resume retries them
        return S.COMPLETED

    def _compute_efficiency(self) -> float | None:
        """Plan lower bound / active duration (engine clock). For a resumed or gappy run the
        bound covers only the events stored in this run (stop-and-go model)."""
        elapsed = self._elapsed()
        if elapsed <= 0 or not self._stored_this_run:  # e.g. a resumed run with nothing left to do
            return None
        if self._stored_this_run >= set(self._by_id):
            lower = self.steps.lower_bound_s()
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
        out.update(self.steps.summary())
        if self._lens_on:  # a real rig's run ended between the operator's cap and uncap
            log.warning("session %s ended with the lens cap on (as last confirmed)", self.session_id)
            out["lens_cap_on"] = True
        if isinstance(self.qc, SummarisingQc):  # the QC hook keeps the distribution of its scores
            out["qc"] = self.qc.summary()
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
            key = self.steps.unit_key(first)
            if key is None:
                return [first]
            # Events the steps capture together (a continuous pass): whatever is still to do of it.
            unit = [first]
            for ev in list(self._requeue):
                if self.steps.unit_key(ev) == key:
                    unit.append(ev)
                    self._requeue.remove(ev)
            while self._cursor < len(self.events):
                ev = self.events[self._cursor]
                if self.steps.unit_key(ev) != key:
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

    def _park(self, reason: str | None = None, lens: bool | None = None) -> None:
        """Go to ``paused`` (lamps off, motion stopped) and wait for resume or abort (or, with
        ``lens``, for :meth:`confirm_lens`)."""
        with self._lock:
            if self._state is S.RUNNING:
                self._set_state(S.PAUSING, "suspend", reason)
                self._pause_reason = reason
                self._lens_wait = lens
            elif self._state is S.ABORTING:
                raise _AbortRequested
        self._pipeline.drain()
        self._handle_outcomes(parking=True)
        report = self.ops.make_safe()
        for exc in report.errors:
            self._note_fault(exc, "teardown", None)
        if not report.safe:
            raise RuntimeError("cannot park the rig safely: " + "; ".join(str(e) for e in report.errors[-3:]))
        self.steps.forget()
        with contextlib.suppress(Exception):
            self.store.set_state("paused")
        with self._lock:
            if self._state is S.PAUSING:
                self._set_state(S.PAUSED, "park", self._pause_reason)
                self._stats.paused_at = self.clock.monotonic()
            while self._state is S.PAUSED:
                self._cond.wait()
            self._lens_wait = None
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

    def _operator_lens(self, capped: bool) -> None:
        """A real rig's lens cap: park until the operator confirms it on (``capped``) or off.
        A no-op when it is so already (for a simulated rig it is always off here)."""
        if self._lens_on is capped:
            return
        while self._lens_on is not capped:  # an operator's own pause first: then the lens
            self._park(reason=lens_reason(capped), lens=capped)
        self.store.record_event("lens", {"capped": capped, "confirmed_by": "operator",
                                         "clock_s": self.clock.monotonic()})

    # ------------------------------------------------------------------ faults
    def _note_fault(self, exc: BaseException, action: str, ev: CaptureEvent | None,
                    attempt: int = 1) -> FaultInfo:
        info = FaultInfo(
            time_s=self.clock.monotonic(), fault_class=fault_class_of(exc), action=action,
            message=f"{type(exc).__name__}: {exc}", event_id=ev.event_id if ev else None, attempt=attempt,
            device=device_of(exc),
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
        failures: collections.Counter[str] = collections.Counter()
        while True:
            todo = [e for e in unit if self._is_pending(e)]
            if not todo:
                return
            self._stop_if_aborting()
            try:
                if todo[0].kind != "dark":
                    self._operator_lens(False)  # a real rig's cap off (confirmed) before lit frames
                self._attempt = sum(failures.values()) + 1
                self.steps.execute(todo, self._attempt)
                # A pass cut short by a pause leaves marks to do: back in the queue.
                with self._lock:
                    self._requeue.extend(e for e in todo if self._is_pending(e) and e not in self._requeue)
                return
            except LensCycled:
                continue  # a dark taken mid-unit: the unit again, lamps and pose re-commanded
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
                # An abort (e.g. an emergency stop that caused this very fault) wins over any
                # recovery: never re-home, move or relight after it was asked for.
                self._stop_if_aborting()
                if decision.retries:
                    try:
                        if decision.reconnect:
                            self.ops.reconnect(device_of(err))
                        if decision.home:
                            self.ops.home(device_of(err))
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
        roles = self.ops.roles_named(device_of(err))
        known = bool(roles)
        self.ops.invalidate(lamps=not known or "lights" in roles,
                            pose=not known or bool(roles & {"turntable", "tilt"}))
        self.steps.recover()  # the camera's setting re-commanded, any stream stopped

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
    def _dark_stored(self, ev: CaptureEvent) -> None:
        if ev.event_id in self._by_id:  # a planned dark (not one taken for auto exposure or drift)
            with self._lock:
                self._done.add(ev.event_id)
                self._stored_this_run.add(ev.event_id)
                self._last_event = ev
            self._publish_progress()

    def _condition(self, ev: CaptureEvent) -> None:
        with self._lock:
            self._cur.update(lighting=ev.lighting, elevation=ev.elevation)

    def _submit(self, ev: CaptureEvent, data: np.ndarray, meta: dict[str, Any], dark: Dark | None,
                truth: Any) -> None:
        processor = self._frames.processor(dark)
        with self._lock:
            self._inflight[ev.event_id] = ev
        self._pipeline.submit(ev, CapturedFrame(data, meta, processor, truth))
        self._publish(Captured, event_id=ev.event_id, index=ev.index, lighting=ev.lighting,
                      elevation=ev.elevation, azimuth_deg=meta["pose"]["turntable_deg"],
                      tilt_deg=meta["pose"]["tilt_deg"], exposure_s=meta["exposure_s"])


def _last_lens_capped(store: SessionStore) -> bool:
    """The session's last lens confirmation (journal event ``lens``) said the cap was on."""
    last = [e for e in store.events() if e["kind"] == "lens"][-1:]
    return bool(last and last[0]["payload"].get("capped"))


def interrupted_sessions(root: str | Path) -> list[str]:
    """Sessions under ``root`` that a restarted daemon should resume: their journal says they
    were running or paused when the process ended (oldest first)."""
    from m2s2hil.store.session import list_sessions

    found = [s for s in list_sessions(root) if s.state in ("running", "paused")]
    return [s.session_id for s in sorted(found, key=lambda s: s.created or 0.0)]


__all__ = ["Engine", "EngineStatus", "FaultPolicy", "RunState", "SessionFailed", "interrupted_sessions"]
