"""The capture engine's run states, status snapshot and event bus.

States and the transitions the engine allows (anything else raises
:class:`IllegalTransition`)::

    idle ──run──▶ running ──▶ completed
                    │  ▲ ╲──▶ failed
              pause │  │ resume
                    ▼  │
                 pausing ─▶ paused ──abort──▶ aborting ─▶ aborted
                                              (also from running / pausing)

``pausing`` and ``aborting`` are the "requested, not yet at a safe boundary" states:
the engine finishes the capture in hand (moves and exposures are never cut short) and
only then parks. A fault whose policy is *suspend* (e.g. a full disk) takes the same
path into ``paused`` with ``pause_reason`` set. ``aborted`` is a terminal state of its
own so an operator's abort is not reported as a failure.

:class:`EngineStatus` is a frozen snapshot; take a fresh one with ``Engine.status()``.

Events (:class:`StateChanged`, :class:`Progress`, :class:`Captured`,
:class:`FrameStored`, :class:`FaultRecorded`, :class:`SessionFinished`) are frozen
dataclasses with a monotonically increasing ``seq`` per engine and a ``kind`` string
(``state``, ``progress``, ``captured``, ``frame``, ``fault``, ``finished``; use it as the
SSE event name, ``to_dict()`` as its data). :class:`EventBus` delivers them
synchronously to callbacks (``subscribe``) or into bounded per-consumer queues that
another thread drains (``listen``), and keeps a short history so a reconnecting SSE
client can ask for everything after the last ``seq`` it saw (``since``).
"""

from __future__ import annotations

import collections
import enum
import itertools
import logging
import queue
import threading
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from typing import Any, ClassVar

from m2s2hil.errors import UsageError

log = logging.getLogger(__name__)


class RunState(enum.StrEnum):
    IDLE = "idle"
    RUNNING = "running"
    PAUSING = "pausing"
    PAUSED = "paused"
    ABORTING = "aborting"
    COMPLETED = "completed"
    COMPLETED_WITH_GAPS = "completed_with_gaps"  # ran to the end; some planned frames skipped
    FAILED = "failed"
    ABORTED = "aborted"

    @property
    def terminal(self) -> bool:
        return self in (RunState.COMPLETED, RunState.COMPLETED_WITH_GAPS, RunState.FAILED, RunState.ABORTED)

    @property
    def active(self) -> bool:
        """The run thread is alive and owns the hardware."""
        return self in (RunState.RUNNING, RunState.PAUSING, RunState.PAUSED, RunState.ABORTING)


S = RunState
TRANSITIONS: dict[RunState, frozenset[RunState]] = {
    S.IDLE: frozenset({S.RUNNING, S.FAILED}),
    S.RUNNING: frozenset({S.PAUSING, S.ABORTING, S.COMPLETED, S.COMPLETED_WITH_GAPS, S.FAILED}),
    S.PAUSING: frozenset({S.PAUSED, S.ABORTING, S.FAILED}),
    S.PAUSED: frozenset({S.RUNNING, S.ABORTING, S.FAILED}),
    S.ABORTING: frozenset({S.ABORTED, S.FAILED}),
    S.COMPLETED: frozenset(),
    S.COMPLETED_WITH_GAPS: frozenset(),
    S.FAILED: frozenset(),
    S.ABORTED: frozenset(),
}


class IllegalTransition(UsageError):
    """A control request that the current state does not allow (HTTP 409)."""

    def __init__(self, current: RunState, target: RunState, action: str) -> None:
        self.current = current
        self.target = target
        self.action = action
        allowed = ", ".join(sorted(t.value for t in TRANSITIONS[current])) or "nothing (terminal)"
        super().__init__(
            f"cannot {action} while {current.value}; from {current.value} the engine may go to: {allowed}"
        )


def check_transition(current: RunState, target: RunState, action: str) -> None:
    if target not in TRANSITIONS[current]:
        raise IllegalTransition(current, target, action)


# -- status snapshot ----------------------------------------------------------------


@dataclass(frozen=True)
class FaultInfo:
    """One fault the engine met and what the policy did about it."""

    time_s: float  # engine clock
    fault_class: str
    action: str  # "retry" | "reconnect" | "home" | "skip" | "suspend" | "abort" | "teardown"
    message: str
    event_id: str | None = None
    attempt: int = 1
    device: str | None = None


@dataclass(frozen=True)
class EngineStatus:
    state: RunState
    session_id: str
    done: int  # events stored (frames and darks) including those from earlier runs
    total: int  # events in the plan
    skipped: int  # events given up in this run (each recorded in the store with its reason)
    progress: float  # (done + skipped) / total, 0..1
    eta_s: float | None  # remaining session time on the engine clock
    elapsed_s: float  # active time on the engine clock (paused time excluded)
    lighting: str | None = None
    elevation: str | None = None
    tilt_deg: float | None = None  # read-back
    azimuth_deg: float | None = None  # read-back
    lamps_on: tuple[int, ...] = ()
    last_frame_index: int | None = None
    last_event_id: str | None = None
    faults: tuple[FaultInfo, ...] = ()  # the most recent ones (see fault_count)
    fault_count: int = 0  # every fault of this run
    pause_reason: str | None = None
    error: str | None = None
    efficiency: float | None = None  # lower bound / actual duration, once completed
    mode: str = "stop-and-go"

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["state"] = self.state.value
        return d


# -- events -------------------------------------------------------------------------


