"""The operator console's endpoints against a daemon on the simulated rig (virtual clock): manual
control, the live stream, snapshots, calibration captures, plan estimates, the session browser."""

from __future__ import annotations

import asyncio
import json
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile
from api_support import daemon, long_sweep, small_rig_config, sweep
from m2s2hil.drivers.interfaces import Frame

from m2s2hil.processing.calibration import load_calibration
from m2s2hil.rig.live_view import HIST_BINS, LiveFrame, LiveNotice, LiveSettings, LiveStream

SENSOR = 64  # px a side: a frame costs a quarter of the CPU it does at 256² (the endpoints do not care)


@pytest.fixture
def d(tmp_path: Path):
    with daemon(tmp_path / "data", rig_config=small_rig_config(SENSOR)) as dd:
        yield dd


def wait_idle(d, axis: str, timeout: float = 30.0) -> dict:
    """The axis once it stands; simulated time goes on meanwhile (the rig's virtual clock moves only
    when someone sleeps on it: a move would crawl at the pace of these polls)."""
    deadline = time.monotonic() + timeout
    while True:
        axes = {a["role"]: a for a in d.client.get("/rig/axes").json()["axes"]}
        if not axes[axis]["moving"]:
            return axes[axis]
        assert time.monotonic() < deadline, "the axis never stopped"
        d.rig.clock.advance(0.05)
        time.sleep(0.01)


def mjpeg_frames(body: bytes) -> list[tuple[dict[str, str], bytes]]:
    """The frame parts of a live stream (not its notices, nor the part saying why it ended)."""
    return [(f, jpeg) for f, jpeg in mjpeg_parts(body) if "X-Live-Stats" in f]


def mjpeg_parts(body: bytes) -> list[tuple[dict[str, str], bytes]]:
    parts = []
    for chunk in body.split(b"--m2s2hil-frame\r\n")[1:]:
        head, _, rest = chunk.partition(b"\r\n\r\n")
        fields = dict(line.split(": ", 1) for line in head.decode().split("\r\n") if ": " in line)
        n = int(fields["Content-Length"])
        parts.append((fields, rest[:n]))
    return parts


def test_console_page_is_served_offline_with_a_strict_policy(d) -> None:
    r = d.client.get("/")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    csp = r.headers["content-security-policy"]
    assert "frame-ancestors 'none'" in csp and "script-src 'self'" in csp
    assert r.headers["x-frame-options"] == "DENY"
    assert '<script src="/console/console.js"' in r.text and "http" not in r.text.split("<body>")[0].lower()
    js = d.client.get("/console/console.js")
    assert js.status_code == 200 and "text/javascript" in js.headers["content-type"]
    assert "innerHTML" not in js.text  # every daemon string reaches the page as text
    assert d.client.get("/console/../app.py").status_code in (404, 422)


def test_jog_moves_the_stage_and_limits_are_refused_before_sending(d) -> None:
    before = wait_idle(d, "turntable")["position_deg"]
    r = d.client.post("/rig/axes/turntable/jog", json={"delta_deg": 10})
    assert r.status_code == 202, r.text
    assert r.json()["target_deg"] == pytest.approx(before + 10)
    after = wait_idle(d, "turntable")["position_deg"]
    assert after == pytest.approx(before + 10, abs=0.05)
    # read back through GET /rig too (the device, not the console's own view)
    rig = {e["name"]: e for e in d.client.get("/rig").json()["devices"]}
    assert rig["stage"]["state"]["turntable_deg"] == pytest.approx(after, abs=0.05)
    tilt = d.client.get("/rig/axes").json()["axes"][1]
    r = d.client.post("/rig/axes/tilt/goto", json={"position_deg": tilt["max_deg"] + 1})
    assert r.status_code == 422 and "soft limits" in r.json()["detail"]
    assert wait_idle(d, "tilt")["position_deg"] == pytest.approx(tilt["position_deg"], abs=0.05)


