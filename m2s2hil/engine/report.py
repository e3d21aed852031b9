"""What a run reports: its status snapshot, ETA, efficiency and end-of-run summary.

Time is the engine clock's (virtual in simulation); paused time does not count. The ETA is
the plan's estimate of what is left, scaled by how the run has kept to the plan so far
(between 0.5 and 3 times); the efficiency is the plan's lower bound over the active
duration, for the events this run stored (the steps' own bound when it stored them all).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

from m2s2hil.engine.frames import QcHook
from m2s2hil.engine.pipeline import Pipeline
from m2s2hil.engine.schedule import UnitSchedule
from m2s2hil.engine.state import EngineStatus, FaultInfo, RunState
from m2s2hil.engine.steps import CaptureSteps
from m2s2hil.plan import CaptureEvent, Sweep, estimate, physical_floor
from m2s2hil.rig.opened import Rig
from m2s2hil.rig.operations import RigOps

log = logging.getLogger(__name__)

STATUS_FAULTS = 50  # faults listed in a status snapshot (all are in the journal and the events)
S = RunState


@runtime_checkable
class SummarisingQc(Protocol):
    """A QC hook that also keeps the distribution of its scores (for the run summary)."""

    def summary(self) -> dict[str, Any]: ...


@dataclass
class RunClock:
    """The active time of a run on the engine clock."""

    started_at: float = 0.0
    paused_s: float = 0.0
    paused_at: float | None = None
    ended_at: float | None = None

    def elapsed(self, now: float) -> float:
        if not self.started_at:
            return 0.0
        end = self.ended_at if self.ended_at is not None else now
        paused = self.paused_s + ((end - self.paused_at) if self.paused_at is not None else 0.0)
        return max(0.0, end - self.started_at - paused)

    def pause(self, now: float) -> None:
        self.paused_at = now

    def unpause(self, now: float) -> None:
        if self.paused_at is not None:
            self.paused_s += now - self.paused_at
            self.paused_at = None


class RunReport:
    """Status, ETA, efficiency and summary of one run (read from any thread)."""

    def __init__(self, rig: Rig, sweep: Sweep, schedule: UnitSchedule, ops: RigOps, steps: CaptureSteps,
                 pipeline: Pipeline, qc: QcHook | None) -> None:
        self.rig = rig
        self.sweep = sweep
        self.schedule = schedule
        self.ops = ops
        self.steps = steps
        self.pipeline = pipeline
        self.qc = qc
        self.time = RunClock()
        self.condition: CaptureEvent | None = None  # lighting and elevation in front of the camera
        self.efficiency: float | None = None
        self.lower_bound_s: float | None = None
        #: The least rig time of any mode (m2s2hil.plan.floor) and the efficiency against it.
        self.physical_floor_s: float | None = None
        self.physical_efficiency: float | None = None
        self._eta_basis: float | None = None
        self._eta_cache: tuple[int, float | None] = (-1, None)

    def elapsed(self) -> float:
        return self.time.elapsed(self.rig.clock.monotonic())

    def restart_eta(self) -> None:
        """The plan's estimate of what is pending now is the ETA's basis."""
        self._eta_basis = None
        self._eta_cache = (-1, None)
        self.eta(S.RUNNING)

    def eta(self, state: RunState) -> float | None:
        if state.terminal:
            return 0.0 if state is S.COMPLETED else None
        n = self.schedule.settled_count
        if self._eta_cache[0] == n:
            return self._eta_cache[1]
        rem = self.schedule.remaining()
        est = estimate(rem, self.rig.config).total_s if rem else 0.0
        if self._eta_basis is None:
            self._eta_basis = est
        ratio = 1.0
        planned_done = self._eta_basis - est
        elapsed = self.elapsed()
        if planned_done > 1.0 and elapsed > 0:
            ratio = min(3.0, max(0.5, elapsed / planned_done))
        eta = est * ratio
        self._eta_cache = (n, eta)
        return eta

    def status(self, state: RunState, session_id: str, faults: list[FaultInfo], *, pause_reason: str | None,
               error: str | None) -> EngineStatus:
        sch = self.schedule
        total, done, skipped = sch.total, sch.done_count, sch.skipped_count
        pose = self.ops.pose()
        last, cond = sch.last_done, self.condition
        return EngineStatus(
            state=state, session_id=session_id, done=done, total=total, skipped=skipped,
            progress=(done + skipped) / total if total else 1.0,
            eta_s=self.eta(state), elapsed_s=self.elapsed(),
            lighting=cond.lighting if cond else None, elevation=cond.elevation if cond else None,
            tilt_deg=pose["tilt"], azimuth_deg=pose["turntable"], lamps_on=tuple(sorted(self.ops.lit)),
            last_frame_index=last.index if last else None, last_event_id=last.event_id if last else None,
            faults=tuple(faults[-STATUS_FAULTS:]), fault_count=len(faults),
            pause_reason=pause_reason if state in (S.PAUSING, S.PAUSED) else None,
            error=error, efficiency=self.efficiency, mode=self.sweep.mode,
        )

    def compute_efficiency(self) -> float | None:
        """Plan lower bound / active duration (engine clock). For a resumed or gappy run the
        bound covers only the events stored in this run (stop-and-go model)."""
        elapsed = self.elapsed()
        stored = self.schedule.stored_this_run
        if elapsed <= 0 or not stored:  # e.g. a resumed run with nothing left to do
            self.efficiency = None
            return None
        if stored >= set(self.schedule.by_id):
            lower = self.steps.lower_bound_s()
            floor = self.sweep.physical_floor(self.rig.config).total_s
        else:
            ran = [e for e in self.schedule.events if e.event_id in stored]
            overlap = getattr(self.steps, "overlap", False)
            lower = estimate(ran, self.rig.config, overlap=overlap).lower_bound_s
            floor = physical_floor(ran, self.rig.config).total_s
        self.lower_bound_s = lower
        self.efficiency = lower / elapsed
        self.physical_floor_s = floor
        self.physical_efficiency = floor / elapsed
        return self.efficiency

    def summary(self, final: RunState, *, faults: int, error: str | None, lens_on: bool,
                session_id: str) -> dict[str, Any]:
        st = self.pipeline.stats()
        out: dict[str, Any] = {
            "state": final.value,
            "duration_s": self.elapsed(),
            "done": self.schedule.done_count,
            "total": self.schedule.total,
            "skipped": sorted(self.schedule.skipped_ids()),
            "lower_bound_s": self.lower_bound_s,
            "efficiency": self.efficiency,
            "physical_floor_s": self.physical_floor_s,
            "physical_efficiency": self.physical_efficiency,
            "faults": faults,
            "error": error,
            "mode": self.sweep.mode,
            "pipeline": {
                "max_in_flight": st.max_in_flight, "bound": st.bound, "blocked_s": st.blocked_s,
                "blocked_count": st.blocked_count, "process_s": st.process_s, "store_s": st.store_s,
            },
        }
        out.update(self.steps.summary())
        if lens_on:  # a real rig's run ended between the operator's cap and uncap
            log.warning("session %s ended with the lens cap on (as last confirmed)", session_id)
            out["lens_cap_on"] = True
        if isinstance(self.qc, SummarisingQc):  # the QC hook keeps the distribution of its scores
            out["qc"] = self.qc.summary()
        return out


def final_state(*, failed: bool, aborting: bool, schedule: UnitSchedule,
                faults: int) -> tuple[RunState, str | None]:
    """The state a run ends in, and the error when it is ``failed`` for storing nothing:
    ``failed`` on an error (including a rig left unsafe, or no frame stored at all),
    ``aborted`` when asked to, ``completed_with_gaps`` when planned events are missing (each
    skip recorded), else ``completed``."""
    if failed:
        return S.FAILED, None
    if aborting:
        return S.ABORTED, None
    frames = {e.event_id for e in schedule.events if e.kind == "frame"}
    if frames and not frames & schedule.done_ids():  # every frame given up: nothing useful stored
        return S.FAILED, (f"no frame stored: all {len(frames)} planned frame(s) were skipped "
                          f"({faults} fault(s); see the journal's skips)")
    if schedule.missing_ids():
        return S.COMPLETED_WITH_GAPS, None  # each gap recorded with its reason; a resume retries them
    return S.COMPLETED, None
