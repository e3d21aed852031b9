"""Server-Sent Events: content, Last-Event-ID resumption, live streaming over a real socket,
journal replay after a restart."""

from __future__ import annotations

import json
import time

import httpx
import pytest
from api_support import daemon, long_sweep, parse_sse, small_rig_config, sweep, uvicorn_thread

from m2s2hil.api.sse import Cursor, parse_last_event_id


def _seqs(msgs: list[dict]) -> list[int]:
    return [int(m["id"].split("-")[1]) for m in msgs if "id" in m]


def test_events_of_a_session_in_order(tmp_path) -> None:
    with daemon(tmp_path / "data") as d:
        sid = d.client.post("/sessions", json=sweep()).json()["session_id"]
        d.wait_done(sid)
        r = d.client.get(f"/sessions/{sid}/events")
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/event-stream")
        msgs = parse_sse(r.text)
        seqs = _seqs(msgs)
        assert seqs == list(range(1, len(seqs) + 1))  # every event, once, in order
        assert all(m["id"].startswith("1-") for m in msgs)
        kinds = [m["event"] for m in msgs]
        assert kinds[0] == "state" and kinds[-1] == "finished"
        frames = [json.loads(m["data"]) for m in msgs if m["event"] == "frame"]
        assert len(frames) == 4 and len({f["event_id"] for f in frames}) == 4
        assert all(f["session_id"] == sid and f["run"] == 1 for f in frames)
        progress = [json.loads(m["data"])["done"] for m in msgs if m["event"] == "progress"]
        assert progress == sorted(progress) and progress[-1] == 5
        final = json.loads(msgs[-1]["data"])
        assert final["state"] == "completed" and final["done"] == final["total"] == 5

        # resumption: only what comes after the given id
        r = d.client.get(f"/sessions/{sid}/events", headers={"Last-Event-ID": f"1-{seqs[4]}"})
        assert _seqs(parse_sse(r.text)) == seqs[5:]
        r = d.client.get(f"/sessions/{sid}/events", headers={"Last-Event-ID": str(seqs[-2])})  # plain seq
        assert _seqs(parse_sse(r.text)) == seqs[-1:]
        r = d.client.get(f"/sessions/{sid}/events", headers={"Last-Event-ID": "garbage"})
        assert _seqs(parse_sse(r.text)) == seqs  # unreadable id: from the start
        assert d.client.get("/sessions/nope/events").status_code == 404


@pytest.mark.slow  # a real socket, a long session: ~22 s
@pytest.mark.timeout(600)  # generous: a loaded machine stretches it, it does not fail it
def test_live_stream_over_a_socket_resumes_without_loss_or_duplicates(tmp_path) -> None:
    # 64²: the capture QC of 108 frames is most of the test's CPU at 256² (22 s against 7 s)
    with daemon(tmp_path / "data", rig_config=small_rig_config(64)) as d:
        d.manager.hold("test")
        sid = d.client.post("/sessions", json=long_sweep()).json()["session_id"]
        with uvicorn_thread(d.client.app) as base, httpx.Client(base_url=base, timeout=30) as http:
            first: list[dict] = []
            with http.stream("GET", f"/sessions/{sid}/events") as resp:
                assert resp.status_code == 200
                buf = ""
                released = False
                deadline = time.monotonic() + 60
                for chunk in resp.iter_text():
                    assert time.monotonic() < deadline, f"stream stalled: {buf[-500:]!r}"
                    buf += chunk.replace("\r\n", "\n")
                    msgs = parse_sse(buf.rsplit("\n\n", 1)[0]) if "\n\n" in buf else []
                    if msgs and msgs[0]["event"] == "queued" and not released:
                        assert json.loads(msgs[0]["data"])["position"] == 1
                        d.manager.release()  # the session starts while we listen
                        released = True
                    if sum(m.get("event") == "frame" for m in msgs) >= 3:
                        first = msgs
                        break  # drop the connection mid-session
            last_id = [m for m in first if "id" in m][-1]["id"]
            r = http.get(f"/sessions/{sid}/events", headers={"Last-Event-ID": last_id})
            rest = parse_sse(r.text)
        seqs = _seqs(first) + _seqs(rest)
        assert seqs == list(range(1, len(seqs) + 1))
        assert rest[-1]["event"] == "finished"
        frames = [json.loads(m["data"])["event_id"] for m in first + rest if m.get("event") == "frame"]
        assert len(frames) == len(set(frames)) == 108


def test_replay_from_the_journal_after_a_restart(tmp_path) -> None:
    root = tmp_path / "data"
    with daemon(root) as d:
        sid = d.client.post("/sessions", json=sweep()).json()["session_id"]
        d.wait_done(sid)
    with daemon(root) as d:
        msgs = parse_sse(d.client.get(f"/sessions/{sid}/events").text)
        assert msgs[-1]["event"] == "end" and json.loads(msgs[-1]["data"])["state"] == "completed"
        ids = [m["id"] for m in msgs if "id" in m]
        assert ids == [f"j-{n}" for n in range(1, len(ids) + 1)]
        assert sum(m["event"] == "frame" for m in msgs) == 4
        assert [m["event"] for m in msgs if "id" in m][-1] == "finished"
        again = parse_sse(d.client.get(f"/sessions/{sid}/events", headers={"Last-Event-ID": "j-2"}).text)
        assert [m["id"] for m in again if "id" in m] == ids[2:]


def test_a_cancelled_session_ends_its_stream(tmp_path) -> None:
    with daemon(tmp_path / "data") as d:
        d.manager.hold("test")
        sid = d.client.post("/sessions", json=sweep()).json()["session_id"]
        d.client.post(f"/sessions/{sid}/abort")
        msgs = parse_sse(d.client.get(f"/sessions/{sid}/events").text)
        assert [m["event"] for m in msgs] == ["state"]
        assert json.loads(msgs[0]["data"])["new"] == "cancelled"


@pytest.mark.parametrize(("value", "cursor"), [
    ("2-17", Cursor(2, 17)), ("17", Cursor(0, 17)), ("j-4", Cursor(None, 4)), (" 1-0 ", Cursor(1, 0)),
    ("", None), (None, None), ("x-y", None), ("1-", None),
])
def test_last_event_id_parsing(value, cursor) -> None:
    assert parse_last_event_id(value) == cursor
