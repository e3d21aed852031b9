"""The fault policy applied: one place for the faults of the steps and of the pipeline.

:meth:`Recovery.handle` takes a fault (the error, the events it cost, how often their
capture failed so far per fault class, and where it happened) and does what the
:class:`~m2s2hil.engine.fault_policy.FaultPolicy` decides: every fault is recorded (status,
event bus, journal event ``fault``); a capture's own fault makes the runner trust nothing of
the failing device (its state re-commanded next time); a retry first reconnects or clears
the alarm of the device as the rule says (a recovery that fails is a fault of its own, under
the policy too) and waits the back-off; a skip records each event given up
(``store.record_skip`` with its reason). What is left to the runner is where it stands: a
capture is retried at once, a stored frame's is requeued; a suspend parks the run.

The action recorded names what is really done: ``home+retry`` only when an axis behind the
device has switches; an alarm on a controller without them is cleared by reset and unlock
(``unlock+retry``, the position re-read and the retried move verified), never homed.
"""

from __future__ import annotations

import collections
import enum
import logging
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

from m2s2hil.config import AxisConfig
from m2s2hil.engine.fault_policy import Decision, FaultPolicy, device_of, fault_class_of
from m2s2hil.engine.schedule import UnitSchedule
from m2s2hil.engine.state import FaultInfo
from m2s2hil.engine.steps import CaptureSteps
from m2s2hil.plan import CaptureEvent
from m2s2hil.rig.opened import AxisRole, DeviceLink, Rig
from m2s2hil.rig.operations import RigOps
from m2s2hil.store.session import SessionStore

log = logging.getLogger(__name__)


class Verdict(enum.Enum):
    RETRY = "retry"  # capture it again (recovery done, back-off waited)
    SKIPPED = "skipped"  # given up, each event recorded as a gap
    SUSPEND = "suspend"  # park the run until an operator resumes it, then again
    ABORT = "abort"  # end the run as failed with this error
    STOPPED = "stopped"  # an abort was asked for meanwhile: no recovery after it


@dataclass(frozen=True)
class Resolution:
    verdict: Verdict
    error: BaseException
    fault_class: str

    @property
    def reason(self) -> str:
        """A suspension's pause reason."""
        return f"{self.fault_class}: {self.error}"


def alarm_recovery(links: Iterable[DeviceLink], axes: dict[AxisRole, AxisConfig]) -> str:
    """What clearing an alarm does on ``links`` (as :meth:`RigOps.home` does it): ``home``
    when an axis behind them has switches, ``unlock`` when the controller clears its own
    alarm without homing (GRBL: reset and ``$X``), else ``re-read`` (the position only)."""
    links = [link for link in links if link.axis_roles]
    if any(axes[r].homing == "switches" for link in links for r in link.axis_roles):
        return "home"
    return "unlock" if any(link.alarm is not None for link in links) else "re-read"


