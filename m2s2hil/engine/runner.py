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

The runner owns the run states and their transitions, pause/abort honoured at safe
boundaries, the pipeline (processing and storage threads behind bounded queues,
:mod:`m2s2hil.engine.pipeline`, stages in :mod:`m2s2hil.engine.frames`), events and the safe
state on every exit path. Its parts: which unit comes next (:mod:`m2s2hil.engine.schedule`),
the fault policy applied (:mod:`m2s2hil.engine.recovery`), status, ETA and summary
(:mod:`m2s2hil.engine.report`). The steps own how a unit of events is captured:
:class:`~m2s2hil.engine.stop_and_go.StopAndGoSteps` or
:class:`~m2s2hil.engine.continuous_steps.ContinuousSteps` by the sweep's mode; they yield
what they capture and need (:mod:`m2s2hil.engine.messages`) and the runner acts on it
between yields. Tuning is :class:`~m2s2hil.engine.options.EngineOptions`.

Control: ``pause``/``abort`` are honoured at the next safe boundary (between units; in
continuous mode between frames, stopping the turntable); ``resume`` continues a
pause or a suspension. On a real rig the run also parks for the operator's lens cap before
darks and after them (pause reason ``lens_cap: ...``, :mod:`m2s2hil.engine.darks`);
``confirm_lens`` continues it, ``resume`` does not. Illegal requests (e.g. ``resume`` while
running, anything after the end) raise :class:`~m2s2hil.engine.state.IllegalTransition` (a
``UsageError``: HTTP 409).
Final states (decided in :func:`~m2s2hil.engine.report.final_state`): ``completed`` (every planned event
stored), ``completed_with_gaps`` (the rest skipped, each recorded), ``aborted``, ``failed``
(also when not one frame was stored).

Faults, the steps' and the pipeline's alike, go through the
:class:`~m2s2hil.engine.fault_policy.FaultPolicy` in :meth:`Recovery.handle
<m2s2hil.engine.recovery.Recovery.handle>`; every fault is recorded (status, event bus,
journal event ``fault``) and every capture given up is recorded with ``store.record_skip``
and its reason. Every exit path (completion, abort, failure, Ctrl-C,
even a failing teardown step) ends with lamps off and motion stopped
(:meth:`RigOps.make_safe`), and the original error is kept.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from m2s2hil.atomic import DiskFull, check_free_space
from m2s2hil.engine.continuous_steps import ContinuousSteps
from m2s2hil.engine.control import RunControl
from m2s2hil.engine.darks import SessionDarks, lens_reason
from m2s2hil.engine.exposure import CameraControl, ExposureMeter
from m2s2hil.engine.fault_policy import FaultPolicy
from m2s2hil.engine.frame_flow import FrameFlow
from m2s2hil.engine.frames import FrameStages, QcHook
from m2s2hil.engine.messages import ConditionReached, DarkStored, FrameCaptured, LensRequest, StepGen
from m2s2hil.engine.options import EngineOptions
from m2s2hil.engine.pipeline import Pipeline, PipelineStats
from m2s2hil.engine.recovery import Recovery, Verdict
from m2s2hil.engine.report import RunReport, final_state
from m2s2hil.engine.schedule import UnitSchedule
from m2s2hil.engine.state import (
    EngineEvent,
    EngineStatus,
    EventBus,
    FaultRecorded,
    Listener,
    Progress,
    RunState,
    SessionFinished,
    StateChanged,
)
from m2s2hil.engine.steps import CaptureKit, CaptureSteps
from m2s2hil.engine.stop_and_go import StopAndGoSteps
from m2s2hil.errors import M2S2Error, UsageError
from m2s2hil.plan import CaptureEvent, Sweep
from m2s2hil.rig.opened import Rig
from m2s2hil.rig.operations import RigOps
from m2s2hil.store.estimates import estimate_session_bytes
from m2s2hil.store.folder import software_version
from m2s2hil.store.session import SessionStore

log = logging.getLogger(__name__)
S = RunState