def test_lamp_presets_and_single_lamps(d) -> None:
    r = d.client.put("/rig/lamps", json={"preset": "weak"})
    assert r.status_code == 200 and r.json()["lamps_on"] == ["bar1", "bar2", "bar3"]
    assert d.client.put("/rig/lamps", json={"lamps": ["spot"]}).json()["lamps_on"] == ["spot"]
    assert sorted(d.rig.lights.state()) == [d.rig.config.lamps["spot"].channel]
    r = d.client.put("/rig/lamps", json={"lamps": ["nope"]})
    assert r.status_code == 422 and "nope" in r.json()["detail"]
    assert d.client.put("/rig/lamps", json={"preset": None}).json()["lamps_on"] == []


def test_manual_control_is_refused_while_a_session_owns_the_rig(d) -> None:
    sid = d.client.post("/sessions", json=long_sweep()).json()["session_id"]
    d.wait(sid, lambda st: st["state"] == "running" and st["done"] >= 2)  # past its darks: lamps on
    assert d.client.get("/queue").json()["rig"] == "running"
    # the lamps the session switched on, not "none" (the axes card read the devices only when idle)
    assert d.client.get("/rig/axes").json()["lamps_on"] == ["bar1", "bar2", "bar3"]
    r = d.client.post("/rig/axes/turntable/jog", json={"delta_deg": 5})
    assert r.status_code == 409 and sid in r.json()["detail"]
    assert d.client.put("/rig/lamps", json={"preset": None}).status_code == 409
    assert d.client.post("/snapshots", json={}).status_code == 409
    assert d.client.get("/rig/axes").json()["owner"] == sid
    d.client.post(f"/sessions/{sid}/abort")
    d.wait_done(sid)
    assert d.client.post("/rig/axes/turntable/jog", json={"delta_deg": 1}).status_code == 202


def test_live_stream_frames_and_statistics(d) -> None:
    assert d.client.put("/camera/live", json={"exposure_s": 0.004, "view": "rgb"}).status_code == 200
    r = d.client.get("/camera/live.mjpeg", params={"max_frames": 3})
    assert r.status_code == 200 and r.headers["content-type"].startswith("multipart/x-mixed-replace")
    parts = mjpeg_frames(r.content)
    assert len(parts) == 3
    end = json.loads(mjpeg_parts(r.content)[-1][0]["X-Live-End"])  # the last part says why it ended
    assert end["frames"] == 3 and "max_frames" in end["reason"]
    size = d.rig.config.camera.model.width // d.rig.config.camera.model.period
    seqs = []
    for fields, jpeg in parts:
        img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
        assert img.shape == (size, size, 3)
        st = json.loads(fields["X-Live-Stats"])
        assert len(st["histogram"]) == HIST_BINS and sum(st["histogram"]) > 0
        assert 0.0 <= st["saturated_fraction"] <= 1.0 and st["focus"] > 0
        assert st["exposure_s"] == pytest.approx(0.004)
        seqs.append(st["seq"])
    assert seqs == sorted(set(seqs))  # each frame once, in order
    status = d.client.get("/camera/live").json()
    assert status["state"] in ("streaming", "idle") and status["stream_fps"] > 0
    assert status["cold_start_s"] is not None and "stopped_reason" in status
    r = d.client.put("/camera/live", json={"view": 3, "gain": 2.0})
    assert r.json()["settings"]["view"] == 3
    (fields, _), = mjpeg_frames(d.client.get("/camera/live.mjpeg", params={"max_frames": 1}).content)
    st = json.loads(fields["X-Live-Stats"])
    assert st["view"] == 3 and st["gain"] == 2.0
    assert d.client.put("/camera/live", json={"view": 99}).status_code == 422
    assert d.client.put("/camera/live", json={"exposure_s": -1}).status_code == 422