class Recovery:
    """Applies the policy for one run; keeps every fault recorded (``faults``)."""

    def __init__(self, policy: FaultPolicy, rig: Rig, ops: RigOps, steps: CaptureSteps, store: SessionStore,
                 schedule: UnitSchedule, *, aborting: Callable[[], bool],
                 on_fault: Callable[[FaultInfo], None]) -> None:
        self.policy = policy
        self.rig = rig
        self.ops = ops
        self.steps = steps
        self.store = store
        self.schedule = schedule
        self.aborting = aborting
        self.on_fault = on_fault
        self.faults: list[FaultInfo] = []
        self.failed_stores: collections.defaultdict[str, collections.Counter[str]] = (
            collections.defaultdict(collections.Counter))  # per event: the pipeline's failures

    def handle(self, err: BaseException, events: Sequence[CaptureEvent],
               failures: collections.Counter[str], *, stage: str | None = None,
               final: bool = False) -> Resolution:
        """Apply the policy to ``err``, which cost ``events``: a capture's fault (``stage``
        None) or the pipeline's at ``stage`` (``final``: at teardown, no back-off waited).
        ``failures`` counts the earlier failures of these events per class (updated)."""
        while True:
            fc = fault_class_of(err)
            failures[fc] += 1
            decision = self.policy.decide(fc, failures[fc])
            action = self._action_text(decision, err, stage)
            self.note(err, action, events[0] if events else None, failures[fc])
            if isinstance(err, (KeyboardInterrupt, SystemExit)):
                raise err
            if stage is None:
                self._forget_after(err)
                # An abort (e.g. an emergency stop that caused this very fault) wins over any
                # recovery: never re-home, move or relight after it was asked for.
                if self.aborting():
                    return Resolution(Verdict.STOPPED, err, fc)
            if decision.retries:
                if stage is None:
                    try:
                        if decision.reconnect:
                            self.ops.reconnect(device_of(err))
                        if decision.home:
                            self.ops.home(device_of(err))
                        self.rig.clock.sleep(decision.delay_s)
                    except Exception as rexc:  # the recovery failed: a fault of its own
                        err = rexc
                        continue
                elif decision.delay_s and not final:
                    self.rig.clock.sleep(decision.delay_s)
                return Resolution(Verdict.RETRY, err, fc)
            if decision.action == "skip":
                for ev in events:
                    self.store.record_skip(ev, f"{type(err).__name__}: {err}", fc)
                    self.schedule.mark_skipped(ev)
                return Resolution(Verdict.SKIPPED, err, fc)
            if decision.action == "suspend":
                return Resolution(Verdict.SUSPEND, err, fc)
            return Resolution(Verdict.ABORT, err, fc)

    def handle_stored(self, err: BaseException, ev: CaptureEvent, stage: str, *, final: bool) -> Resolution:
        """A frame the pipeline failed at ``stage``: counted per event across its captures."""
        return self.handle(err, [ev], self.failed_stores[ev.event_id], stage=stage, final=final)

    def note(self, exc: BaseException, action: str, ev: CaptureEvent | None, attempt: int = 1) -> FaultInfo:
        """Record a fault: status, event bus and journal (event ``fault``)."""
        clock = self.rig.clock
        info = FaultInfo(
            time_s=clock.monotonic(), fault_class=fault_class_of(exc), action=action,
            message=f"{type(exc).__name__}: {exc}", event_id=ev.event_id if ev else None, attempt=attempt,
            device=device_of(exc),
        )
        self.faults.append(info)
        log.warning("fault %s on %s (attempt %d): %s -> %s", info.fault_class, info.event_id, attempt,
                    info.message, action)
        self.on_fault(info)
        try:
            self.store.record_event("fault", {
                "fault_class": info.fault_class, "action": action, "message": info.message,
                "event_id": info.event_id, "attempt": attempt, "device": info.device, "clock_s": info.time_s,
            })
        except Exception as rec_exc:  # e.g. a full disk: the fault is still in status and events
            log.error("could not journal fault: %s", rec_exc)
        return info

    def _action_text(self, decision: Decision, err: BaseException, stage: str | None) -> str:
        if stage is not None:
            return f"{decision.action} ({stage})"
        if decision.retries and decision.home:
            device = device_of(err)
            links = [link for link in self.ops.links_named(device) if link.axis_roles] or list(self.rig.links)
            return f"{alarm_recovery(links, self.rig.config.axes)}+{decision.action}"
        return decision.action

    def _forget_after(self, err: BaseException) -> None:
        """After a fault, stop trusting what we know about the device that failed (all of
        them if it is not known): its state is re-commanded and re-verified next time."""
        roles = self.ops.roles_named(device_of(err))
        known = bool(roles)
        self.ops.invalidate(lamps=not known or "lights" in roles,
                            pose=not known or bool(roles & {"turntable", "tilt"}))
        self.steps.recover()  # the camera's setting re-commanded, any stream stopped