class SessionFailed(M2S2Error):
    """The session ended in ``failed``; ``cause`` is the original error, ``status`` the final status."""

    def __init__(self, status: EngineStatus, cause: BaseException | None) -> None:
        self.status = status
        self.cause = cause
        super().__init__(f"session {status.session_id} failed: {status.error}")


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
        self._version = software_version()
        self._frames = FrameStages(rig, store, self.sweep, self.ops, qc=qc,
                                   save_truth=opts.save_truth and rig.simulated,
                                   processor_factory=opts.processor_factory)
        self.steps = make_steps(rig, store, self.sweep, self.ops, self._frames, opts)
        self._pipeline = Pipeline(self._frames.process, self._frames.write, process_depth=opts.process_depth,
                                  store_depth=opts.store_depth, store_workers=opts.store_workers,
                                  name=f"engine-{store.session_id}")

        # Resume trusts nothing unchecked: a stored capture whose files are missing or damaged
        # is moved aside (kept, journalled) and captured again in this run.
        if not store.writable:
            raise UsageError(f"session {store.session_id} is open for reading; a run needs it open for "
                             "writing (SessionStore.open(..., mode='write'))")
        self.quarantined = store.check_stored() if store.completed_event_ids() else []
        self.schedule = UnitSchedule(self.events, self.steps.unit_key, done=store.completed_event_ids(),
                                     skipped=() if opts.retry_skipped else store.skipped_event_ids())
        self._done_before = self.schedule.done_count

        self.report = RunReport(rig, self.sweep, self.schedule, self.ops, self.steps, self._pipeline, qc)
        # A run resumed after one that ended with the lens capped (e.g. parked for the uncap)
        # asks for it off before any lit frame.
        lens_on = rig.lens_needs_operator and _last_lens_capped(store)
        self.control = RunControl(
            lambda old, new, reason: self._publish(StateChanged, old=old, new=new, reason=reason),
            self.report.time, self.clock.monotonic, lens_on=lens_on)
        self._lock = self.control.lock
        self._error: BaseException | None = None
        self._error_text: str | None = None
        self._thread: threading.Thread | None = None
        self.recovery = Recovery(self.policy, rig, self.ops, self.steps, store, self.schedule,
                                 aborting=lambda: self.state is S.ABORTING,
                                 on_fault=lambda info: self._publish(FaultRecorded, fault=info))
        self.flow = FrameFlow(self._pipeline, self._frames, self.schedule, self.recovery, self._publish,
                              self._publish_progress)
        #: Set by teardown: the rig ended safe (lamps off, motion stopped), apart from the data's state.
        self.rig_safe: bool | None = None

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
            return self.control.state

    def subscribe(self, callback: Callable[[EngineEvent], None]) -> Callable[[], None]:
        """Call ``callback(event)`` for every engine event (in the engine thread); returns unsubscribe."""
        return self.bus.subscribe(callback)

    def listen(self, maxsize: int = 1000) -> Listener:
        """A bounded queue of events for a consumer in another thread (e.g. an SSE stream)."""
        return self.bus.listen(maxsize)

    def pause(self) -> None:
        """Ask the run to park at the next safe boundary (lamps off, motion stopped)."""
        self.control.request(S.PAUSING, "pause", reason="operator")

    def resume(self) -> None:
        """Continue a paused run (also clears a suspension, e.g. after freeing disk space);
        not one waiting for the lens cap (that needs :meth:`confirm_lens`)."""
        self.control.resume()

    @property
    def lens_wait(self) -> bool | None:
        """While parked for the operator: True waiting for the lens cap on, False for it off."""
        return self.control.waiting_for_lens()

    def confirm_lens(self, capped: bool) -> None:
        """The operator says the lens cap is on (``capped``) or off: continues a run parked for
        exactly that (IllegalTransition otherwise). Trusted: a real rig cannot check it."""
        self.control.confirm_lens(capped)

    def abort(self) -> None:
        """End the run at the next safe boundary; the session is marked ``aborted``."""
        self.control.request(S.ABORTING, "abort", reason="operator")

    def start(self) -> threading.Thread:
        """Run in a daemon thread; follow it with :meth:`status`, events and :meth:`wait`.

        The engine is ``running`` when this returns, so pause/abort may follow at once.
        """
        with self._lock:
            self.control.set_state(S.RUNNING, "start")
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
        self.control.set_state(S.RUNNING, "run")
        return self._run_body()

    def status(self) -> EngineStatus:
        c = self.control
        with self._lock:
            return self.report.status(c.state, self.session_id, self.recovery.faults,
                                      pause_reason=c.pause_reason, error=self._error_text)

    def pipeline_stats(self) -> PipelineStats:
        return self._pipeline.stats()

    # ------------------------------------------------------------------ control internals
    def _publish(self, cls: type[EngineEvent], **fields: Any) -> None:
        ev = cls(seq=self.bus.next_seq(), time_s=self.clock.monotonic(), wall=self.clock.wall(), **fields)
        self.bus.publish(ev)

    def _publish_progress(self) -> None:
        s = self.status()
        self._publish(Progress, done=s.done, total=s.total, skipped=s.skipped, progress=s.progress,
                      eta_s=s.eta_s, elapsed_s=s.elapsed_s)

    def _run_quietly(self) -> None:
        try:
            self._run_body()
        except SessionFailed:
            pass  # kept in status().error and the SessionFinished event
        except BaseException:
            log.exception("engine thread for %s ended with an error", self.session_id)

    # ------------------------------------------------------------------ run phases
    def _run_body(self) -> EngineStatus:
        interrupted: BaseException | None = None
        error: BaseException | None = None
        try:
            if self._setup():
                self._main_loop()
        except KeyboardInterrupt as exc:
            interrupted = exc
            with self._lock:
                if self.control.state is not S.ABORTING:
                    self.control.set_state(S.ABORTING, "interrupted")
        except BaseException as exc:
            error = exc
        final = self._teardown(error)
        if interrupted is not None:
            raise interrupted
        if final.state is S.FAILED:
            raise SessionFailed(final, self._error) from self._error
        return final

    def _setup(self) -> bool:
        """Disk space checked, the steps set up, the run journalled; False when aborted meanwhile."""
        pending = self.schedule.remaining()
        if self.options.check_disk and pending:
            total = estimate_session_bytes(self.sweep, self.rig.config)
            need = int(total * len(pending) / max(1, len(self.events)))
            while True:  # too little disk to start: paused and resumable (exit 3), not failed
                try:
                    check_free_space(self.store.path, need)
                    break
                except DiskFull as exc:
                    self.recovery.note(exc, "suspend", None)
                    if not self._park(reason=f"disk_full: {exc}"):
                        return False
        self.steps.setup()  # restores what an earlier run learnt, mounts the scene (once per run)
        with self._lock:
            self.report.restart_eta()
        self.store.set_state("running")
        self.store.record_event("run_started", {
            "pending": len(pending), "done_before": self._done_before, "mode": self.sweep.mode,
            "policy": self.policy.model_dump(mode="json"), "software_version": self._version,
            "rig_digest": self.rig.config.digest, "clock_s": self.clock.monotonic(),
        })
        self._pipeline.start()
        return True

    def _main_loop(self) -> None:
        while self._boundary():
            unit = self.schedule.next_unit()
            if unit:
                if not self._execute(unit):
                    return
                continue
            if self._pipeline.in_flight:
                self._pipeline.drain()
                continue
            with self._lock:
                if self.schedule.has_requeued or self.control.state is not S.RUNNING:
                    continue
                self.control.finishing = True
            if not self._handle_outcomes():  # nothing can be in flight; consume any last outcome
                return
            if not self.schedule.has_requeued:
                return
            with self._lock:
                self.control.finishing = False

    def _boundary(self) -> bool:
        """Between units: outcomes consumed, a pause parked; False once the run is to end."""
        if not self._handle_outcomes():
            return False
        state = self.state
        if state is S.PAUSING:
            return self._park()
        return state is not S.ABORTING

    def _park(self, reason: str | None = None, lens: bool | None = None) -> bool:
        """Go to ``paused`` (lamps off, motion stopped) and wait for resume or abort (or, with
        ``lens``, for :meth:`confirm_lens`); False when the run is to end (aborted)."""
        if not self.control.begin_park(reason, lens):
            return False
        self._pipeline.drain()
        self._handle_outcomes(parking=True)
        report = self.ops.make_safe()
        for exc in report.errors:
            self.recovery.note(exc, "teardown", None)
        if not report.safe:
            raise RuntimeError("cannot park the rig safely: " + "; ".join(str(e) for e in report.errors[-3:]))
        self.steps.forget()
        with contextlib.suppress(Exception):
            self.store.set_state("paused")
        if not self.control.parked():
            return False
        self.ops.invalidate()
        with contextlib.suppress(Exception):
            self.store.set_state("running")
        self.store.record_event("resumed", {"clock_s": self.clock.monotonic()})
        return True

    def _operator_lens(self, capped: bool) -> bool:
        """A real rig's lens cap: park until the operator confirms it on (``capped``) or off
        (a no-op when it is so already: for a simulated rig it is always off here). False
        when the run is to end."""
        if self.control.lens_on is capped:
            return True
        while self.control.lens_on is not capped:  # an operator's own pause first: then the lens
            if not self._park(reason=lens_reason(capped), lens=capped):
                return False
        self.store.record_event("lens", {"capped": capped, "confirmed_by": "operator",
                                         "clock_s": self.clock.monotonic()})
        return True

    # ------------------------------------------------------------------ units and their messages
    def _execute(self, unit: list[CaptureEvent]) -> bool:
        """Capture one unit (an event, or a continuous pass) under the fault policy; False
        when the run is to end (an abort)."""
        failures: collections.Counter[str] = collections.Counter()
        while True:
            todo = self.schedule.pending_of(unit)
            if not todo:
                return True
            if self.state is S.ABORTING:
                return False
            try:
                if not self._drive(self.steps.execute(todo, sum(failures.values()) + 1)):
                    return False
                self.schedule.requeue(todo)  # a pass cut short by a pause: what is left, again
                return True
            except Exception as exc:
                res = self.recovery.handle(exc, todo, failures)
            if res.verdict is Verdict.RETRY:
                continue
            if res.verdict is Verdict.SKIPPED:
                self._publish_progress()
                return True
            if res.verdict is Verdict.STOPPED:
                return False
            if res.verdict is Verdict.SUSPEND:
                if not self._park(reason=res.reason):
                    return False
                failures.clear()
                continue
            raise res.error

    def _drive(self, steps: StepGen[None]) -> bool:
        """Act on a unit's messages (:mod:`m2s2hil.engine.messages`), answering each with
        whether a pause or abort is pending; False when an abort came while parked for the
        lens (the steps are closed: a pass stops its rotation and stream)."""
        reply: bool | None = None
        with contextlib.closing(steps):
            while True:
                try:
                    msg = steps.send(reply)
                except StopIteration:
                    return True
                if isinstance(msg, FrameCaptured):
                    self.flow.submit(msg)
                elif isinstance(msg, DarkStored):
                    if self.schedule.mark_done(msg.event):  # a planned dark (not one for auto exposure)
                        self._publish_progress()
                elif isinstance(msg, ConditionReached):
                    with self._lock:
                        self.report.condition = msg.event
                elif isinstance(msg, LensRequest) and not self._operator_lens(msg.capped):
                    return False
                reply = self.state is not S.RUNNING

    def _handle_outcomes(self, *, parking: bool = False, final: bool = False) -> bool:
        """Consume the pipeline's results; a batch with a suspending fault parks once, after
        every outcome of the batch is accounted for (so none is acted on after a resume).
        False when that parking ended in an abort."""
        suspend = self.flow.collect(final=final)
        return suspend is None or parking or final or self._park(reason=suspend)

    # ------------------------------------------------------------------ the end
    def _teardown(self, error: BaseException | None) -> EngineStatus:
        """Safe state first, then the captured frames to disk, then the session record."""
        report = self.ops.make_safe()
        self.steps.teardown()
        for exc in report.errors:
            self.recovery.note(exc, "teardown", None)
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
            self.control.finishing = True
            self.report.time.ended_at = self.clock.monotonic()
            if error is not None:
                self._error = error
                self._error_text = f"{type(error).__name__}: {error}"
                if unsafe and unsafe not in self._error_text:
                    self._error_text += f" ({unsafe})"
            final, nothing = final_state(failed=error is not None, aborting=self.control.state is S.ABORTING,
                                         schedule=self.schedule, faults=len(self.recovery.faults))
            if nothing is not None:
                self._error_text = nothing
                self._error = RuntimeError(nothing)
        if final in (S.COMPLETED, S.COMPLETED_WITH_GAPS):
            self.report.compute_efficiency()
        summary = self.report.summary(final, faults=len(self.recovery.faults), error=self._error_text,
                                      lens_on=self.control.lens_on, session_id=self.session_id)
        summary["rig_safe"] = report.safe  # the rig's outcome, apart from the data's (state)
        self.rig_safe = report.safe
        failure = _record_end(self.store, final, summary)
        if failure is not None and final is not S.FAILED:
            final = S.FAILED
            self._error = failure
            self._error_text = f"{type(failure).__name__}: {failure}"
        with self._lock:
            self.control.set_state(final, "finish", reason=self._error_text)
            status = self.status()
        self._publish(SessionFinished, state=final, session_id=self.session_id, done=status.done,
                      total=status.total, skipped=status.skipped, duration_s=status.elapsed_s,
                      efficiency=self.report.efficiency, error=self._error_text)
        self.bus.close()
        return status


