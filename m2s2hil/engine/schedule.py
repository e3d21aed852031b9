"""Which capture comes next: the run's unit schedule, pure bookkeeping (no rig, no disk).

The sweep's events are taken in plan order by a cursor; an event is *pending* while it is
neither done (stored), skipped (given up, recorded) nor in flight (captured, in the
pipeline). Events to capture again (a pass cut short, a frame the pipeline failed) are
requeued and come first, lowest plan index first. Events the steps capture together (one
continuous pass: the same non-None ``unit_key``) form one unit: whatever is still to do of it.

Thread-safe: the run's thread changes it, status readers in other threads count it.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Hashable, Iterable, Sequence

from m2s2hil.plan import CaptureEvent

UnitKey = Callable[[CaptureEvent], Hashable | None]


class UnitSchedule:
    """The cursor, the requeue and the done / skipped / in-flight sets of one run."""

    def __init__(self, events: Sequence[CaptureEvent], unit_key: UnitKey, *, done: Iterable[str] = (),
                 skipped: Iterable[str] = ()) -> None:
        self.events = list(events)
        self.by_id = {e.event_id: e for e in self.events}
        self._unit_key = unit_key
        self._lock = threading.Lock()
        self._done = set(done) & self.by_id.keys()
        self._skipped = set(skipped) & self.by_id.keys()
        self._inflight: dict[str, CaptureEvent] = {}
        self._requeue: list[CaptureEvent] = []
        self._cursor = 0
        #: Planned events stored by this run (not before it): the efficiency's basis.
        self.stored_this_run: set[str] = set()
        self.last_done: CaptureEvent | None = None

    # -- reading ------------------------------------------------------------------
    @property
    def total(self) -> int:
        return len(self.events)

    @property
    def done_count(self) -> int:
        with self._lock:
            return len(self._done)

    @property
    def skipped_count(self) -> int:
        """Events given up and not stored since (a retried skip that succeeded is done)."""
        with self._lock:
            return len(self._skipped - self._done)

    @property
    def settled_count(self) -> int:
        """Done or skipped: the progress's numerator and the ETA cache's key."""
        with self._lock:
            return len(self._done | self._skipped)

    def done_ids(self) -> set[str]:
        with self._lock:
            return set(self._done)

    def skipped_ids(self) -> set[str]:
        """Skipped and not stored since, as the summary lists them."""
        with self._lock:
            return self._skipped - self._done

    def missing_ids(self) -> set[str]:
        """Planned events not stored (a run ending with some is ``completed_with_gaps``)."""
        with self._lock:
            return self.by_id.keys() - self._done

    def remaining(self) -> list[CaptureEvent]:
        """Events neither done nor skipped, in plan order (the ETA's)."""
        with self._lock:
            gone = self._done | self._skipped
            return [e for e in self.events if e.event_id not in gone]

    def is_pending(self, ev: CaptureEvent) -> bool:
        with self._lock:
            return self._pending(ev)

    def pending_of(self, unit: Iterable[CaptureEvent]) -> list[CaptureEvent]:
        with self._lock:
            return [e for e in unit if self._pending(e)]

    @property
    def has_requeued(self) -> bool:
        with self._lock:
            return bool(self._requeue)

    # -- changing -----------------------------------------------------------------
    def next_unit(self) -> list[CaptureEvent]:
        """The next unit to capture, in plan order; empty when nothing is left to start."""
        with self._lock:
            if self._requeue:
                self._requeue.sort(key=lambda e: e.index)
                first: CaptureEvent | None = self._requeue.pop(0)
            else:
                first = None
                while self._cursor < len(self.events):
                    ev = self.events[self._cursor]
                    self._cursor += 1
                    if self._pending(ev):
                        first = ev
                        break
            if first is None:
                return []
            key = self._unit_key(first)
            if key is None:
                return [first]
            unit = [first]
            for ev in list(self._requeue):
                if self._unit_key(ev) == key:
                    unit.append(ev)
                    self._requeue.remove(ev)
            while self._cursor < len(self.events):
                ev = self.events[self._cursor]
                if self._unit_key(ev) != key:
                    break
                self._cursor += 1
                if self._pending(ev):
                    unit.append(ev)
            return sorted(unit, key=lambda e: e.index)

    def requeue(self, events: Iterable[CaptureEvent]) -> None:
        """Capture these again (those still pending; each once)."""
        with self._lock:
            self._requeue.extend(e for e in events if self._pending(e) and e not in self._requeue)

    def requeue_failed(self, ev: CaptureEvent) -> None:
        """A frame the pipeline could not finish: out of flight and captured again."""
        with self._lock:
            self._inflight.pop(ev.event_id, None)
            self._requeue.append(ev)

    def submitted(self, ev: CaptureEvent) -> None:
        with self._lock:
            self._inflight[ev.event_id] = ev

    def settled(self, ev: CaptureEvent) -> None:
        """The pipeline is done with ``ev``, whatever its outcome."""
        with self._lock:
            self._inflight.pop(ev.event_id, None)

    def mark_done(self, ev: CaptureEvent) -> bool:
        """``ev`` is stored; False (nothing counted) for an event not in the plan (a dark
        taken for auto exposure or a temperature retake)."""
        if ev.event_id not in self.by_id:
            return False
        with self._lock:
            self._done.add(ev.event_id)
            self.stored_this_run.add(ev.event_id)
            self.last_done = ev
        return True

    def mark_skipped(self, ev: CaptureEvent) -> None:
        with self._lock:
            self._skipped.add(ev.event_id)

    def _pending(self, ev: CaptureEvent) -> bool:
        i = ev.event_id
        return i not in self._done and i not in self._skipped and i not in self._inflight
