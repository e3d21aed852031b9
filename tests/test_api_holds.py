"""A hold (emergency stop, operator hold, failed session) is kept on the data root: written before
it is acknowledged, in force after kill -9 and a restart (also of an interrupted session resumed
with --resume) until an operator releases it; a damaged hold file holds too."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import pytest
from api_support import DaemonProcess, daemon, long_sweep, quick_rig_file, sweep

from m2s2hil.daemon.hold import HOLD_NAME, HoldFile
from m2s2hil.store.session import SessionStore

#: Realtime sessions on quick_rig_file's rig: LONG runs long enough to act on, SHORT ends in seconds.
LONG = {"satellite": "iss", "build": "B2", "lighting": ["weak"], "tilts": ["E0", "E1", "E2"],
        "azimuth_step_deg": 30, "dark": {"frames": 1}}
SHORT = {"satellite": "iss", "build": "B2", "lighting": ["weak"], "tilts": ["E1"], "azimuth_step_deg": 120,
         "dark": {"frames": 1}}


# ---------------------------------------------------------------------------------- the file
def test_hold_file_round_trip_and_release(tmp_path) -> None:
    hf = HoldFile(tmp_path)
    assert hf.load() is None
    saved = hf.save("mockup swap", since=1_800_000_000.0)
    back = hf.load()
    assert back is not None and back.reason == "mockup swap" and back.since == saved.since
    assert back.damaged is None and back.since_iso == "2027-01-15T08:00:00Z"
    assert json.loads((tmp_path / HOLD_NAME).read_text())["reason"] == "mockup swap"
    assert [p.name for p in tmp_path.iterdir()] == [HOLD_NAME]  # no temporary file left
    hf.clear()
    assert hf.load() is None and not (tmp_path / HOLD_NAME).exists()
    hf.clear()  # nothing to release: fine


@pytest.mark.parametrize("content", [b"", b"{\"reason\": \"emergency st", b"\xff\xfe", b"[1, 2]",
                                     b'{"reason": "", "since_unix": 1}', b'{"reason": "x"}',
                                     b'{"reason": "x", "since_unix": "yesterday"}'],
                         ids=["empty", "truncated", "not-utf8", "not-an-object", "no-reason", "no-since",
                              "bad-since"])
def test_a_damaged_hold_file_still_holds(tmp_path, content) -> None:
    (tmp_path / HOLD_NAME).write_bytes(content)
    hold = HoldFile(tmp_path).load()
    assert hold is not None and hold.damaged
    assert "is damaged" in hold.reason and "held until released" in hold.reason


# ---------------------------------------------------------------------------------- in process
def test_hold_and_stop_are_on_disk_when_acknowledged_and_release_removes_them(tmp_path) -> None:
    root = tmp_path / "data"
    with daemon(root) as d:
        assert d.client.post("/queue/hold", params={"reason": "mockup swap"}).json()["held"] == "mockup swap"
        on_disk = HoldFile(root).load()
        assert on_disk is not None and on_disk.reason == "mockup swap"
        assert d.client.post("/queue/release").json()["held"] is None
        assert HoldFile(root).load() is None

        assert d.client.post("/rig/stop").json()["errors"] == []
        on_disk = HoldFile(root).load()
        assert on_disk is not None and on_disk.reason == "emergency stop"


def test_a_daemon_starts_held_by_what_the_last_one_left(tmp_path, caplog) -> None:
    root = tmp_path / "data"
    HoldFile(root).save("emergency stop", since=1_800_000_000.0)
    with caplog.at_level(logging.WARNING), daemon(root) as d:
        assert d.client.get("/queue").json()["held"] == "emergency stop"
        assert d.client.get("/healthz").json()["status"] == "degraded"
        sid = d.client.post("/sessions", json=sweep()).json()["session_id"]
        assert d.client.get(f"/sessions/{sid}").json()["state"] == "queued"
        held_lines = [r.getMessage() for r in caplog.records if "rig HELD" in r.getMessage()]
        assert held_lines == ["rig HELD since 2027-01-15T08:00:00Z: emergency stop; no session starts "
                              "until an operator releases it (POST /queue/release)"]
        d.client.post("/queue/release")
        assert d.wait_done(sid)["state"] == "completed"


def test_a_damaged_hold_file_holds_with_a_clear_line_and_no_traceback(tmp_path, caplog) -> None:
    root = tmp_path / "data"
    root.mkdir()
    (root / HOLD_NAME).write_bytes(b'{"reason": "emergency st')  # cut short by a power loss
    with caplog.at_level(logging.WARNING), daemon(root) as d:
        held = d.client.get("/queue").json()["held"]
        assert held.startswith(f"the hold file {root / HOLD_NAME} is damaged (not JSON")
        sid = d.client.post("/sessions", json=sweep()).json()["session_id"]
        assert d.client.get(f"/sessions/{sid}").json()["state"] == "queued"
        lines = [r for r in caplog.records if "rig HELD" in r.getMessage()]
        assert len(lines) == 1 and lines[0].levelno == logging.ERROR and lines[0].exc_info is None
        assert "is damaged (not JSON" in lines[0].getMessage() and "fail safe" in lines[0].getMessage()
        assert d.client.post("/queue/release").json()["held"] is None
        assert not (root / HOLD_NAME).exists()
        assert d.wait_done(sid)["state"] == "completed"


def test_a_hold_that_cannot_be_saved_is_refused_loudly_and_holds_anyway(tmp_path) -> None:
    root = tmp_path / "data"
    (root / HOLD_NAME).mkdir(parents=True)  # the rename onto it fails, as a read-only disk would
    (root / HOLD_NAME / "x").write_text("keeps the folder from being removed")
    with daemon(root) as d:
        held = d.client.get("/queue").json()["held"]
        assert held.startswith(f"the hold file {root / HOLD_NAME} is damaged")
        r = d.client.post("/queue/release")  # cannot remove a folder: stays held
        assert r.status_code == 500 and "could not be removed" in r.json()["detail"]
        assert d.client.get("/queue").json()["held"] is not None
        r = d.client.post("/queue/hold", params={"reason": "mockup swap"})
        detail = r.json()["detail"]
        assert r.status_code == 500
        assert "could not be saved" in detail and "would not survive a restart" in detail
        assert d.client.get("/queue").json()["held"] == "mockup swap"  # in force in this process
        rep = d.client.post("/rig/stop").json()  # the stop itself goes on, and says what failed
        assert rep["safe"] is True and any("could not be saved" in e for e in rep["errors"])


def test_a_failed_sessions_hold_is_on_disk(tmp_path) -> None:
    root = tmp_path / "data"
    with daemon(root, faults={"stage": [{"kind": "alarm", "count": 2, "after": 2}]}) as d:
        sid = d.client.post("/sessions", json=sweep()).json()["session_id"]
        assert d.wait_done(sid)["state"] == "failed"
        assert d.manager.job(sid).finished.wait(10)  # its end handled: held, on disk, then finished
        on_disk = HoldFile(root).load()
        assert on_disk is not None and on_disk.reason.startswith(f"session {sid} failed: StageAlarm")
        assert d.client.get("/queue").json()["held"] == on_disk.reason


def test_an_emergency_stop_replaces_an_operator_hold_on_disk(tmp_path) -> None:
    with daemon(tmp_path / "data") as d:
        sid = d.client.post("/sessions", json=long_sweep()).json()["session_id"]
        d.wait(sid, lambda s: s["state"] == "running" and s["done"] >= 2)
        d.client.post("/queue/hold", params={"reason": "look"})
        d.client.post("/rig/stop")
        assert d.client.get("/queue").json()["held"] == "emergency stop"
        assert HoldFile(tmp_path / "data").load().reason == "emergency stop"


# ---------------------------------------------------------------------------------- real processes
def _journal(root: Path, sid: str) -> tuple[str, int, int]:
    """(state, runs started, frames stored) as the session's journal says."""
    store = SessionStore.open(root, sid)
    try:
        runs = sum(1 for e in store.events() if e["kind"] == "run_started")
        return store.state, runs, len(store.frames())
    finally:
        store.close()


