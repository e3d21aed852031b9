"""The run's unit schedule on its own: plan order, what is pending, requeues and continuous passes.

No rig and no disk: the events come from a sweep expanded on the built-in rig's configuration.
"""

from __future__ import annotations

from collections.abc import Hashable

import pytest

from m2s2hil.config import default_rig
from m2s2hil.engine.schedule import UnitSchedule
from m2s2hil.plan import CaptureEvent, Sweep, dark_event


def plan(mode: str = "stop-and-go") -> list[CaptureEvent]:
    """2 darks, then 2 passes (strong, weak) of 4 azimuths each."""
    sweep = Sweep(satellite="voyager", build="B3", lighting=["weak", "strong"], tilts=["E1"],
                  azimuth_step_deg=90, mode=mode, dark={"frames": 2})
    return sweep.expand(default_rig())


def single(ev: CaptureEvent) -> Hashable | None:
    return None


def by_pass(ev: CaptureEvent) -> Hashable | None:
    return ev.pass_index if ev.kind == "frame" else None


def ids(unit: list[CaptureEvent]) -> list[str]:
    return [e.event_id for e in unit]


def drain(s: UnitSchedule) -> list[list[str]]:
    out = []
    while unit := s.next_unit():
        out.append(ids(unit))
        for ev in unit:
            s.mark_done(ev)
    return out


def test_one_event_per_unit_in_plan_order_skipping_what_is_done_or_skipped() -> None:
    events = plan()
    s = UnitSchedule(events, single, done=[events[0].event_id], skipped=[events[3].event_id, "not/planned"])
    assert (s.total, s.done_count, s.skipped_count, s.settled_count) == (len(events), 1, 1, 2)
    units = drain(s)
    assert units == [[e.event_id] for i, e in enumerate(events) if i not in (0, 3)]
    assert s.done_count == len(events) - 1 and s.missing_ids() == {events[3].event_id}
    assert s.remaining() == [] and s.skipped_ids() == {events[3].event_id}


def test_in_flight_is_not_pending_until_it_settles_and_a_failed_store_comes_first_again() -> None:
    events = plan()
    s = UnitSchedule(events, single)
    first, second, third = (s.next_unit()[0] for _ in range(3))
    s.submitted(third)
    assert not s.is_pending(third) and s.is_pending(first)
    s.requeue_failed(third)  # the pipeline could not store it: captured again, before the cursor's
    assert s.is_pending(third)
    s.requeue([first, second])  # a pass cut short: what is left of it
    assert [ids(s.next_unit()) for _ in range(3)] == [[first.event_id], [second.event_id], [third.event_id]]
    assert ids(s.next_unit()) == [events[3].event_id]  # then the cursor goes on


def test_requeue_keeps_one_copy_and_only_what_is_still_pending() -> None:
    events = plan()
    s = UnitSchedule(events, single)
    a, b = s.next_unit()[0], s.next_unit()[0]
    s.mark_done(a)
    s.requeue([a, b, b])
    assert s.has_requeued
    assert ids(s.next_unit()) == [b.event_id]
    assert not s.has_requeued


def test_a_continuous_pass_is_one_unit_of_whatever_is_left_of_it() -> None:
    events = plan("continuous")
    darks, strong, weak = events[:2], events[2:6], events[6:]
    s = UnitSchedule(events, by_pass, done=[strong[1].event_id])
    assert ids(s.next_unit()) == [darks[0].event_id]  # darks stay one per unit
    assert ids(s.next_unit()) == [darks[1].event_id]
    unit = s.next_unit()
    assert ids(unit) == ids([strong[0], strong[2], strong[3]])  # the stored mark left out
    s.mark_done(strong[0])
    s.requeue(unit)  # stopped early: the rest of the pass, again, before the next pass
    assert ids(s.next_unit()) == ids([strong[2], strong[3]])
    assert ids(s.next_unit()) == ids(weak)
    assert s.next_unit() == []


def test_a_mark_whose_store_failed_is_captured_again_on_its_own() -> None:
    events = plan("continuous")
    strong, weak = events[2:6], events[6:]
    s = UnitSchedule(events, by_pass, done=[e.event_id for e in events[:2]])
    assert ids(s.next_unit()) == ids(strong)
    s.requeue_failed(strong[2])  # its store failed after the pass
    assert ids(s.next_unit()) == ids([strong[2]])  # the rest of its pass is done or in hand
    assert ids(s.next_unit()) == ids(weak)


@pytest.mark.parametrize("planned", [True, False])
def test_only_planned_events_count_as_done(planned: bool) -> None:
    events = plan()
    s = UnitSchedule(events, single)
    ev = events[0] if planned else dark_event(0.123, 1.0, 2)  # e.g. a dark taken for auto exposure
    assert s.mark_done(ev) is planned
    assert s.done_count == int(planned) and s.stored_this_run == ({ev.event_id} if planned else set())
    assert s.last_done is (ev if planned else None)
