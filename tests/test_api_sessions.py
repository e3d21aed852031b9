"""REST round trips through httpx (Starlette's TestClient) against the app: sessions, frames,
control, queueing, errors."""

from __future__ import annotations

import hashlib
import io

import numpy as np
import pytest
from api_support import daemon, long_sweep, small_rig_config, sweep
from PIL import Image

from m2s2hil.store.frame_files import decode_tiff
from m2s2hil.store.session import SessionStore


@pytest.fixture
def d(tmp_path):
    with daemon(tmp_path / "data") as dm:
        yield dm


def test_create_run_and_read_back(d) -> None:
    r = d.client.post("/sessions", json=sweep())
    assert r.status_code == 202
    body = r.json()
    sid = body["session_id"]
    assert r.headers["location"].endswith(f"/sessions/{sid}") and body["url"] == r.headers["location"]
    assert body["planned_events"] == 5  # one dark + 4 azimuths
    st = d.wait_done(sid)
    assert st["state"] == "completed" and st["done"] == st["total"] == 5 and st["progress"] == 1.0
    assert st["eta_s"] == 0.0 and st["lamps_on"] == [] and st["live"] is True

    frames = d.client.get(f"/sessions/{sid}/frames").json()
    assert frames["total"] == 4
    store = SessionStore.open(d.root, sid)
    try:
        stored = {f.index: f for f in store.frames()}
    finally:
        store.close()
    assert sorted(i["n"] for i in frames["items"]) == sorted(stored)
    item = frames["items"][0]
    pose = stored[item["n"]].meta["pose"]
    assert item["meta"]["pose"]["turntable_deg"] == pytest.approx(pose["turntable_deg"])
    raw = d.client.get(item["raw_url"])
    assert raw.status_code == 200 and raw.headers["content-type"] == "image/tiff"
    assert hashlib.sha256(raw.content).hexdigest() == item["files"]["raw"]["sha256"]
    arr, desc = decode_tiff(raw.content)
    assert desc["session_id"] == sid and desc["event"]["index"] == item["n"]
    assert arr.shape == (256, 256) and arr.dtype == np.uint16
    jpg = d.client.get(item["preview_url"])  # the stored quick-look, as stored: JPEG
    assert jpg.status_code == 200 and jpg.headers["content-type"] == "image/jpeg"
    assert hashlib.sha256(jpg.content).hexdigest() == item["files"]["preview"]["sha256"]
    assert Image.open(io.BytesIO(jpg.content)).format == "JPEG"
    png = d.client.get(f"{item['preview_url']}.png")  # and as PNG for clients that want one
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    as_png = Image.open(io.BytesIO(png.content))
    assert as_png.mode == "RGB" and as_png.format == "PNG"
    diff = np.asarray(as_png).astype(int) - np.asarray(Image.open(io.BytesIO(jpg.content)))
    assert np.abs(diff).max() <= 2  # the same JPEG, decoded by OpenCV then Pillow

    # pagination and a second look from the journal (as after a daemon restart)
    page = d.client.get(f"/sessions/{sid}/frames", params={"offset": 1, "limit": 2}).json()
    assert [i["n"] for i in page["items"]] == [i["n"] for i in frames["items"][1:3]]
    d.manager.known_jobs().clear()  # forget the live job: status now comes from disk
    disk = d.client.get(f"/sessions/{sid}").json()
    assert disk["live"] is False and disk["state"] == "completed" and disk["done"] == 5


@pytest.mark.slow  # ~2 s
def test_list_filter_and_paginate(d) -> None:
    ids = []
    for sat, build in (("voyager", "B3"), ("iss", "B1"), ("voyager", "B1")):
        r = d.client.post("/sessions", json=sweep(satellite=sat, build=build))
        assert r.status_code == 202
        ids.append(r.json()["session_id"])
    for sid in ids:
        d.wait_done(sid)
    all_ = d.client.get("/sessions").json()
    assert all_["total"] == 3 and {s["session_id"] for s in all_["items"]} == set(ids)
    voy = d.client.get("/sessions", params={"satellite": "Voyager"}).json()
    assert {s["session_id"] for s in voy["items"]} == {ids[0], ids[2]}
    b1 = d.client.get("/sessions", params={"build": "B1", "state": "completed"}).json()
    assert {s["session_id"] for s in b1["items"]} == {ids[1], ids[2]}
    p1 = d.client.get("/sessions", params={"limit": 2}).json()
    p2 = d.client.get("/sessions", params={"limit": 2, "offset": 2}).json()
    assert p1["total"] == p2["total"] == 3 and len(p1["items"]) == 2 and len(p2["items"]) == 1
    assert {s["session_id"] for s in p1["items"] + p2["items"]} == set(ids)
    assert d.client.get("/sessions", params={"state": "paused"}).json()["total"] == 0