@dataclass(frozen=True)
class EngineEvent:
    kind: ClassVar[str] = "event"
    seq: int
    time_s: float  # engine clock (virtual in simulation)
    wall: float  # epoch seconds

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["kind"] = self.kind
        for k, v in d.items():
            if isinstance(v, enum.Enum):
                d[k] = v.value
        return d


@dataclass(frozen=True)
class StateChanged(EngineEvent):
    kind: ClassVar[str] = "state"
    old: RunState = RunState.IDLE
    new: RunState = RunState.IDLE
    reason: str | None = None


@dataclass(frozen=True)
class Progress(EngineEvent):
    kind: ClassVar[str] = "progress"
    done: int = 0
    total: int = 0
    skipped: int = 0
    progress: float = 0.0
    eta_s: float | None = None
    elapsed_s: float = 0.0


@dataclass(frozen=True)
class Captured(EngineEvent):
    """A frame left the camera (read-back pose); it is stored later (FrameStored)."""

    kind: ClassVar[str] = "captured"
    event_id: str = ""
    index: int = 0
    lighting: str | None = None
    elevation: str | None = None
    azimuth_deg: float | None = None  # read-back (continuous: interpolated at mid-exposure)
    tilt_deg: float | None = None
    exposure_s: float | None = None


@dataclass(frozen=True)
class FrameStored(EngineEvent):
    kind: ClassVar[str] = "frame"
    event_id: str = ""
    index: int = 0
    lighting: str | None = None
    elevation: str | None = None
    azimuth_deg: float | None = None
    exposure_s: float | None = None
    path: str | None = None
    qc_score: float | None = None


@dataclass(frozen=True)
class FaultRecorded(EngineEvent):
    kind: ClassVar[str] = "fault"
    fault: FaultInfo = field(default_factory=lambda: FaultInfo(0.0, "other", "abort", ""))


@dataclass(frozen=True)
class SessionFinished(EngineEvent):
    kind: ClassVar[str] = "finished"
    state: RunState = RunState.COMPLETED
    session_id: str = ""
    done: int = 0
    total: int = 0
    skipped: int = 0
    duration_s: float = 0.0
    efficiency: float | None = None
    error: str | None = None


Callback = Callable[[EngineEvent], None]


class Listener:
    """A bounded queue of events for a consumer in another thread.

    The engine never waits for a listener: when the queue is full the oldest event
    is dropped and ``lost`` counts it (the consumer can refetch via ``EventBus.since``).
    """

    def __init__(self, bus: EventBus, maxsize: int) -> None:
        self._bus = bus
        self._q: queue.Queue[EngineEvent] = queue.Queue(maxsize=maxsize)
        self.lost = 0
        self.closed = False

    def _put(self, ev: EngineEvent) -> None:
        while True:
            try:
                self._q.put_nowait(ev)
                return
            except queue.Full:
                try:
                    self._q.get_nowait()
                    self.lost += 1
                except queue.Empty:
                    pass

    def get(self, timeout: float | None = None) -> EngineEvent | None:
        """Next event, or None after ``timeout`` seconds (real time) without one."""
        try:
            return self._q.get(timeout=timeout)
        except queue.Empty:
            return None

    def __iter__(self) -> Iterator[EngineEvent]:
        """Events until the bus closes (after SessionFinished)."""
        while True:
            ev = self.get(timeout=0.1)
            if ev is not None:
                yield ev
            elif self.closed or self._bus.closed:
                while (ev := self.get(timeout=0)) is not None:
                    yield ev
                return

    def close(self) -> None:
        self.closed = True
        self._bus._remove_listener(self)


class EventBus:
    """Typed engine events with sequence numbers, for callbacks and other threads."""

    def __init__(self, history: int = 1000) -> None:
        self._lock = threading.Lock()
        self._seq = itertools.count(1)
        self._callbacks: list[Callback] = []
        self._listeners: list[Listener] = []
        self._history: collections.deque[EngineEvent] = collections.deque(maxlen=history)
        self.closed = False

    def next_seq(self) -> int:
        with self._lock:
            return next(self._seq)

    def subscribe(self, callback: Callback) -> Callable[[], None]:
        """Call ``callback(event)`` for every event; returns unsubscribe.

        Callbacks run in the thread that publishes: the engine's, except the StateChanged
        of pause/resume/abort, which runs in the caller's. Keep them short (the engine
        waits for them); an exception in one is logged and does not stop the session.
        """
        with self._lock:
            self._callbacks.append(callback)

        def unsubscribe() -> None:
            with self._lock:
                if callback in self._callbacks:
                    self._callbacks.remove(callback)

        return unsubscribe

    def listen(self, maxsize: int = 1000) -> Listener:
        lst = Listener(self, maxsize)
        with self._lock:
            self._listeners.append(lst)
        return lst

    def _remove_listener(self, lst: Listener) -> None:
        with self._lock:
            if lst in self._listeners:
                self._listeners.remove(lst)

    def since(self, seq: int) -> list[EngineEvent]:
        """Events still in the history with a sequence number above ``seq``."""
        with self._lock:
            return [e for e in self._history if e.seq > seq]

    def publish(self, event: EngineEvent) -> None:
        with self._lock:
            self._history.append(event)
            callbacks = list(self._callbacks)
            listeners = list(self._listeners)
        for lst in listeners:
            lst._put(event)
        for cb in callbacks:
            try:
                cb(event)
            except Exception:
                log.exception("engine event subscriber %r failed on %s", cb, event.kind)

    def close(self) -> None:
        self.closed = True
