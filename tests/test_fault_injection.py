"""Fault plans: counts, ``after`` and seeded ``rate`` rules."""

import pytest
from m2s2hil.simulators.fault_injection import FAULT_KINDS, FAULT_KINDS_BY_DEVICE, FaultPlan


def _fired(plan: FaultPlan, kind: str, n: int) -> list[int]:
    return [i for i in range(n) if plan.take(kind) is not None]


def test_count_and_after():
    plan = FaultPlan()
    plan.add("stall", after=2, count=2, fraction=0.25)
    assert _fired(plan, "stall", 10) == [2, 3]
    assert plan.log == [("stall", {"fraction": 0.25})] * 2
    assert not plan.pending("stall")


def test_rate_fires_about_that_often_forever_and_is_seeded():
    plan = FaultPlan(seed=7)
    plan.add("garble", rate=0.3)
    hits = _fired(plan, "garble", 2000)
    assert 480 <= len(hits) <= 720  # binomial(2000, 0.3): 600 ± 5.8 σ
    assert plan.pending("garble")  # a rate without a count never runs out
    again = FaultPlan(seed=7)
    again.add("garble", rate=0.3)
    assert _fired(again, "garble", 2000) == hits
    other = FaultPlan(seed=8)
    other.add("garble", rate=0.3)
    assert _fired(other, "garble", 2000) != hits


def test_rate_with_count_and_after():
    plan = FaultPlan(seed=1)
    plan.add("drop_reply", rate=0.5, count=3, after=10)
    hits = _fired(plan, "drop_reply", 200)
    assert len(hits) == 3 and hits[0] >= 10


@pytest.mark.parametrize(("kw", "match"), [
    ({"kind": "bogus"}, "unknown fault kind"),
    ({"kind": "garble", "rate": 0.0}, "rate"),
    ({"kind": "garble", "rate": 1.5}, "rate"),
    ({"kind": "garble", "count": -2}, "count"),
])
def test_bad_rules_are_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        FaultPlan().add(**kw)


def test_from_config_takes_rate():
    plan = FaultPlan.from_config([{"kind": "late_reply", "rate": 1.0, "delay_s": 0.5}], seed=3)
    assert [plan.take("late_reply") for _ in range(3)] == [{"delay_s": 0.5}] * 3


def test_the_kind_table_matches_what_the_simulators_ask_for():
    """Every kind a simulator takes is in the table, and every kind in the table is taken."""
    import re
    from pathlib import Path

    import m2s2hil.simulators

    src = Path(m2s2hil.simulators.__file__).parent
    asked = set()
    for path in src.glob("*.py"):
        asked |= set(re.findall(r'faults\.(?:take|pending)\("([a-z_]+)"\)', path.read_text()))
        for group in re.findall(r"faults\.pending\(k\) for k in \(([^)]*)\)", path.read_text()):
            asked |= set(re.findall(r'"([a-z_]+)"', group))
    assert asked == FAULT_KINDS
    assert set(FAULT_KINDS_BY_DEVICE) == {"grbl", "zaber", "modbus-rtu", "ascii-relay", "u3v"}