def test_queue_is_fifo_visible_and_cancellable(tmp_path) -> None:
    with daemon(tmp_path / "data") as d:
        d.manager.hold("test: hold the queue")
        ids = [d.client.post("/sessions", json=sweep(azimuth_step_deg=step)).json()["session_id"]
               for step in (90, 120, 180)]
        q = d.client.get("/queue").json()
        assert q["running"] is None and q["held"] == "test: hold the queue"
        queued = [(i["session_id"], i["position"]) for i in q["items"]]
        assert queued == [(s, n) for n, s in enumerate(ids, 1)]
        assert d.client.get(f"/sessions/{ids[1]}").json()["queue_position"] == 2

        # a queued session cannot be paused or resumed; abort cancels it
        for action in ("pause", "resume"):
            r = d.client.post(f"/sessions/{ids[1]}/{action}")
            assert r.status_code == 409 and "queued (position 2)" in r.json()["detail"]
        r = d.client.post(f"/sessions/{ids[1]}/abort")
        assert r.status_code == 200 and r.json()["state"] == "cancelled"
        assert [i["session_id"] for i in d.client.get("/queue").json()["items"]] == [ids[0], ids[2]]

        d.client.post("/queue/release")
        for sid in (ids[0], ids[2]):
            assert d.wait_done(sid)["state"] == "completed"
        starts = {}
        for sid in ids:
            store = SessionStore.open(d.root, sid)
            try:
                starts[sid] = [e["time"] for e in store.events() if e["kind"] == "run_started"]
                assert store.state == ("cancelled" if sid == ids[1] else "completed")
            finally:
                store.close()
        assert starts[ids[1]] == []  # the cancelled one never ran
        assert starts[ids[0]][0] < starts[ids[2]][0]  # first in, first out
        assert d.client.post(f"/sessions/{ids[1]}/resume").status_code == 409


def test_queue_limit_answers_429(tmp_path) -> None:
    with daemon(tmp_path / "data", queue_limit=1) as d:
        d.manager.hold("test")
        assert d.client.post("/sessions", json=sweep()).status_code == 202
        r = d.client.post("/sessions", json=sweep())
        assert r.status_code == 429 and "limit 1" in r.json()["detail"] and r.headers["retry-after"]


def test_pause_resume_abort_a_running_session(d) -> None:
    sid = d.client.post("/sessions", json=long_sweep()).json()["session_id"]
    d.wait_state(sid, "running")
    r = d.client.post(f"/sessions/{sid}/pause")
    assert r.status_code == 200 and r.json()["state"] in ("pausing", "paused")
    st = d.wait_state(sid, "paused")
    assert st["pause_reason"] == "operator" and d.rig.world.lamps_on() == frozenset()
    done_at_pause = st["done"]
    r = d.client.post(f"/sessions/{sid}/pause")
    assert r.status_code == 409 and "cannot pause while paused" in r.json()["detail"]
    assert d.client.get(f"/sessions/{sid}").json()["done"] == done_at_pause  # parked: nothing captured
    assert d.client.post(f"/sessions/{sid}/resume").status_code == 200
    d.wait(sid, lambda s: s["done"] > done_at_pause)
    assert d.client.post(f"/sessions/{sid}/abort").status_code == 200
    st = d.wait_done(sid)
    assert st["state"] == "aborted" and st["done"] < st["total"]
    r = d.client.post(f"/sessions/{sid}/resume")
    assert r.status_code == 409 and "aborted" in r.json()["detail"]


@pytest.mark.slow  # ~23 s
@pytest.mark.timeout(600)  # generous: a loaded machine stretches it, it does not fail it
def test_resume_an_interrupted_session_from_disk(tmp_path) -> None:
    root = tmp_path / "data"
    rig = small_rig_config(64)  # the capture QC of 108 frames is most of the CPU at 256² (22 s against 7 s)
    with daemon(root, rig_config=rig) as d:
        sid = d.client.post("/sessions", json=long_sweep()).json()["session_id"]
        d.wait(sid, lambda s: s["done"] >= 3)
        d.manager.close(timeout=30)  # as on SIGTERM: parks the session and marks it interrupted
    with daemon(root, rig_config=rig) as d:  # a new daemon without automatic resumption
        st = d.client.get(f"/sessions/{sid}").json()
        assert st["state"] == "interrupted" and st["resumable"] and not st["live"]
        before = st["done"]
        r = d.client.post(f"/sessions/{sid}/resume")
        assert r.status_code == 200 and r.json()["state"] in ("queued", "running", "idle")
        st = d.wait_done(sid)
        assert st["state"] == "completed" and st["done"] == st["total"] > before
        store = SessionStore.open(root, sid)
        try:
            ids = [f.event_id for f in store.frames()]
        finally:
            store.close()
        assert len(ids) == len(set(ids)) == 108