def make_steps(rig: Rig, store: SessionStore, sweep: Sweep, ops: RigOps, frames: FrameStages,
           opts: EngineOptions) -> CaptureSteps:
    """The steps of the sweep's mode, with the helpers they share (the runner keeps the
    frame stages: they are its pipeline's stages)."""
    snap_timeout = rig.config.camera.timeout_s if opts.snap_timeout_s is None else opts.snap_timeout_s
    camera = CameraControl(rig, snap_timeout)
    kit = CaptureKit(
        rig=rig, store=store, sweep=sweep, ops=ops, camera=camera,
        exposure=ExposureMeter(sweep, store, camera, rig.config.camera.model),
        darks=SessionDarks(rig, store, sweep, ops, camera), frames=frames,
    )
    if sweep.mode == "continuous":
        return ContinuousSteps(kit, opts.continuous)
    return StopAndGoSteps(kit, overlap=opts.overlap)


def _record_end(store: SessionStore, final: RunState, summary: dict[str, Any]) -> BaseException | None:
    """The end of the run in the session: its summary, then complete (manifest, final checks)
    or just the manifest of what is stored; the error if that failed (the session is then
    marked failed)."""
    try:
        store.record_event("run_finished", summary)
        if final in (S.COMPLETED, S.COMPLETED_WITH_GAPS):
            store.complete(final.value)
        else:
            store.manifest(final.value)  # what is stored, whatever ended the run
            store.set_state(final.value)
    except BaseException as exc:
        log.error("could not record the end of session %s: %s", store.session_id, exc)
        with contextlib.suppress(Exception):  # e.g. a stored file failed the final check
            store.set_state(S.FAILED.value)
        return exc
    return None


def _last_lens_capped(store: SessionStore) -> bool:
    """The session's last lens confirmation (journal event ``lens``) said the cap was on."""
    last = [e for e in store.events() if e["kind"] == "lens"][-1:]
    return bool(last and last[0]["payload"].get("capped"))


def interrupted_sessions(root: str | Path) -> list[str]:
    """Sessions under ``root`` that a restarted daemon should resume: their journal says they
    were running or paused when the process ended (oldest first)."""
    from m2s2hil.store.catalogue import list_sessions

    found = [s for s in list_sessions(root) if s.state in ("running", "paused")]
    return [s.session_id for s in sorted(found, key=lambda s: s.created or 0.0)]


__all__ = ["Engine", "EngineStatus", "FaultPolicy", "RunState", "SessionFailed", "interrupted_sessions"]