def _pose(d: DaemonProcess) -> dict:
    rig = d.http.get("/rig").json()
    stage = next(x for x in rig["devices"] if x["name"] == "stage")
    assert stage["health"] == "ok", rig  # not "busy": no session owns the rig
    return stage["state"]


def _stays_held(d: DaemonProcess, root: Path, waiting: list[str], reason: str) -> None:
    """For a few seconds (a dispatcher starts a session within milliseconds): still held, nothing
    running, the waiting sessions queued with no run started, the stage where it was."""
    pose = _pose(d)
    journals = {sid: _journal(root, sid) for sid in waiting}
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:
        q = d.http.get("/queue").json()
        assert q["held"] == reason and q["running"] is None
        assert [i["session_id"] for i in q["items"]] == waiting
        time.sleep(0.2)
    assert _pose(d) == pose
    assert {sid: _journal(root, sid) for sid in waiting} == journals


@pytest.mark.slow  # two daemon processes and realtime sessions: about a minute
def test_an_emergency_stop_survives_kill_9_and_a_restart(tmp_path) -> None:
    rig = quick_rig_file(tmp_path)
    root = tmp_path / "data"
    with DaemonProcess(tmp_path, rig) as d:
        stopped = d.http.post("/sessions", json=LONG).json()["session_id"]
        waiting = [d.http.post("/sessions", json=SHORT).json()["session_id"] for _ in range(2)]
        d.wait(stopped, lambda s: s["state"] == "running" and s["done"] >= 2)
        rep = d.http.post("/rig/stop").json()
        assert rep["safe"] is True and rep["session_id"] == stopped and rep["errors"] == []
        d.kill()  # right after the acknowledgement: nothing else was written
    assert HoldFile(root).load().reason == "emergency stop"
    assert _journal(root, stopped)[0] == "estopped"
    assert [_journal(root, sid) for sid in waiting] == [("queued", 0, 0)] * 2

    with DaemonProcess(tmp_path, rig, "--resume") as d:
        log = d.log.read_text()
        assert "rig HELD since " in log and ": emergency stop; no session starts until an operator " \
               "releases it (POST /queue/release)" in log
        assert d.http.get("/healthz").json()["held"] == "emergency stop"
        _stays_held(d, root, waiting, "emergency stop")
        # Homing is motion too: the axes with switches were not homed at the held start.
        assert "axes with switches are not homed now" in d.log.read_text()
        assert "deferred while the rig was held" not in d.log.read_text()
        r = d.http.post(f"/sessions/{stopped}/resume")
        assert r.status_code == 409 and "POST /queue/release" in r.json()["detail"]

        assert d.http.post("/queue/release").json()["held"] is None
        for sid in waiting:
            st = d.wait(sid, lambda s: s["state"] in ("completed", "failed", "aborted"))
            assert st["state"] == "completed"
        assert "homed turntable, tilt (deferred while the rig was held)" in d.log.read_text()
        d.stop()
    assert not (root / HOLD_NAME).exists()
    assert [_journal(root, sid)[:2] for sid in waiting] == [("completed", 1)] * 2


