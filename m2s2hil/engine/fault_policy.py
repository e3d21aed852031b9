"""The engine's declarative fault policy: what to do per fault class.

Every error the engine meets has a ``fault_class`` (device errors carry one, the
store's ``DiskFull`` is ``"disk_full"``, anything else is ``"other"``). The policy
maps each class to a :class:`FaultRule`:

- ``retry``: try the capture again, up to ``attempts`` times, waiting
  ``backoff_s * backoff_factor**(n-1)`` (capped at ``max_backoff_s``) on the engine's
  clock before retry *n*; ``home_first`` homes the failing axis before each retry
  (a stage alarm needs it); then ``then``.
- ``reconnect``: call the failing device's ``reconnect()``, then retry, up to
  ``attempts`` times; then ``then``.
- ``skip``: give the capture up; the gap is recorded in the session with its reason.
- ``suspend``: park the session in ``paused`` (lamps off, motion stopped) until an
  operator resumes it; the capture is retried on resume.
- ``abort``: end the session as failed.

Defaults (``FaultPolicy()``): timeout → retry 3 then skip; protocol → retry 2 then
skip; alarm → home + retry once then abort; frame_incomplete → retry 3 then skip;
device_gone → reconnect + retry 2 then abort; disk_full → suspend; other → abort.

A policy is plain data: ``FaultPolicy.model_validate({"timeout": {"action": "skip"}})``
overrides one class and keeps the defaults for the rest; unknown keys are rejected.

Beside faults, ``qc_pause`` names capture-time QC flags that park the session like a
``suspend`` (the flagged frame is stored; nothing is captured again): a wrong build on the
turntable or a dead lamp is the operator's to fix before the sweep goes on.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

FAULT_CLASSES = ("timeout", "protocol", "alarm", "frame_incomplete", "device_gone", "disk_full", "other")
FaultClass = Literal["timeout", "protocol", "alarm", "frame_incomplete", "device_gone", "disk_full", "other"]
Action = Literal["retry", "reconnect", "skip", "suspend", "abort"]
Final = Literal["skip", "suspend", "abort"]


def fault_class_of(exc: BaseException) -> str:
    fc = getattr(exc, "fault_class", None)
    return fc if isinstance(fc, str) and fc in FAULT_CLASSES else "other"


def device_of(exc: BaseException) -> str | None:
    """The device an error names (driver errors carry it as ``device``), if any."""
    dev = getattr(exc, "device", None)
    return dev if isinstance(dev, str) else None


class FaultRule(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    action: Action
    attempts: Annotated[int, Field(ge=0, le=20)] = 0  # retries (retry / reconnect)
    backoff_s: Annotated[float, Field(ge=0, le=600)] = 0.5
    backoff_factor: Annotated[float, Field(ge=1, le=10)] = 2.0
    max_backoff_s: Annotated[float, Field(ge=0, le=3600)] = 30.0
    home_first: bool = False
    then: Final = "skip"

    @model_validator(mode="after")
    def _check(self) -> FaultRule:
        if self.action in ("retry", "reconnect") and self.attempts < 1:
            raise ValueError(f"action {self.action!r} needs attempts >= 1")
        return self

    def backoff(self, retry: int) -> float:
        """Wait before retry number ``retry`` (1-based)."""
        return min(self.max_backoff_s, self.backoff_s * self.backoff_factor ** max(0, retry - 1))


def _rule(**kw: Any) -> Any:
    return Field(default_factory=lambda: FaultRule(**kw))


class FaultPolicy(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    timeout: FaultRule = _rule(action="retry", attempts=3, then="skip")
    protocol: FaultRule = _rule(action="retry", attempts=2, then="skip")
    alarm: FaultRule = _rule(action="retry", attempts=1, home_first=True, then="abort")
    frame_incomplete: FaultRule = _rule(action="retry", attempts=3, backoff_s=0.1, then="skip")
    device_gone: FaultRule = _rule(action="reconnect", attempts=2, backoff_s=1.0, then="abort")
    disk_full: FaultRule = _rule(action="suspend")
    other: FaultRule = _rule(action="abort")
    #: Capture-time QC flags that pause the session (the frame is kept): e.g. the twin's
    #: ``wrong_build`` or ``lamp_out`` (``analysis.qc.FLAGS``). Empty: QC never pauses.
    qc_pause: tuple[Annotated[str, Field(pattern=r"^[a-z][a-z_]{0,31}$")], ...] = ()

    def qc_pause_reason(self, qc: Any, event_id: str) -> str | None:
        """Why a stored frame's QC result (``meta["qc"]``) pauses the session, or None."""
        if not self.qc_pause or not isinstance(qc, dict):
            return None
        hit = [f for f in qc.get("flags") or () if f in self.qc_pause]
        return f"QC flagged {event_id}: {', '.join(hit)}" if hit else None

    def rule_for(self, fault_class: str) -> FaultRule:
        return getattr(self, fault_class if fault_class in FAULT_CLASSES else "other")

    def decide(self, fault_class: str, failures: int) -> Decision:
        """What to do after the ``failures``-th failure (1-based) of one capture in this class."""
        rule = self.rule_for(fault_class)
        if rule.action in ("retry", "reconnect"):
            if failures <= rule.attempts:
                return Decision(
                    action=rule.action,
                    delay_s=rule.backoff(failures),
                    home=rule.home_first,
                    reconnect=rule.action == "reconnect",
                    retry=failures,
                )
            return Decision(action=rule.then)
        return Decision(action=rule.action)


@dataclass(frozen=True)
class Decision:
    action: str  # "retry" | "reconnect" | "skip" | "suspend" | "abort"
    delay_s: float = 0.0
    home: bool = False
    reconnect: bool = False
    retry: int = 0

    @property
    def retries(self) -> bool:
        return self.action in ("retry", "reconnect")
