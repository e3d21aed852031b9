"""GET /rig, the emergency stop during a running session, /healthz and /metrics."""

from __future__ import annotations

import re

import pytest
from api_support import daemon, long_sweep, sweep


def _metrics(text: str) -> dict[str, float]:
    """Prometheus text -> {"name{labels}": value}; checks every line is well formed on the way."""
    out: dict[str, float] = {}
    typed: set[str] = set()
    for line in text.splitlines():
        if line.startswith("# TYPE "):
            _, _, name, kind = line.split(" ")
            assert kind in ("counter", "gauge", "histogram")
            typed.add(name)
            continue
        if line.startswith("# HELP ") or not line:
            continue
        m = re.fullmatch(r'([a-z_:][a-z0-9_:]*)(\{(?:[a-z_]+="[^"]*",?)*\})? (\S+)', line)
        assert m, f"malformed sample line {line!r}"
        base = re.sub(r"_(bucket|sum|count)$", "", m.group(1))
        assert m.group(1) in typed or base in typed, f"{line!r} has no # TYPE"
        out[m.group(1) + (m.group(2) or "")] = float(m.group(3))
    return out


def test_rig_state_when_idle(tmp_path) -> None:
    with daemon(tmp_path / "data") as d:
        rig = d.client.get("/rig").json()
        assert rig["simulated"] is True and rig["session_id"] is None and rig["held"] is None
        dev = {x["name"]: x for x in rig["devices"]}
        assert set(dev) == {"stage", "relays", "camera"}
        assert all(x["health"] == "ok" for x in dev.values())
        assert dev["stage"]["state"]["turntable_moving"] is False
        assert dev["stage"]["state"]["tilt_deg"] == d.rig.world.pose().tilt_deg
        assert dev["relays"]["state"]["lamps_on"] == []
        assert dev["camera"]["state"]["width"] == 256 and dev["camera"]["state"]["temperature_c"] > 0


@pytest.mark.slow  # ~3-4 s each
@pytest.mark.parametrize("grace_s", [0.5, 0.0], ids=["engine-teardown", "stop-from-request"])
def test_emergency_stop_during_a_session_leaves_lamps_off_and_stage_stopped(tmp_path, grace_s) -> None:
    # grace 0: the request thread stops the axes itself while the engine is still mid-capture
    with daemon(tmp_path / "data", estop_grace_s=grace_s) as d:
        sid = d.client.post("/sessions", json=long_sweep()).json()["session_id"]
        nxt = d.client.post("/sessions", json=sweep()).json()["session_id"]
        d.wait(sid, lambda s: s["state"] == "running" and s["done"] >= 3)
        assert d.rig.world.lamps_on()  # lit while capturing
        busy = d.client.get("/rig").json()
        assert busy["session_id"] == sid and {x["health"] for x in busy["devices"]} == {"busy"}

        r = d.client.post("/rig/stop")
        assert r.status_code == 200
        rep = r.json()
        assert rep["safe"] is True and rep["lamps_on"] == [] and rep["errors"] == []
        assert rep["moving"] == {"turntable": False, "tilt": False}
        assert rep["session_id"] == sid and rep["session_state"] == "aborted"
        # what the simulated world says, not only what the drivers report
        assert d.rig.world.lamps_on() == frozenset()
        assert not d.rig.turntable.is_moving() and not d.rig.tilt.is_moving()
        st = d.client.get(f"/sessions/{sid}").json()
        # stopped, not given up: its status says so as its journal does, and it may be resumed later
        assert st["state"] == "estopped" and st["resumable"] and st["done"] < st["total"]

        # the queue is held: the next session waits until an operator releases it
        assert d.client.get(f"/sessions/{nxt}").json()["state"] == "queued"
        health = d.client.get("/healthz").json()
        assert health["status"] == "degraded" and health["held"] == "emergency stop"
        assert d.client.post("/queue/release").json()["held"] is None
        assert d.wait_done(nxt)["state"] == "completed"


def test_metrics_count_frames_faults_queue_and_durations(tmp_path) -> None:
    # one frame the simulated camera never sends: a fault the engine's policy retries
    faults = {"toucan": [{"kind": "frame_timeout", "count": 1, "after": 2}]}
    with daemon(tmp_path / "data", faults=faults) as d:
        m0 = _metrics(d.client.get("/metrics").text)
        assert m0["m2s2hil_frames_captured_total"] == 0
        assert m0['m2s2hil_faults_total{fault_class="timeout"}'] == 0
        sid = d.client.post("/sessions", json=sweep()).json()["session_id"]
        st = d.wait_done(sid)
        assert st["state"] == "completed"
        d.manager.hold("test")
        for _ in range(2):
            d.client.post("/sessions", json=sweep())
        r = d.client.get("/metrics")
        assert r.headers["content-type"].startswith("text/plain; version=0.0.4")
        m = _metrics(r.text)
        assert m["m2s2hil_frames_captured_total"] == 4
        faults = {k: v for k, v in m.items() if k.startswith("m2s2hil_faults_total")}
        assert sum(faults.values()) == len(st["faults"]) >= 1
        assert m['m2s2hil_faults_total{fault_class="timeout"}'] == sum(
            f["fault_class"] == "timeout" for f in st["faults"])
        assert m['m2s2hil_sessions_finished_total{state="completed"}'] == 1
        assert m["m2s2hil_session_duration_seconds_count"] == 1
        assert m["m2s2hil_session_duration_seconds_sum"] == st["elapsed_s"]
        assert m['m2s2hil_session_duration_seconds_bucket{le="+Inf"}'] == 1
        assert m['m2s2hil_queue_depth{queue="sessions"}'] == 2
        assert m["m2s2hil_queue_held"] == 1 and m["m2s2hil_sessions_running"] == 0


def test_a_failed_session_holds_the_queue(tmp_path) -> None:
    # two stage alarms: the policy homes and retries once, then gives the session up
    with daemon(tmp_path / "data", faults={"stage": [{"kind": "alarm", "count": 2, "after": 2}]}) as d:
        first = d.client.post("/sessions", json=sweep()).json()["session_id"]
        second = d.client.post("/sessions", json=sweep()).json()["session_id"]
        st = d.wait_done(first)
        assert st["state"] == "failed" and "StageAlarm" in st["error"]
        assert [f["action"] for f in st["faults"]] == ["home+retry", "abort"]
        q = d.client.get("/queue").json()
        assert q["held"].startswith(f"session {first} failed: StageAlarm")
        assert [i["session_id"] for i in q["items"]] == [second]  # waits for an operator
        assert d.client.get("/healthz").json()["status"] == "degraded"
        assert d.rig.world.lamps_on() == frozenset()  # the failure left the rig safe
        d.client.post("/queue/release")
        assert d.wait_done(second)["state"] == "completed"


def test_the_state_filter_finds_what_the_list_shows(tmp_path) -> None:
    # an e-stopped session this daemon still knows: its engine ended "aborted", it is "estopped"
    with daemon(tmp_path / "data") as d:
        sid = d.client.post("/sessions", json=long_sweep()).json()["session_id"]
        d.wait(sid, lambda s: s["state"] == "running" and s["done"] >= 2)
        assert d.client.post("/rig/stop").json()["session_state"] == "aborted"
        listed = {s["session_id"]: s["state"] for s in d.client.get("/sessions").json()["items"]}
        assert listed == {sid: "estopped"}
        page = d.client.get("/sessions", params={"state": "estopped"}).json()
        assert page["total"] == 1 and [s["session_id"] for s in page["items"]] == [sid]
        assert d.client.get("/sessions", params={"state": "aborted"}).json()["total"] == 0