def test_live_view_waits_for_a_cold_camera_and_says_why_it_stopped() -> None:
    """A camera slow to give its first frame: the viewer is told what the stream waits for (no
    timeout ends it), gets the frame once it comes, and the stream's stop has its reason."""
    model = small_rig_config(64).camera.model
    gate = threading.Event()

    def grab(settings: LiveSettings) -> Frame:
        assert gate.wait(30), "the test never released the camera"
        return Frame(np.full((64, 64), 100, np.uint16), 1, 0.0, settings.exposure_s, settings.gain,
                     "Mono10", 25.0)

    live = LiveStream(model, grab, idle_stop_s=0.0)

    async def view() -> list:
        got: list = []
        async for item in live.aframes(max_frames=1, notice_s=0.05):
            got.append(item)
            if len(got) == 2:
                assert live.state == "starting" and live.fps is None
                gate.set()
        return got

    got = asyncio.run(view())
    assert [type(g) for g in got[:2]] == [LiveNotice, LiveNotice], got
    assert got[0].state == "waiting" and "first frame" in got[0].reason
    assert isinstance(got[-1], LiveFrame) and live.cold_start_s is not None and live.cold_start_s > 0
    deadline = time.monotonic() + 30
    while live.running:  # no viewer left: the producer stops, and says why
        assert time.monotonic() < deadline
        time.sleep(0.01)
    assert live.state == "idle" and "no viewer" in (live.stopped_reason or "")
    # a camera stuck in its read: the viewer is told, then the stream ends with the reason
    gate.clear()
    stuck = LiveStream(model, grab, idle_stop_s=0.0)

    async def view_stuck() -> list:
        return [item async for item in stuck.aframes(max_frames=1, notice_s=0.05, give_up_s=0.3)]

    try:
        got = asyncio.run(view_stuck())
    finally:
        gate.set()
    assert got[0].state == "waiting" and got[-1].state == "ended" and "gave up" in got[-1].reason


def _frame(n: int, size: int = 64) -> Frame:
    return Frame(np.full((size, size), 100 + n % 50, np.uint16), n, 0.0, 0.004, 1.0, "Mono10", 25.0)


