"""The console's pictures (m2s2hil/api/console/pictures.py, m2s2hil/console/pictures.js): the
spectrum at a point or region of a stored frame and of the live view, the ten-band mosaic, the
coverage map (console and report) and the calibration pictures; then the same in headless
Chromium at desktop and phone sizes.

The session here is written straight into the store (no capture: a few ms) with mosaics whose
bands hold known values, so the spectra are checked to the DN; the daemon's sensor is 64² so
the live view and calibration captures are cheap."""

from __future__ import annotations

import os
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from api_support import daemon, small_rig_config

from m2s2hil.plan import Sweep
from m2s2hil.processing.calibration import CameraCalibration, save_calibration
from m2s2hil.processing.mosaic import MosaicLayout
from m2s2hil.store.session import SessionStore

N = 64
DARK = 3.0


CLASSES = ("background", "gold_foil", "solar_panel")
LABELS = np.zeros((N // 4, N // 4), np.uint8)  # a projected label map at the cube's size
LABELS[2:8, 2:14], LABELS[9:14, 4:10] = 1, 2


def band_levels(ev_index: int) -> np.ndarray:
    return 100.0 + 10.0 * np.arange(10) + ev_index  # DN per band before the dark


def mosaic_of(levels: np.ndarray, model, region_levels: np.ndarray | None = None) -> np.ndarray:
    """A mosaic whose band-b pixels hold levels[b]; the top-left 16×16 holds region_levels."""
    lay = MosaicLayout.from_camera(model).array
    out = np.asarray(levels)[np.tile(lay, (N // lay.shape[0], N // lay.shape[1]))]
    if region_levels is not None:
        out[:16, :16] = np.asarray(region_levels)[np.tile(lay, (16 // lay.shape[0], 16 // lay.shape[1]))]
    return out


def write_session(root: Path) -> tuple[str, dict[str, int]]:
    """weak × (E0, E2) × 4 azimuths: 5 frames written (one QC-flagged), one skipped, 2 pending."""
    rig = small_rig_config(N)
    sweep = Sweep(satellite="voyager", build="B3", lighting=["weak"], tilts=["E0", "E2"], azimuth_step_deg=90,
                  dark={"frames": 1})
    st = SessionStore.create(root, sweep, rig)
    model = rig.camera.model
    idx: dict[str, int] = {}
    frames = [e for e in sweep.expand(st.rig) if e.kind == "frame"]
    for ev in sweep.expand(st.rig):
        if ev.kind == "dark":
            st.write_dark(ev, np.full((N, N), DARK, np.float32))
    for k, ev in enumerate(frames[:5]):
        raw = mosaic_of(band_levels(k), model, region_levels=band_levels(k) + 50).astype(np.uint16)
        rgb = np.zeros((N // 4, N // 4, 3), np.uint8)
        rgb[..., 1] = 40 * (k + 1)
        qc = {"score": 0.4, "flags": ["unstable"]} if k == 1 else {"score": 0.95, "flags": []}
        extra = None
        if k == 1:  # the twin flagged it and projected its labels (as analysis.qc stores them)
            qc = {**qc, "flags": ["unstable", "off_axis"],
                  "twin": {"flags": ["off_axis"], "frame_flags": ["off_axis"]},
                  "projected_labels": {"class_names": list(CLASSES), "confidence": 0.9, "source": "twin"}}
            extra = {"projected_labels": LABELS}
        elif k == 2:  # checked, nothing found, no placement yet
            qc = {**qc, "twin": {"flags": [], "frame_flags": ["yawed"]}}
        rec = st.write_frame(ev, raw, preview_rgb=rgb, meta={"exposure_s": 0.01, "gain": 1.0, "qc": qc,
                                                             "temperature_c": 30.0}, extra=extra)
        idx[ev.event_id] = rec.index
    st.record_skip(frames[5], "MoveStalled: the turntable stalled", "motion")
    st.close()
    return st.session_id, {"first": idx[frames[0].event_id], "flagged": idx[frames[1].event_id],
                           "checked": idx[frames[2].event_id],
                           "skipped_event": frames[5].event_id}  # type: ignore[dict-item]


@pytest.fixture(scope="module")
def d(tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("pictures") / "data"
    sid, idx = write_session(root)
    with daemon(root, rig_config=small_rig_config(N)) as dd:
        dd.sid, dd.idx = sid, idx  # type: ignore[attr-defined]
        quick_live_stop(dd.client)
        yield dd


def quick_live_stop(client) -> None:
    """The app's live view stops as soon as its last viewer leaves (not 2 s later: frames nobody
    sees cost CPU the other tests pay for)."""
    client.get("/camera/live")  # makes the app's console state
    client.app.state.console.live.idle_stop_s = 0.0



# what the frame viewer drew over the ten bands' label bars, with the canvas's pixels there
BAND_LABELS_JS = """(() => {
    const f = window.m2s2hilPictures.fv, cv = document.getElementById('fv-canvas');
    const dpr = window.devicePixelRatio || 1, ctx = cv.getContext('2d');
    const lit = f.bandLabels.map(l => {
        const px = ctx.getImageData(l.x * dpr, l.y * dpr, l.w * dpr, (l.px + 4) * dpr).data;
        let text = 0, dark = 0;
        for (let i = 0; i < px.length; i += 4) {
            if (px[i] > 200 && px[i + 1] > 200 && px[i + 2] > 200) text++;
            else if (px[i] < 80 && px[i + 1] < 80 && px[i + 2] < 80) dark++; }
        return [text, dark / (px.length / 4)]; });
    return [f.bandLabels, f.bandsNm, lit]; })()"""


def assert_band_labels_drawn(page) -> None:
    """Every tile's wavelength is drawn at ≥ 11 px, as white text on a dark box where the viewer
    says it drew it (not the light band image under it)."""
    drawn, nm, lit = page.evaluate(BAND_LABELS_JS)
    assert nm and len(nm) == 10 and [label["text"] for label in drawn] == [f"{v:g} nm" for v in nm], drawn
    assert all(label["px"] >= 11 for label in drawn), drawn
    assert all(text > 5 and dark > 0.4 for text, dark in lit), lit

def test_stored_spectrum_is_the_dark_subtracted_band_means(d) -> None:
    n = d.idx["first"]
    # one point: the mosaic cell holding it, every band's own pixels
    r = d.client.get(f"/sessions/{d.sid}/frames/{n}/spectrum", params={"x": 33, "y": 41})
    assert r.status_code == 200, r.text
    s = r.json()
    assert s["region"] == {"x": 32, "y": 40, "w": 4, "h": 4} and s["sensor"] == [N, N]
    assert s["bands_nm"] == list(d.rig.config.camera.model.bands_nm)
    assert s["dn"] == pytest.approx(list(band_levels(0) - DARK))
    assert s["dark"] and s["reflectance"] is None  # no white reference yet
    # a region inside the brighter top-left square, and one half in it
    url = f"/sessions/{d.sid}/frames/{n}/spectrum"
    s = d.client.get(url, params={"x": 0, "y": 0, "w": 16, "h": 16}).json()
    assert s["dn"] == pytest.approx(list(band_levels(0) + 50 - DARK))
    s = d.client.get(url, params={"x": 0, "y": 0, "w": 32, "h": 16}).json()
    assert s["dn"] == pytest.approx(list(band_levels(0) + 25 - DARK))


@pytest.mark.parametrize("params, key", [({"x": N, "y": 0}, "query.x"), ({"x": 0, "y": 99}, "query.y"),
                                         ({"x": 60, "y": 0, "w": 8}, "query.w"),
                                         ({"x": 0, "y": 60, "h": 5}, "query.h")])
def test_spectrum_outside_the_sensor_is_a_422_naming_the_parameter(d, params, key) -> None:
    r = d.client.get(f"/sessions/{d.sid}/frames/{d.idx['first']}/spectrum", params=params)
    assert r.status_code == 422 and r.json()["detail"].startswith(key), r.text


def test_spectrum_of_a_missing_frame_or_session_is_404(d) -> None:
    assert d.client.get(f"/sessions/{d.sid}/frames/999/spectrum", params={"x": 0, "y": 0}).status_code == 404
    r = d.client.get("/sessions/20000101T000000-nope-B1-weak-0000/frames/0/spectrum", params={"x": 0, "y": 0})
    assert r.status_code == 404


def test_band_mosaic_tiles_ten_labelled_bands(d) -> None:
    r = d.client.get(f"/sessions/{d.sid}/frames/{d.idx['first']}/bands.png", params={"tile": 64})
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    img = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (2 * (64 + 22 + 4), 5 * (64 + 4), 3)  # 2 rows of 5 tiles, a label bar on each
    # each tile is stretched to its band's own level: the bright top-left square shows in every band
    tile = img[2 + 22: 2 + 22 + 64, 2: 2 + 64, 1].astype(int)
    assert tile[:8, :8].mean() > tile[-8:, -8:].mean() + 20


def test_coverage_states_and_report_map(d) -> None:
    cov = d.client.get(f"/sessions/{d.sid}/coverage").json()
    assert cov["elevations"] == ["E0", "E2"] and cov["azimuths_deg"] == [0.0, 90.0, 180.0, 270.0]
    assert cov["counts"] == {"captured": 4, "flagged": 1, "skipped": 1, "failed": 0, "pending": 2}
    by = {c["event_id"]: c for c in cov["cells"]}
    assert by[d.idx["skipped_event"]]["reason"].startswith("MoveStalled")
    assert [c["n"] for c in cov["cells"] if c["state"] == "flagged"] == [d.idx["flagged"]]
    page = d.client.get(f"/sessions/{d.sid}/report.html").text
    assert "<svg" in page and "coverage map" in page
    assert "href='#frame-" in page and "id='frame-" in page  # a cell links to its frame in the sheet
    assert "<details" in page  # the per-pose table stays, folded


def test_twin_flags_and_projected_labels_of_a_frame(d) -> None:
    n, url = d.idx["flagged"], f"/sessions/{d.sid}/frames/{{}}/twin"
    t = d.client.get(url.format(n)).json()
    assert t["checked"] and t["flags"] == ["off_axis"] and t["confidence"] == 0.9
    legend = [(i["index"], i["name"], i["pixels"]) for i in t["legend"]]
    assert legend == [(1, "gold_foil", 72), (2, "solar_panel", 30)]
    r = d.client.get(t["labels_url"])
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    assert "gold_foil" in r.headers["x-alt"]
    img = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img.shape == (N // 4, N // 4, 4)
    assert img[0, 0, 3] == 0 and img[3, 3, 3] == 255 and img[10, 5, 3] == 255  # background clear
    hexes = {i["index"]: i["colour"] for i in t["legend"]}
    bgr = {1: img[3, 3, :3], 2: img[10, 5, :3]}
    assert all(f"#{c[2]:02x}{c[1]:02x}{c[0]:02x}" == hexes[k] for k, c in bgr.items()), (bgr, hexes)
    # checked with nothing found (its own frame flag kept), and never checked: no labels, a 404 saying why
    t2 = d.client.get(url.format(d.idx["checked"])).json()
    assert t2["checked"] and t2["flags"] == [] and t2["frame_flags"] == ["yawed"] and t2["labels_url"] is None
    t0 = d.client.get(url.format(d.idx["first"])).json()
    assert not t0["checked"] and t0["legend"] == []
    r = d.client.get(f"/sessions/{d.sid}/frames/{d.idx['first']}/labels.png")
    assert r.status_code == 404 and "no projected labels" in r.json()["detail"]
    assert d.client.get(url.format(999)).status_code == 404
    cov = d.client.get(f"/sessions/{d.sid}/coverage").json()
    marked = {c["n"]: (c["twin_flags"], c["labels"]) for c in cov["cells"] if c["twin_flags"] or c["labels"]}
    assert marked == {n: (["off_axis"], True)} and cov["twin"] == {"checked": 2, "flagged": 1, "labelled": 1}


def test_live_spectrum_reads_the_newest_live_frame(d) -> None:
    r = d.client.get("/camera/live/spectrum", params={"x": 0, "y": 0})
    assert r.status_code in (200, 409)  # 409 before any live frame (another test may have streamed)
    d.client.put("/camera/live", json={"exposure_s": 0.004})
    assert d.client.get("/camera/live.mjpeg", params={"max_frames": 1}).status_code == 200
    s = d.client.get("/camera/live/spectrum", params={"x": 8, "y": 8, "w": 8, "h": 8}).json()
    assert s["source"].startswith("live/") and len(s["dn"]) == 10 and s["region"]["w"] == 8
    assert s["exposure_s"] == pytest.approx(0.004) and max(s["dn"]) > 0
    assert d.client.get("/camera/live/spectrum", params={"x": N, "y": 0}).status_code == 422


def test_reflectance_against_the_white_reference(d, tmp_path: Path) -> None:
    from m2s2hil.api.console.state import calibration_path_for

    model = d.rig.config.camera.model
    white = mosaic_of(2.0 * (band_levels(0) - DARK), model).astype(np.float32)  # a panel twice as bright
    path = calibration_path_for(d.manager)
    save_calibration(path, CameraCalibration(source=str(path), white_mosaic=white,
                                             white_reflectance=np.full(10, 0.9)),
                     bands_nm=list(model.bands_nm),
                     provenance={"exposure_s": 0.02, "gain": 1.0, "lighting": "weak", "captured_at": "now"})
    try:
        url = f"/sessions/{d.sid}/frames/{d.idx['first']}/spectrum"
        s = d.client.get(url, params={"x": 40, "y": 40}).json()
        # frame 10 ms, panel 20 ms: per unit exposure the frame is as bright as the 0.9 panel
        assert s["reflectance"] == pytest.approx([0.9] * 10, rel=1e-4)
        assert s["white_reference"]["same_lighting"] is True and not s["notes"]
        pics = d.client.get("/calibration/pictures").json()["items"]
        white_pic = next(p for p in pics if p["kind"] == "white")
        r = d.client.get(white_pic["url"])
        assert r.status_code == 200 and r.content[:4] == b"\x89PNG"
    finally:
        path.unlink()
        (path.parent / f"{path.stem}_white.tiff").unlink()


def test_calibration_pictures_dark_maps_and_phase_cost_map(d) -> None:
    r = d.client.post("/calibration/darks",
                      json={"exposures": [{"exposure_s": 0.004, "gain": 1.0}], "n_frames": 2})
    assert r.status_code == 201, r.text
    pics = d.client.get("/calibration/pictures").json()["items"]
    darks = [p for p in pics if p["kind"] == "dark"]
    assert darks and "hot pixels" in darks[0]["alt"]
    r = d.client.get(darks[0]["url"])
    assert r.status_code == 200 and r.content[:4] == b"\x89PNG"
    assert d.client.get("/calibration/darks/nope.json/map.png").status_code in (404, 422)
    r = d.client.post("/calibration/phase.png", json={"exposure_s": 0.01})
    assert r.status_code == 200 and r.content[:4] == b"\x89PNG", r.text
    assert "cost at origin" in r.headers["x-phase-summary"]


# ----------------------------------------------------------------------------- in the browser
@pytest.mark.slow
@pytest.mark.timeout(300)
def test_pictures_in_the_browser(d, new_page) -> None:
    from api_support import uvicorn_thread

    from m2s2hil.api import create_app

    # screenshots only when asked for (M2S2HIL_SCREENSHOTS=DIR): encoding them is most of the
    # browser's CPU time here; docs/images has the ones from a real simulated capture
    shots = os.environ.get("M2S2HIL_SCREENSHOTS")

    def shot(page, name: str, **kw) -> None:
        if shots:
            Path(shots).mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(Path(shots) / name), **kw)
    import httpx

    app = create_app(d.manager)
    with uvicorn_thread(app) as base:
        httpx.get(base + "/camera/live").raise_for_status()
        app.state.console.live.idle_stop_s = 0.0
        page = new_page(viewport={"width": 1400, "height": 950}, bypass_csp=True)
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(base + "/")
        # the browser view: a session's coverage map, a click on a cell opens the frame viewer
        page.click("#tabs button[data-view='browser']")
        page.locator("#sessions-table tbody tr", has_text=d.sid).click()
        page.wait_for_selector("#b-coverage rect.cov-flagged")
        assert page.locator("#b-coverage rect.cov-skipped").count() == 1
        assert page.locator("#b-coverage rect.cov-pending").count() == 2
        page.locator(f"#b-coverage rect[data-n='{d.idx['flagged']}']").click()
        page.wait_for_selector("#frame-viewer:not([hidden])")
        page.wait_for_function("document.getElementById('fv-title').textContent.endsWith('frame "
                               f"{d.idx['flagged']}')")
        # the centre cell's spectrum comes at once; a click elsewhere asks for that cell
        page.wait_for_function("window.m2s2hilPictures.fv.region !== null")
        assert page.locator("#b-coverage path.cov-twin").count() == 1
        page.wait_for_selector("#fv-labels:not([disabled])")
        box = page.locator("#fv-canvas").bounding_box()
        assert box is not None
        page.mouse.click(box["x"] + box["width"] / 2 - 0.45 * min(box["width"], box["height"]) + 4,
                         box["y"] + box["height"] / 2 - 0.45 * min(box["width"], box["height"]) + 4)
        page.wait_for_function("window.m2s2hilPictures.fv.region.x === 0")
        label = page.locator("#fv-spectrum canvas").get_attribute("aria-label")
        assert label is not None and "431 nm 148.0 DN" in label  # frame 1's top-left: 100 + 1 + 50 − 3
        # the twin on the same views: its flag on the coverage cell, its flags and labels in the viewer
        twin = page.locator("#fv-twin").inner_text()
        assert "twin ⚑ off_axis" in twin and "gold_foil" in twin and "solar_panel" in twin, twin
        assert page.evaluate("window.m2s2hilPictures.fv.labels.naturalWidth") == N // 4
        assert page.is_checked("#fv-labels")
        page.uncheck("#fv-labels")
        assert page.evaluate("localStorage.getItem('m2s2hil.fv.labels')") == "0"
        page.check("#fv-labels")
        # zoom with the wheel, then reset
        page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
        page.mouse.wheel(0, -400)
        page.wait_for_function("window.m2s2hilPictures.fv.scale > 1.5")
        tx = page.evaluate("window.m2s2hilPictures.fv.tx")  # a drag pans (the default drag mode)
        page.mouse.down()
        page.mouse.move(box["x"] + box["width"] / 2 + 60, box["y"] + box["height"] / 2, steps=4)
        page.mouse.up()
        assert page.evaluate("window.m2s2hilPictures.fv.tx") == pytest.approx(tx + 60, abs=2)
        shot(page, "console_frame_viewer.png")
        page.click("#fv-reset")
        assert page.evaluate("window.m2s2hilPictures.fv.scale") == 1
        page.select_option("#fv-mode", "bands")
        page.wait_for_function("window.m2s2hilPictures.fv.bandsGeom !== null")
        shot(page, "console_ten_bands.png")
        assert_band_labels_drawn(page)
        page.click("#fv-close")
        # the export's progress bar (what console.js's export loop shows for each polled job)
        bar = page.evaluate("""() => { const d = document.createElement('div');
            exportProgress(d, {fraction: 0.4, done: 2, total: 5});
            return [d.querySelector('progress').value, d.textContent]; }""")
        assert bar[0] == pytest.approx(0.4) and "40% · 2 of 5 frames" in bar[1], bar
        # the running view's coverage map repaints once when the watched session ends, even off
        # the sessions view (where its 3 s refresh stops): the session's state as pollRun sees it
        # is played through a route, "running" then "completed"
        said = {"state": "running"}

        def session_state(route) -> None:
            body = route.fetch().json()
            route.fulfill(json={**body, "state": said["state"]})

        page.route(f"**/sessions/{d.sid}", session_state)
        page.evaluate("(sid) => watch(sid)", d.sid)
        page.wait_for_function("document.getElementById('run-state').textContent === 'running' && "
                               f"document.getElementById('run-coverage').dataset.session === '{d.sid}'")
        page.evaluate("() => { const b = document.getElementById('run-coverage'); b.replaceChildren();"
                      " delete b.dataset.session; }")
        said["state"] = "completed"
        page.wait_for_selector("#run-coverage rect.cov-skipped", state="attached")
        page.unroute(f"**/sessions/{d.sid}")
        # the session-end sound: a labelled checkbox, on by default, remembered; no tone when off
        page.click("#tabs button[data-view='sessions']")  # it sits under "Running"
        shot(page, "console_run_coverage_ended.png", full_page=True)
        assert page.locator("label", has=page.locator("#sound-on")).inner_text().strip() == "sound"
        assert page.is_checked("#sound-on")
        played = page.evaluate("chime(false)")  # the page has had clicks: audio is unlocked if it can be
        page.uncheck("#sound-on")
        assert page.evaluate("[localStorage.getItem('m2s2hil.sound'), chime(false)]") == ["0", False]
        page.check("#sound-on")
        assert page.evaluate("window.m2s2hilSound.ctx !== null")  # made by the first gesture
        print(f"sound: tone played after a gesture in headless Chromium: {played}")
        # the live view: a click on the image gives the live spectrum
        page.click("#tabs button[data-view='setup']")
        page.click("#live-toggle")
        page.wait_for_function("window.m2s2hilLive && window.m2s2hilLive.frames >= 1", timeout=60000)
        page.wait_for_function("window.m2s2hilPictures.live.sensor !== null", timeout=30000)
        page.locator("#live-canvas").click(position={"x": 40, "y": 40})
        page.wait_for_function("document.querySelector('#live-spectrum canvas').getAttribute('aria-label')"
                               ".includes('431 nm')", timeout=30000)
        page.click("#live-toggle")
        shot(page, "console_live_spectrum.png", full_page=True)
        # phone: the viewer fills the screen and stacks the spectrum under the image
        page.set_viewport_size({"width": 390, "height": 844})
        page.click("#tabs button[data-view='browser']")
        page.locator(f"#b-coverage rect[data-n='{d.idx['first']}']").click()
        page.wait_for_function(f"window.m2s2hilPictures.fv.n === {d.idx['first']} && "
                               "window.m2s2hilPictures.fv.region !== null")
        width = page.evaluate("document.documentElement.scrollWidth")
        stage, spec = page.locator(".pic-stage").bounding_box(), page.locator("#fv-spectrum").bounding_box()
        shot(page, "console_frame_viewer_phone.png")
        assert width <= 390, f"the frame viewer is {width} px wide on a 390-px phone"
        assert stage and spec and spec["y"] >= stage["y"] + stage["height"] - 1  # stacked, not squeezed
        # the picture was fitted on the desktop's stage: on the phone's it is fitted and centred again
        placed = page.evaluate("""(() => {
            const f = window.m2s2hilPictures.fv, cv = document.getElementById('fv-canvas');
            const k = Math.min(cv.clientWidth / f.img.naturalWidth, cv.clientHeight / f.img.naturalHeight);
            return [f.tx, cv.clientWidth - f.tx - f.img.naturalWidth * k,
                    f.ty, cv.clientHeight - f.ty - f.img.naturalHeight * k]; })()""")
        assert abs(placed[0] - placed[1]) <= 1 and abs(placed[2] - placed[3]) <= 1, placed
        # fitted to the phone, bands.png's own labels are a few pixels tall: the viewer draws every
        # tile's wavelength again at a readable size
        assert page.evaluate("window.m2s2hilPictures.fv.mode") == "bands"
        assert_band_labels_drawn(page)
        # a session-end toast spans the phone's width: the viewer's chart scrolls up from under it
        page.evaluate("toast('session s-test completed', false)")
        page.locator(".pic-viewer").evaluate("v => { v.scrollTop = v.scrollHeight; }")
        chart, note = (page.locator(sel).bounding_box() for sel in ("#fv-spectrum", "#toasts"))
        shot(page, "console_frame_viewer_phone_toast.png")
        assert chart and note and chart["y"] + chart["height"] <= note["y"], (chart, note)
        page.close()  # before its server goes
    assert not errors, errors


def test_export_progress_reaches_the_callback_the_job_and_the_activity_log(d, tmp_path: Path) -> None:
    from m2s2hil.store.export import Progress, export_session

    calls: list[tuple[int, int]] = []
    with d.manager.reads.reading(d.sid) as st:
        export_session(st, tmp_path / "out", "m2s2", progress=lambda k, n: calls.append((k, n)))
    assert calls[0] == (1, 5) and calls[-1] == (5, 5), calls  # first and last always told
    assert [k for k, _ in calls] == sorted({k for k, _ in calls})  # rising, none twice
    p, seen = Progress(lambda k, n: seen.append(k), 100, every_s=3600.0), []  # throttled: ends only
    for _ in range(100):
        p.step()
    assert seen == [1, 100]
    since = d.client.get("/activity").json()["last_seq"]
    job = d.client.post(f"/sessions/{d.sid}/export/jobs", json={"layout": "m2s2", "overwrite": True})
    assert job.status_code == 202 and job.json()["fraction"] == 0.0 and job.json()["total"] == 5, job.text
    deadline = time.monotonic() + 60
    while (j := d.client.get(job.json()["url"]).json())["state"] == "running":
        assert time.monotonic() < deadline and 0.0 <= j["fraction"] <= 1.0, j
        time.sleep(0.02)
    assert j["state"] == "done" and (j["done"], j["total"], j["fraction"]) == (5, 5, 1.0), j
    log = d.client.get("/activity", params={"since": since, "kind": "action"}).json()["items"]
    marks = [a["details"].get("export_progress") for a in log if a["details"].get("job_id") == j["job_id"]]
    assert marks == [0.0, 1.0], log