@pytest.mark.slow  # two daemon processes and realtime sessions: about a minute
def test_a_hold_survives_kill_9_of_a_running_session_and_holds_its_resumption(tmp_path) -> None:
    rig = quick_rig_file(tmp_path)
    root = tmp_path / "data"
    with DaemonProcess(tmp_path, rig) as d:
        # 12 frames: on a loaded machine the session must not finish between the hold and the kill
        sid = d.http.post("/sessions", json=SHORT | {"azimuth_step_deg": 30}).json()["session_id"]
        d.wait(sid, lambda s: s["state"] == "running" and s["done"] >= 2)
        assert d.http.post("/queue/hold", params={"reason": "mockup swap"}).json()["held"] == "mockup swap"
        d.kill()  # mid-session: the journal still says running
    state, runs, frames = _journal(root, sid)
    assert state == "running" and runs == 1 and 1 <= frames < 12

    with DaemonProcess(tmp_path, rig, "--resume") as d:
        log = d.log.read_text()
        assert f"resuming 1 interrupted session(s): {sid}" in log
        assert ": mockup swap; no session starts until an operator releases it" in log
        assert _journal(root, sid)[0] == "queued"
        _stays_held(d, root, [sid], "mockup swap")
        assert _journal(root, sid)[1:] == (runs, frames)  # no second run, no new frame

        d.http.post("/queue/release")
        st = d.wait(sid, lambda s: s["state"] in ("completed", "completed_with_gaps", "failed", "aborted"))
        assert st["state"] == "completed" and st["done"] == st["total"] == 13
        d.stop()
    store = SessionStore.open(root, sid)
    try:
        ids = [f.event_id for f in store.frames()]
        planned = {e.event_id for e in store.sweep.expand(store.rig) if e.kind == "frame"}
    finally:
        store.close()
    assert sorted(ids) == sorted(planned) and len(ids) == 12  # every planned frame once