def _wait_until(cond, what: str, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, what
        time.sleep(0.005)


def test_live_view_grabs_while_it_renders_and_drops_stale_frames() -> None:
    """The next grab runs while the last frame renders (two threads, one slot between them): with
    the render held up, grabbing goes on; released, the viewer gets the newest frame, not a queue."""
    model = small_rig_config(64).camera.model
    grabbed = []

    def grab(settings: LiveSettings) -> Frame:
        grabbed.append(len(grabbed) + 1)
        return _frame(len(grabbed))

    live = LiveStream(model, grab, idle_stop_s=0.0, max_fps=500.0)
    render, held, at_hold, rendered = live.renderer.render, threading.Event(), [], []

    def slow_render(frame, settings, seq, grabbed_at=None):
        rendered.append(frame.block_id)
        if seq == 1:  # the first frame rendered is held up
            at_hold.append(len(grabbed))
            assert held.wait(30), "the test never released the render"
        return render(frame, settings, seq, grabbed_at)

    live.renderer.render = slow_render  # type: ignore[method-assign]

    async def view() -> list:
        got = []
        async for item in live.aframes(max_frames=2, notice_s=0.05):
            if isinstance(item, LiveFrame):
                got.append(item)
            elif not held.is_set():
                await asyncio.to_thread(_wait_until, lambda: at_hold and len(grabbed) >= at_hold[0] + 3,
                                        "no grab during the render")
                held.set()
        return got

    first, second = asyncio.run(view())
    # three grabbed while the first rendered: the next render is the newest, the ones between dropped
    assert rendered[1] >= rendered[0] + 3 and second.stats["dropped"] >= 2
    assert second.seq > first.seq and "grab_ms" in second.stats
    _wait_until(lambda: not live.running, "the producer did not stop")
    assert live.state == "idle"


def test_live_view_ends_on_a_camera_that_only_fails_and_on_a_failed_render() -> None:
    """No viewer waits for ever: a camera that only fails ends the stream after ``give_up_s`` with
    the last error; a render that fails ends the producer, and the stream says why."""
    from m2s2hil.drivers.errors import DeviceTimeout

    model = small_rig_config(64).camera.model

    def broken(settings: LiveSettings) -> Frame:
        raise DeviceTimeout("no frame within 1 s (streaming)", device="camera")

    failing = LiveStream(model, broken, idle_stop_s=0.0)

    async def view(live: LiveStream, **kw) -> list:
        return [item async for item in live.aframes(max_frames=1, notice_s=0.05, **kw)]

    got = asyncio.run(view(failing, give_up_s=0.3))
    assert got[0].state == "error" and "no frame within" in got[0].reason
    end = got[-1]
    assert end.state == "ended" and "only errors" in end.reason and "no frame within" in end.reason
    live = LiveStream(model, lambda settings: _frame(1), idle_stop_s=0.0)

    def bad_render(*args, **kw):
        raise ValueError("the cube has no bands")

    live.renderer.render = bad_render  # type: ignore[method-assign]
    got = asyncio.run(view(live))
    assert not any(isinstance(g, LiveFrame) for g in got)
    _wait_until(lambda: not live.running, "the producer did not stop")
    assert live.state == "error" and "the cube has no bands" in (live.stopped_reason or "")


def test_live_stream_recovers_from_a_stalled_camera_stream(tmp_path: Path) -> None:
    """The camera's stream stalls after its first frame (it stays stalled until acquisition is
    restarted): the viewer is told the error, the next grab restarts the stream, and the frames
    asked for arrive (before, every grab timed out again and the request never ended)."""
    with daemon(tmp_path / "data", rig_config=small_rig_config(SENSOR),
                faults={"toucan": [{"kind": "stall", "count": 1, "after": 1}]}) as dd:
        r = dd.client.get("/camera/live.mjpeg", params={"max_frames": 3})
        parts = mjpeg_parts(r.content)
        notices = [json.loads(f["X-Live-Status"]) for f, _ in parts if "X-Live-Status" in f]
        frames = [json.loads(f["X-Live-Stats"]) for f, _ in mjpeg_frames(r.content)]
        assert len(frames) == 3, notices
        ids = [st["block_id"] for st in frames]
        assert ids[-1] - ids[0] > 2, ids  # the stalled frame never came: the stream was restarted
        assert "max_frames" in json.loads(parts[-1][0]["X-Live-End"])["reason"]


def test_live_stream_viewer_leaving_at_the_worst_moment_is_let_go(d) -> None:
    """A client that goes while the stream waits for its first frame, or while a part is being sent
    (its peer vanished mid-send): the request ends (no hang), the viewer leaves the count and the
    stream slot is released; the live view still serves the next client."""
    app = d.client.app
    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "GET",
             "scheme": "http", "path": "/camera/live.mjpeg", "raw_path": b"/camera/live.mjpeg",
             "query_string": b"", "root_path": "", "client": ("127.0.0.1", 50000),
             "server": ("127.0.0.1", 8750), "headers": [(b"host", b"127.0.0.1:8750"), (b"x-m2s2hil", b"1")]}

    async def run(leave: str) -> list[dict]:
        sent: list[dict] = []
        gone = asyncio.Event()
        asked = 0
        if leave == "before the first frame":
            gone.set()

        async def receive() -> dict:
            nonlocal asked
            asked += 1
            if asked == 1:
                return {"type": "http.request", "body": b"", "more_body": False}
            await gone.wait()
            return {"type": "http.disconnect"}

        async def send(message: dict) -> None:
            sent.append(message)
            if message["type"] == "http.response.body" and b"X-Live-Stats" in message.get("body", b""):
                gone.set()
                await asyncio.sleep(30)  # the peer is gone mid-part: only the disconnect ends this

        await asyncio.wait_for(app(scope, receive, send), 60)
        return sent

    for leave in ("before the first frame", "during a send"):
        sent = asyncio.run(run(leave))
        assert app.state.console.live.viewers == 0 and app.state.streams.live.count == 0, leave
        if leave == "during a send":
            assert any(b"X-Live-Stats" in m.get("body", b"") for m in sent)
    assert len(mjpeg_frames(d.client.get("/camera/live.mjpeg", params={"max_frames": 1}).content)) == 1