@pytest.mark.parametrize(("body", "where"), [
    ({"satellite": "apollo", "build": "B1"}, "body.satellite: unknown satellite 'apollo'"),
    ({"satellite": "iss", "build": "B9"}, "body.build"),
    ({"satellite": "iss", "build": "B1", "lighting": ["moon"]}, "unknown lighting condition 'moon'"),
    ({"satellite": "iss", "build": "B1", "azimuth_step_deg": 0}, "body.azimuth_step_deg: Input should be"),
    ({"satellite": "iss", "build": "B1", "colour": "red"}, "body.colour: Extra inputs are not permitted"),
    ({"satellite": "iss", "build": "B1", "azimuth_step_deg": 0.05}, "at most 20000"),
    ({"satellite": "iss", "build": "B1", "processing": "magic"}, "body.processing: unknown demosaicing"),
    ({"satellite": "iss", "build": "B1", "azimuth_step_deg": 1e-219}, "greater than or equal to 0.01"),
])
def test_invalid_sweeps_get_422_with_the_place(d, body, where) -> None:
    r = d.client.post("/sessions", json=body)
    assert r.status_code == 422, r.text
    assert where in r.json()["detail"]


def test_malformed_requests(d) -> None:
    r = d.client.post("/sessions", content=b"{not json", headers={"content-type": "application/json"})
    assert r.status_code == 400 and "malformed JSON" in r.json()["detail"]
    r = d.client.get("/sessions/no-such-session")
    assert r.status_code == 404 and "no session 'no-such-session'" in r.json()["detail"]
    for bad in (".hidden", "a b", "x" * 200):
        assert d.client.get(f"/sessions/{bad}").status_code == 422
    r = d.client.get("/sessions", params={"limit": 0})
    assert r.status_code == 422 and r.json()["detail"].startswith("query.limit:")
    assert d.client.get("/sessions", params={"state": "sleeping"}).status_code == 422
    assert d.client.post("/sessions/no-such-session/pause").status_code == 404


def test_frames_of_unknown_things(d) -> None:
    sid = d.client.post("/sessions", json=sweep()).json()["session_id"]
    d.wait_done(sid)
    r = d.client.get(f"/sessions/{sid}/frames/999/raw")
    assert r.status_code == 404 and "no frame 999" in r.json()["detail"]
    r = d.client.get(f"/sessions/{sid}/frames/0/raw")  # index 0 is the master dark, not a frame
    assert r.status_code == 404
    assert d.client.get(f"/sessions/{sid}/frames/-1/raw").status_code == 422
    assert d.client.get(f"/sessions/{sid}/frames/{2**40}/raw").status_code == 422


def test_sessions_beyond_the_kept_ones_have_their_journals_closed(tmp_path) -> None:
    # The soak found journals left open past keep_finished (4 descriptors each, until the GC).
    with daemon(tmp_path / "data", keep_finished=1, rig_config=small_rig_config(64)) as dm:
        sids = [dm.client.post("/sessions", json=sweep()).json()["session_id"] for _ in range(3)]
        jobs = [dm.manager._queue.get(sid) for sid in sids]
        assert all(j is not None for j in jobs)
        for sid in sids:
            assert dm.wait_done(sid)["state"] == "completed"
        assert dm.manager._queue.get(sids[0]) is None and dm.manager._queue.get(sids[-1]) is jobs[-1]
        assert jobs[0].store.journal._db is None  # dropped: its journal closed
        assert jobs[-1].store.journal._db is not None  # kept: still open for reads
        assert dm.client.get(f"/sessions/{sids[0]}").json()["state"] == "completed"  # read from disk


def test_a_session_retired_during_a_read_stays_open_until_the_read_ends(tmp_path) -> None:
    # Retiring closed the store under a request that was reading it.
    with daemon(tmp_path / "data", keep_finished=1, rig_config=small_rig_config(64)) as dm:
        first = dm.client.post("/sessions", json=sweep()).json()["session_id"]
        assert dm.wait_done(first)["state"] == "completed"
        with dm.manager.reads.reading(first) as store:
            second = dm.client.post("/sessions", json=sweep()).json()["session_id"]
            assert dm.wait_done(second)["state"] == "completed"
            assert dm.manager._queue.get(first) is None  # retired meanwhile
            assert store.journal.query("SELECT COUNT(*) AS n FROM frames")[0]["n"] > 0
        assert store.journal._db is None  # closed once the read ended
        with dm.manager.reads.reading(first) as again:  # later reads open it from disk
            assert again is not store and again.state == "completed"
