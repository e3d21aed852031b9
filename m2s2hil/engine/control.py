"""A run's control state: its :class:`~m2s2hil.engine.state.RunState`, the requests that change
it from any thread (pause, resume, abort, the operator's lens confirmation) and the wait of a
parked run. The runner's thread asks it where the run stands between units and parks in it.

Every transition is checked (:func:`~m2s2hil.engine.state.check_transition`) and published
(:class:`~m2s2hil.engine.state.StateChanged`); an illegal request raises
:class:`~m2s2hil.engine.state.IllegalTransition` (HTTP 409).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from m2s2hil.engine.report import RunClock
from m2s2hil.engine.state import IllegalTransition, RunState, check_transition

S = RunState
#: Publishes a transition: (old, new, reason).
OnTransition = Callable[[RunState, RunState, str | None], None]


class RunControl:
    """The state machine of one run (thread-safe; the lock is re-entrant)."""

    def __init__(self, on_transition: OnTransition, time: RunClock, now: Callable[[], float], *,
                 lens_on: bool = False) -> None:
        self.lock = threading.RLock()
        self._cond = threading.Condition(self.lock)
        self._on_transition = on_transition
        self._time = time
        self._now = now
        self.state = S.IDLE
        self.pause_reason: str | None = None
        self.lens_wait: bool | None = None  # parked for the operator to cap (True) / uncap the lens
        #: The operator confirmed the cap on (a real rig's; see darks).
        self.lens_on = lens_on
        #: The run is on its way out: pause and resume are refused, an abort is a no-op.
        self.finishing = False

    def set_state(self, new: RunState, action: str, reason: str | None = None) -> None:
        with self.lock:
            old = self.state
            check_transition(old, new, action)
            self.state = new
            self._on_transition(old, new, reason)
            if new is S.RUNNING and old is S.IDLE:
                self._time.started_at = self._now()

    def request(self, target: RunState, action: str, reason: str | None = None) -> None:
        """An operator's request (pause, resume, abort), honoured at the next safe boundary."""
        with self.lock:
            if self.state.terminal:
                raise IllegalTransition(self.state, target, action)
            if self.finishing and target is not S.ABORTING:
                raise IllegalTransition(self.state, target, f"{action} (the session is finishing)")
            if self.finishing:
                return  # abort while finishing: the run is already on its way out
            if target is S.RUNNING and self.state is not S.PAUSED:
                # IDLE -> RUNNING is run()'s transition, not resume()'s
                raise IllegalTransition(self.state, target, action)
            self.set_state(target, action, reason)
            if target is S.PAUSING:
                self.pause_reason = reason
            self._cond.notify_all()

    def resume(self) -> None:
        with self.lock:
            if self.state is S.PAUSED and self.lens_wait is not None:
                raise IllegalTransition(self.state, S.RUNNING, f"resume ({self.pause_reason}; the "
                                        "operator confirms it with confirm_lens / POST /sessions/{id}/lens)")
            self.request(S.RUNNING, "resume")

    def waiting_for_lens(self) -> bool | None:
        with self.lock:
            return self.lens_wait if self.state is S.PAUSED else None

    def confirm_lens(self, capped: bool) -> None:
        with self.lock:
            if self.state is not S.PAUSED or self.lens_wait is not capped:
                want = ("nothing" if self.state is not S.PAUSED or self.lens_wait is None
                        else f"the lens cap {'on' if self.lens_wait else 'off'}")
                what = f"confirm the lens cap {'on' if capped else 'off'} (waiting for {want})"
                raise IllegalTransition(self.state, S.RUNNING, what)
            self.lens_on = capped
            self.set_state(S.RUNNING, "lens confirmed")
            self._cond.notify_all()

    def begin_park(self, reason: str | None, lens: bool | None) -> bool:
        """The run's own suspension (a fault, the lens cap) or a pause asked for; False when
        an abort came first."""
        with self.lock:
            if self.state is S.RUNNING:
                self.set_state(S.PAUSING, "suspend", reason)
                self.pause_reason = reason
                self.lens_wait = lens
            return self.state is not S.ABORTING

    def parked(self) -> bool:
        """The rig is safe: ``paused`` until resumed, confirmed or aborted; False on an abort."""
        with self.lock:
            if self.state is S.PAUSING:
                self.set_state(S.PAUSED, "park", self.pause_reason)
                self._time.pause(self._now())
            while self.state is S.PAUSED:
                self._cond.wait()
            self.lens_wait = None
            self._time.unpause(self._now())
            return self.state is not S.ABORTING