def test_live_view_longer_exposure_saturates_more(d) -> None:
    d.client.put("/rig/lamps", json={"preset": "strong"})
    fractions = []
    for exposure in (0.001, 0.2):
        d.client.put("/camera/live", json={"exposure_s": exposure})
        (fields, _), = mjpeg_frames(d.client.get("/camera/live.mjpeg", params={"max_frames": 1}).content)
        fractions.append(json.loads(fields["X-Live-Stats"])["saturated_fraction"])
    assert fractions[0] < fractions[1]


def test_snapshot_is_stored_outside_sessions_and_downloadable(d) -> None:
    d.client.put("/rig/lamps", json={"preset": "weak"})
    r = d.client.post("/snapshots", json={"note": "centring\nline two", "exposure_s": 0.005})
    assert r.status_code == 201, r.text
    meta = r.json()
    assert meta["lamps_on"] == ["bar1", "bar2", "bar3"] and meta["exposure_s"] == 0.005
    raw = d.client.get(meta["files"]["raw.tiff"])
    assert raw.status_code == 200 and "attachment" in raw.headers["content-disposition"]
    tmp = d.root / "dl.tiff"
    tmp.write_bytes(raw.content)
    with tifffile.TiffFile(tmp) as tf:
        arr = tf.asarray()
        desc = json.loads(tf.pages[0].description)
    m = d.rig.config.camera.model
    assert arr.shape == (m.height, m.width) and arr.dtype == np.uint16
    assert desc["turntable_deg"] == pytest.approx(meta["turntable_deg"])
    assert d.client.get("/snapshots").json()["items"][0]["id"] == meta["id"]
    assert d.client.get(f"/snapshots/{meta['id']}/preview.png").headers["content-type"] == "image/png"
    assert d.client.get("/snapshots/20990101T000000-abcdef").status_code == 404
    assert d.client.get("/snapshots/..%2F..%2Fetc").status_code in (404, 422)
    assert not any(p.name == "snapshots" for p in d.root.glob("*/snapshots"))  # not inside a session
    running = d.manager.busy.start("snapshot", "a snapshot")  # as if a first click's were still running
    try:
        assert [b["key"] for b in d.client.get("/busy").json()["items"]] == ["snapshot"]
        assert [b["key"] for b in d.client.get("/rig/axes").json()["busy"]] == ["snapshot"]
        again = d.client.post("/snapshots", json={})
        assert again.status_code == 409 and "already running" in again.json()["detail"]
    finally:
        d.manager.busy.end(running)
    assert d.client.get("/busy").json()["items"] == []


def test_calibration_darks_white_reference_and_phase(d) -> None:
    plan = sweep(lighting=["weak", "directional"])
    r = d.client.post("/calibration/darks", json={"plan": plan, "n_frames": 2})
    assert r.status_code == 201, r.text
    darks = r.json()["darks"]
    assert len(darks) >= 1 and all(x["n_frames"] == 2 for x in darks)
    assert len(d.client.get("/calibration").json()["darks"]) == len(darks)

    too_bright = {"exposure_s": 2.0, "n_frames": 2, "lighting": "strong"}
    r = d.client.post("/calibration/white", json=too_bright)
    assert r.status_code == 422 and "saturated" in r.json()["detail"]
    cal = d.client.get("/calibration").json()
    assert not cal["exists"]

    r = d.client.post("/calibration/white", json={"exposure_s": 0.005, "n_frames": 4, "lighting": "strong"})
    assert r.status_code == 201, r.text
    prov = r.json()["provenance"]
    assert prov["checks"]["saturated_fraction"] == 0.0 and prov["lighting"] == "strong"
    calib = load_calibration(r.json()["file"], d.rig.config.camera.model)
    assert calib.white_mosaic is not None and calib.white_mosaic.shape == (d.rig.config.camera.model.height,
                                                                          d.rig.config.camera.model.width)
    doc = json.loads(Path(r.json()["file"]).read_text())
    assert doc["white_reference"]["provenance"]["n_frames"] == 4
    assert d.rig.lights.state() == frozenset()  # the preset's lamps are off again

    d.client.put("/rig/lamps", json={"preset": "strong"})
    r = d.client.post("/calibration/phase", json={"exposure_s": 0.02})
    assert r.status_code == 200, r.text
    assert r.json()["suspect"] is False


