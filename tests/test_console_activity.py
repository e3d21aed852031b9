"""The daemon's activity log and its other-clients view (issue 24): operator actions with who and
from where, faults, retries, state changes and a session's failure, paging with ``since``."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from api_support import daemon, sweep

from m2s2hil.daemon.activity import ActivityLog, Actor

ORIGIN = "http://127.0.0.1:8750"


@pytest.fixture(scope="module")
def d(tmp_path_factory: pytest.TempPathFactory) -> Iterator:
    root: Path = tmp_path_factory.mktemp("activity") / "data"
    # two stage alarms: the policy homes and retries once, then gives the session up
    with daemon(root, faults={"stage": [{"kind": "alarm", "count": 2, "after": 2}]}) as dd:
        yield dd


def tab(name: str) -> dict[str, str]:
    return {"X-M2S2HIL-Client": name, "Origin": ORIGIN}


def test_an_operator_action_is_logged_with_who_and_from_where(d) -> None:
    since = d.client.get("/activity").json()["last_seq"]
    assert d.client.put("/rig/lamps", json={"preset": "weak"}, headers=tab("tab-a")).status_code == 200
    refused = d.client.put("/rig/lamps", json={"lamps": ["nope"]}, headers=tab("tab-a"))
    assert refused.status_code == 422
    d.client.get("/rig/axes", headers=tab("tab-b"))  # a viewer: seen, not an action
    d.client.post("/plans/estimate", json=sweep(), headers=tab("tab-b"))  # computes only: not an action
    page = d.client.get("/activity", params={"since": since, "kind": "action"}).json()
    ok, bad = page["items"]
    assert ok["message"].startswith("lamps on: bar1, bar2, bar3") and "PUT /rig/lamps → 200" in ok["message"]
    assert ok["actor"]["client"] == "tab-a" and ok["actor"]["origin"] == ORIGIN
    assert ok["actor"]["address"] and ok["actor"]["authenticated"] is False
    assert bad["level"] == "warning" and bad["details"]["status"] == 422
    assert page["last_seq"] >= bad["seq"] and page["gap"] is False
    again = d.client.get("/activity", params={"since": page["last_seq"], "kind": "action"}).json()
    assert again["items"] == []
    assert d.client.get("/activity", params={"kind": "nonsense"}).status_code == 422


def test_other_clients_are_counted_and_who_controls_is_named(d) -> None:
    d.client.put("/rig/lamps", json={"preset": None}, headers=tab("tab-a"))
    d.client.get("/queue", headers=tab("tab-b"))
    seen_by_b = d.client.get("/activity/clients", headers=tab("tab-b")).json()
    rows = {r["client"]: r for r in seen_by_b["clients"]}
    assert rows["tab-b"]["you"] and not rows["tab-a"]["you"]
    assert rows["tab-a"]["controlling"] and rows["tab-a"]["last_action"] == "PUT /rig/lamps"
    assert not rows["tab-b"]["controlling"]
    assert seen_by_b["others_controlling"] >= 1 and seen_by_b["others_connected"] >= 1
    seen_by_a = d.client.get("/activity/clients", headers=tab("tab-a")).json()
    assert {r["client"]: r["you"] for r in seen_by_a["clients"] if r["client"]}["tab-a"] is True
    assert seen_by_a["others_controlling"] == seen_by_b["others_controlling"] - 1


def test_faults_retries_state_changes_and_a_failed_session_are_logged(d) -> None:
    since = d.client.get("/activity").json()["last_seq"]
    sid = d.client.post("/sessions", json=sweep()).json()["session_id"]
    assert d.wait_done(sid)["state"] == "failed"
    items = d.client.get("/activity", params={"since": since, "session_id": sid}).json()["items"]
    kinds = [a["kind"] for a in items]
    assert "retry" in kinds and "fault" in kinds and "state" in kinds
    retry = next(a for a in items if a["kind"] == "retry")
    assert retry["details"]["fault_class"] and "attempt" in retry["message"]
    assert any(a["kind"] == "session" and "started" in a["message"] for a in items)
    end = [a for a in items if a["kind"] == "session"][-1]
    assert end["level"] == "error" and "failed" in end["message"] and "StageAlarm" in end["message"]
    held = d.client.get("/activity", params={"since": since, "kind": "queue"}).json()["items"]
    assert any("queue held" in a["message"] for a in held)
    d.client.post("/queue/release")
    page = d.client.get("/activity", params={"since": since, "kind": ["queue", "action"]}).json()
    last = page["items"][-2:]
    assert "queue released" in last[0]["message"] and "POST /queue/release → 200" in last[1]["message"]


def test_the_ring_is_bounded_and_paging_reports_a_gap() -> None:
    log = ActivityLog(capacity=5)
    for i in range(8):
        log.record("state", f"entry {i}")
    items, next_seq, gap = log.since(0)
    assert [a.seq for a in items] == [4, 5, 6, 7, 8] and gap and next_seq == 8
    items, next_seq, gap = log.since(5, limit=2)
    assert [a.seq for a in items] == [6, 7] and next_seq == 7 and not gap
    assert log.since(7)[0][0].message == "entry 7"
    assert log.since(99)[2] is True  # a seq from before this daemon started: start again from 0
    me = Actor(address="10.0.0.2", user_agent="curl")
    log.seen(me, "POST /rig/stop")
    view = log.clients(me)
    assert view["others_connected"] == 0 and view["clients"][0]["you"] and view["clients"][0]["controlling"]
