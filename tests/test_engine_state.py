"""Engine building blocks without hardware: run states, event bus, fault policy, angle matching."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from pydantic import ValidationError

from m2s2hil.engine.exposure_search import find_exposure, percentile_dn
from m2s2hil.engine.fault_policy import FaultPolicy, FaultRule, fault_class_of
from m2s2hil.engine.marks import AngleTrack, MarkMatcher, TimestampMapper, blur_estimate, run_up_deg
from m2s2hil.engine.state import (
    TRANSITIONS,
    EventBus,
    FaultInfo,
    FaultRecorded,
    IllegalTransition,
    Progress,
    RunState,
    StateChanged,
    check_transition,
)
from m2s2hil.errors import UsageError

S = RunState

ALLOWED = {
    (S.IDLE, S.RUNNING), (S.IDLE, S.FAILED),
    (S.RUNNING, S.PAUSING), (S.RUNNING, S.ABORTING), (S.RUNNING, S.COMPLETED), (S.RUNNING, S.FAILED),
    (S.RUNNING, S.COMPLETED_WITH_GAPS),
    (S.PAUSING, S.PAUSED), (S.PAUSING, S.ABORTING), (S.PAUSING, S.FAILED),
    (S.PAUSED, S.RUNNING), (S.PAUSED, S.ABORTING), (S.PAUSED, S.FAILED),
    (S.ABORTING, S.ABORTED), (S.ABORTING, S.FAILED),
}


@pytest.mark.parametrize("old", list(S))
@pytest.mark.parametrize("new", list(S))
def test_transition_table(old: RunState, new: RunState) -> None:
    if (old, new) in ALLOWED:
        check_transition(old, new, "x")
    else:
        with pytest.raises(IllegalTransition) as ei:
            check_transition(old, new, "do it")
        assert isinstance(ei.value, UsageError)
        assert f"while {old.value}" in str(ei.value)


def test_terminal_states_have_no_way_out() -> None:
    assert {s for s in S if s.terminal} == {S.COMPLETED, S.COMPLETED_WITH_GAPS, S.FAILED, S.ABORTED}
    assert all(not TRANSITIONS[s] for s in S if s.terminal)


def _ev(bus: EventBus, cls=Progress, **kw):
    return cls(seq=bus.next_seq(), time_s=0.0, wall=0.0, **kw)


def test_bus_sequence_numbers_history_and_bad_subscribers() -> None:
    bus = EventBus(history=5)
    got: list[int] = []
    bus.subscribe(lambda e: (_ for _ in ()).throw(RuntimeError("broken subscriber")))
    unsub = bus.subscribe(lambda e: got.append(e.seq))
    for _ in range(8):
        bus.publish(_ev(bus))
    assert got == list(range(1, 9))
    assert [e.seq for e in bus.since(5)] == [6, 7, 8]
    assert [e.seq for e in bus.since(0)] == [4, 5, 6, 7, 8]  # history is bounded
    unsub()
    bus.publish(_ev(bus))
    assert got[-1] == 8


def test_listener_in_another_thread_gets_every_event_in_order() -> None:
    bus = EventBus()
    lst = bus.listen(maxsize=10_000)
    seen: list[int] = []
    t = threading.Thread(target=lambda: seen.extend(e.seq for e in lst))
    t.start()
    for i in range(500):
        bus.publish(_ev(bus, StateChanged, old=S.IDLE, new=S.RUNNING) if i == 0 else _ev(bus))
    bus.close()
    t.join(timeout=10)
    assert seen == list(range(1, 501))
    d = _ev(bus, FaultRecorded, fault=FaultInfo(1.0, "timeout", "retry", "late")).to_dict()
    assert d["kind"] == "fault" and d["fault"]["fault_class"] == "timeout"


def test_slow_listener_loses_oldest_and_says_so() -> None:
    bus = EventBus()
    lst = bus.listen(maxsize=3)
    for _ in range(10):
        bus.publish(_ev(bus))
    assert lst.lost == 7
    assert [lst.get(0).seq for _ in range(3)] == [8, 9, 10]
    assert lst.get(timeout=0) is None


# -- fault policy ---------------------------------------------------------------------


def _actions(policy: FaultPolicy, fc: str, n: int) -> list[str]:
    return [policy.decide(fc, i).action for i in range(1, n + 1)]


def test_default_policy_per_fault_class() -> None:
    p = FaultPolicy()
    assert _actions(p, "timeout", 4) == ["retry", "retry", "retry", "skip"]
    assert _actions(p, "protocol", 3) == ["retry", "retry", "skip"]
    assert _actions(p, "alarm", 2) == ["retry", "abort"]
    assert p.decide("alarm", 1).home
    assert _actions(p, "frame_incomplete", 4) == ["retry", "retry", "retry", "skip"]
    assert _actions(p, "device_gone", 3) == ["reconnect", "reconnect", "abort"]
    assert p.decide("device_gone", 1).reconnect
    assert _actions(p, "disk_full", 3) == ["suspend"] * 3
    assert _actions(p, "other", 1) == ["abort"]
    assert p.decide("no such class", 1).action == "abort"


def test_backoff_is_exponential_and_capped() -> None:
    r = FaultRule(action="retry", attempts=6, backoff_s=0.5, backoff_factor=3, max_backoff_s=10)
    assert [r.backoff(i) for i in range(1, 6)] == [0.5, 1.5, 4.5, 10, 10]
    p = FaultPolicy(timeout=r)
    assert [p.decide("timeout", i).delay_s for i in (1, 2, 3)] == [0.5, 1.5, 4.5]


def test_policy_is_data_and_rejects_nonsense() -> None:
    p = FaultPolicy.model_validate({"timeout": {"action": "abort"}})
    assert p.decide("timeout", 1).action == "abort"
    assert p.decide("protocol", 1).action == "retry"  # the rest keep their defaults
    assert FaultPolicy.model_validate_json(p.model_dump_json()) == p
    with pytest.raises(ValidationError):
        FaultPolicy.model_validate({"timeout": {"action": "retry", "attempts": 0}})
    with pytest.raises(ValidationError):
        FaultPolicy.model_validate({"gremlins": {"action": "skip"}})
    with pytest.raises(ValidationError):
        FaultPolicy.model_validate({"timeout": {"action": "ignore"}})


def test_fault_class_of() -> None:
    from m2s2hil.drivers.errors import DeviceGone, DeviceTimeout, FrameIncomplete, MoveNotVerified

    from m2s2hil.atomic import DiskFull

    assert fault_class_of(DeviceTimeout("x")) == "timeout"
    assert fault_class_of(DeviceGone("x")) == "device_gone"
    assert fault_class_of(FrameIncomplete("x")) == "frame_incomplete"
    assert fault_class_of(MoveNotVerified("x", target=1, actual=2)) == "alarm"
    assert fault_class_of(DiskFull("/data")) == "disk_full"
    assert fault_class_of(ValueError("bug")) == "other"


# -- continuous-mode geometry ----------------------------------------------------------


def test_angle_track_interpolates_and_extrapolates() -> None:
    tr = AngleTrack()
    for t in (0.0, 0.1, 0.2, 0.3):
        tr.add(t, 5.0 + 10.0 * t)
    assert tr.angle_at(0.15) == pytest.approx(6.5)
    assert tr.angle_at(0.5) == pytest.approx(10.0)
    assert tr.speed() == pytest.approx(10.0)
    with pytest.raises(ValueError):
        AngleTrack().angle_at(0.0)


def test_timestamp_mapper_uses_the_latency_floor() -> None:
    m = TimestampMapper()
    for dev, host in ((1.0, 11.05), (2.0, 12.02), (3.0, 13.09)):
        m.observe(dev, host)
    assert m.host_time(4.0) == pytest.approx(14.02)


@pytest.mark.parametrize("direction", [1, -1])
def test_mark_matcher_keeps_the_nearest_frames(direction: int) -> None:
    marks = [(a, f"m{a}") for a in (0.0, 10.0, 20.0)]
    step = 0.37
    angles = [direction * (-3 + i * step) + (20.0 if direction < 0 else 0.0) for i in range(80)]
    mm = MarkMatcher(marks, direction, k=2, window_deg=5)
    out = []
    peak_held = 0
    for i, a in enumerate(angles):
        out += mm.offer(a, i)
        peak_held = max(peak_held, mm.held())
    out += mm.flush()
    assert mm.done() and [m.key for m in out] == [k for _, k in sorted(marks, key=lambda m: direction * m[0])]
    for m in out:
        assert m.complete and len(m.frames) == 2
        best = sorted(range(len(angles)), key=lambda i: abs(angles[i] - m.mark_deg))[:2]
        assert sorted(m.frames) == sorted(best)
        assert abs(m.error_deg) <= step
    assert peak_held <= 2 * 2  # never more than k frames per mark in the window


def test_mark_left_behind_without_frames_is_reported_incomplete() -> None:
    mm = MarkMatcher([(0.0, "a"), (10.0, "b")], 1, k=1, window_deg=2)
    out = mm.offer(-1.0, "f0") + mm.offer(12.5, "f1")  # a gap over mark 10
    assert [(m.key, m.complete) for m in out] == [("a", True), ("b", False)]


def test_blur_and_run_up() -> None:
    b = blur_estimate(30.0, 0.01, radius_px=400)
    assert b.deg == pytest.approx(0.3)
    assert b.px_at_radius == pytest.approx(400 * 0.3 * 3.141592653589793 / 180)
    assert run_up_deg(60, 120, margin_s=0) == pytest.approx(15.0)


# -- automatic exposure search (a linear sensor with black level, noise and clipping) ---------


def _sensor(rate_dn_per_s: float, black: float = 40.0, seed: int = 0):
    rng = np.random.default_rng(seed)
    scene = rng.gamma(2.0, 1.0, size=(128, 128))
    scene /= np.percentile(scene, 99.9)

    def measure(t: float) -> np.ndarray:
        signal = black + scene * rate_dn_per_s * t + rng.normal(0, 2, scene.shape)
        return np.clip(signal, 0, 1023).astype(np.uint16)

    return measure


@pytest.mark.parametrize("rate", [2e3, 3e4, 1e6])  # too dark, about right, saturated at the start
def test_exposure_search_lands_just_under_the_limit(rate: float) -> None:
    res = find_exposure(_sensor(rate), full_scale=1023, start_s=0.01, max_frames=6)
    assert res.converged and res.frames <= 5
    assert 0.83 * 1023 <= res.level < 0.9 * 1023
    longest = (0.9 * 1023 - 40) / rate  # where the (noise-free) 99.9th percentile hits the limit
    assert 0.88 * longest <= res.exposure_s <= longest


def test_exposure_search_reports_its_limits() -> None:
    dim = find_exposure(_sensor(50.0), full_scale=1023, max_s=5.0)
    assert dim.limited == "max_exposure" and dim.exposure_s == 5.0 and not dim.converged
    glare = find_exposure(_sensor(1e9), full_scale=1023, min_s=100e-6, max_frames=8)
    assert glare.limited == "min_exposure" and glare.exposure_s == 100e-6
    with pytest.raises(ValueError):
        find_exposure(_sensor(1e3), full_scale=1023, aim=0.95)


def test_percentile_from_histogram_matches_numpy() -> None:
    data = np.random.default_rng(1).integers(0, 1024, size=(64, 64), dtype=np.uint16)
    assert percentile_dn(data, 99.9, 1023) == pytest.approx(np.percentile(data, 99.9), abs=1)