def test_plan_estimate_matches_the_plan(d) -> None:
    from m2s2hil.plan import Sweep

    body = sweep(tilts=["E0", "E1"], azimuth_step_deg=30)
    r = d.client.post("/plans/estimate", json=body)
    assert r.status_code == 200, r.text
    est = Sweep.model_validate(body).estimate(d.rig.config)
    out = r.json()
    assert out["frames"] == 2 * 12 and out["estimate_s"] == pytest.approx(est.total_s)
    assert 0 < out["lower_bound_s"] <= out["estimate_s"]
    assert d.client.post("/plans/estimate", json={**body, "azimuth_step_deg": 0.001}).status_code == 422
    assert not [p for p in d.root.iterdir() if p.is_dir() and p.name[:1].isdigit()]  # no session made


def test_session_browser_reads_without_writing(d) -> None:
    sid = d.client.post("/sessions", json=sweep()).json()["session_id"]
    d.wait_done(sid)
    folder = d.root / sid
    before = {p: p.stat().st_mtime_ns for p in folder.rglob("*") if p.is_file()}
    r = d.client.get(f"/sessions/{sid}/report.html")
    assert r.status_code == 200 and "<html" in r.text.lower() and "script" not in r.headers[
        "content-security-policy"].replace("script-src", "")
    v = d.client.get(f"/sessions/{sid}/verify").json()
    assert v["ok"] is True and v["frames"] == 4
    st = d.client.get(f"/sessions/{sid}").json()  # captures = frames + darks, each counted apart
    assert (st["planned_frames"], st["planned_darks"]) == (4, st["total"] - 4) and st["planned_darks"] >= 1
    e = d.client.post(f"/sessions/{sid}/export", json={"layout": "m2s2"})
    assert e.status_code == 201, e.text
    assert e.json()["images"] == 4 and Path(e.json()["folder"]).is_dir()
    z = d.client.post(f"/sessions/{sid}/export", json={"layout": "zarr"})
    assert z.status_code == 201 and z.json()["images"] == 4, z.text
    assert d.client.get("/queue").json()["rig"] == "idle"
    # an export as a job: answered at once, followed, then downloaded as a zip
    job = d.client.post(f"/sessions/{sid}/export/jobs", json={"layout": "m2s2", "overwrite": True})
    assert job.status_code == 202, job.text
    deadline = time.monotonic() + 60
    while (j := d.client.get(job.json()["url"]).json())["state"] == "running":
        assert time.monotonic() < deadline, j
        time.sleep(0.05)
    assert j["state"] == "done" and j["result"]["images"] == 4 and j["download_url"], j
    dl = d.client.get(j["download_url"])
    assert dl.status_code == 200 and dl.headers["content-type"] == "application/zip"
    assert f'filename="{sid}-m2s2.zip"' in dl.headers["content-disposition"]
    import io
    import zipfile

    names = zipfile.ZipFile(io.BytesIO(dl.content)).namelist()
    exported = [p for p in Path(e.json()["folder"]).rglob("*") if p.is_file()]
    assert len(names) == len(exported) and all(n.startswith(f"{sid}-m2s2/") for n in names)
    assert d.client.get(f"/sessions/{sid}/export/hf.zip").status_code == 404  # never exported
    claim = d.manager.busy.start(f"export:{sid}:m2s2", "an export")
    try:
        busy = d.client.post(f"/sessions/{sid}/export/jobs", json={"layout": "m2s2"})
        assert busy.status_code == 409 and "already running" in busy.json()["detail"]
    finally:
        d.manager.busy.end(claim)
    after = {p: p.stat().st_mtime_ns for p in folder.rglob("*") if p.is_file()}
    assert {p for p in after if "journal" not in p.name} == {p for p in before if "journal" not in p.name}
    assert all(after[p] == before[p] for p in before if p in after and "journal" not in p.name)
