"""The synthetic domain (m2s2hil.twin.synth): renders by the paper's protocol, its own session kind."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
from cli_support import run_cli
from m2s2hil.simulators.clock import VirtualClock
from m2s2hil.simulators.scene import Scene
from shared_sessions import small_rig, synthetic_session_of

from m2s2hil.analysis.segmenters.rgb import band_colours, camera_weights, wavelength_to_rgb
from m2s2hil.catalog import load_catalog
from m2s2hil.errors import UsageError
from m2s2hil.plan import Sweep
from m2s2hil.sim_config import build_world
from m2s2hil.store.session import SessionStore
from m2s2hil.twin.synth import SynthPlan, SynthRun, band_images, planned_views, pose_key


@pytest.fixture()
def synth(shared_sessions):
    return synthetic_session_of(shared_sessions)


def test_every_pose_has_rgb_ten_bands_and_a_mask(synth):
    with synth.open() as st:
        assert st.kind == "synthetic" and st.state == "completed" and st.verify() == []
        frames = st.frames()
        assert sorted({pose_key(f.meta, f.event_id) for f in frames}) == sorted(
            (e, a) for e in ("E0", "E3") for a in (0, 180))
        e3 = next(f for f in frames if f.meta["elevation"] == "E3")
        assert e3.meta["pose"]["tilt_deg"] == 30.0 and e3.meta["domain"] == "synthetic"
        assert "raw" not in e3.files
        rgb, bands, mask = band_images(st, e3.event_id)
    assert rgb.shape == (32, 32, 3) and bands.shape == (10, 32, 32, 3) and mask.shape == (32, 32)
    names = e3.meta["class_names"]
    assert set(np.unique(mask)) <= set(range(len(names))) and (mask > 0).any()


def test_band_renders_are_lit_with_the_bands_colour(synth):
    with synth.open() as st:
        fr = next(f for f in st.frames() if f.meta["elevation"] == "E0")
        rgb, bands, mask = band_images(st, fr.event_id)
        lights = np.array(fr.meta["synthetic"]["band_light_rgb"])
    bands_nm = fr.meta["synthetic"]["bands_nm"]
    assert np.allclose(lights, band_colours(bands_nm, gamma=0.8), atol=1e-6)
    assert lights[5].tolist() == pytest.approx(list(wavelength_to_rgb(666.0, 0.8)), abs=1e-6)
    red = bands[5][mask > 0].astype(float)  # 666 nm: pure red light, nothing in green or blue
    assert red[:, 0].mean() > 10 and red[:, 1].max() == 0 and red[:, 2].max() == 0
    blue = bands[0][mask > 0].astype(float)  # 431 nm: blue with a little red (Bruton's violet)
    assert blue[:, 2].mean() > blue[:, 0].mean() and blue[:, 1].max() == 0
    assert rgb[mask > 0].mean() > red.mean()  # white light is brighter than one band's


def test_mask_is_the_scenes_label_map_at_the_pose(synth):
    rig = small_rig()
    m = rig.camera.model
    with synth.open() as st:
        fr = next(f for f in st.frames() if pose_key(f.meta) == ("E0", 180))
        _, _, mask = band_images(st, fr.event_id)
    scene = Scene(32, 32, m.bands_nm, m.fwhm_nm, m.layout)
    b = load_catalog().build("hubble", "B2")
    lamps = {ch: 1.0 for ch in rig.lamp_channels("strong")}
    world = build_world(rig, VirtualClock())
    sh = scene.render("hubble", b.materials, 180.0, rig.elevations["E0"], lamps, world.lamp_info, build="B2")
    assert np.array_equal(mask, sh.label)


def test_a_hil_session_needs_its_raw_mosaic(tmp_path):
    sweep = Sweep(satellite="hubble", build="B2", lighting=["weak"], tilts=["E1"], azimuth_step_deg=180)
    with SessionStore.create(tmp_path, sweep, small_rig()) as st:
        assert st.kind == "hil"
        ev = next(e for e in sweep.expand(st.rig) if e.kind == "frame")
        with pytest.raises(UsageError, match="raw mosaic is required in a hil session"):
            st.write_frame(ev, None)


def test_synth_command_refuses_bad_input_in_one_line(tmp_path):
    r = run_cli("synth", "--sat", "hubble", "--build", "B2", "--tilts", "E9", "--root", tmp_path)
    assert r.exit_code == 2 and "unknown elevation 'E9'" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    r = run_cli("synth", "--sat", "hubble", "--build", "B2", "--size", "4", "--root", tmp_path)
    assert r.exit_code == 2 and "outside 16" in r.stderr


class Threshold:
    """A stand-in segmenter: foreground where the brightest channel passes half its maximum."""

    name = "threshold"

    def segment(self, cube: np.ndarray) -> np.ndarray:
        top = cube.max(axis=0)
        return (top > 0.5 * top.max()).astype(np.int64)


def test_fused_bands_is_the_majority_of_bands_5_9_10(synth):
    from m2s2hil.analysis.evaluation.synthetic import _cube, fused_bands

    with synth.open() as st:
        _, bands, _ = band_images(st, st.frames()[0].event_id)
    seg = Threshold()
    maps = [seg.segment(_cube(bands[b - 1])) for b in (5, 9, 10)]
    expected = (np.sum(maps, axis=0) >= 2).astype(np.int64)
    assert np.array_equal(fused_bands(seg, bands) > 0, expected > 0)
    with pytest.raises(Exception, match="outside 1..10"):
        fused_bands(seg, bands, (0, 5))


def test_synthetic_columns_and_sim_to_real(tmp_path, synth):
    from shared_sessions import hil_with_labels

    from m2s2hil.analysis.evaluation.synthetic import evaluate_synthetic

    sid, _ = hil_with_labels(tmp_path / "root")
    out = tmp_path / "eval"
    with synth.open() as st, SessionStore.open(tmp_path / "root", sid) as hil:
        files = evaluate_synthetic(st, Threshold(), out, hil=hil)
    rows = files["synthetic_table2.csv"].read_text().splitlines()
    assert rows[0].startswith("satellite,build,classes,elevation,n,precision_rgb")
    assert [row.split(",")[:5] for row in rows[1:]] == [["hubble", "B2", "5", e, "2"] for e in ("E0", "E3")]
    for row in rows[1:]:
        vals = [float(x) for x in row.split(",")[5:] if x != "nan"]
        assert all(0.0 <= v <= 1.0 for v in vals) and len(vals) >= 6
    pairs = files["sim_to_real.csv"].read_text().splitlines()
    assert len(pairs) == 3 and {p.split(",")[1] for p in pairs[1:]} == {"0", "180"}
    assert all(p.split(",")[4] == "truth_labels" for p in pairs[1:])
    assert "| hubble | B2 | 5 | E3 | 2 |" in files["synthetic_table2.md"].read_text()


@pytest.mark.slow
def test_evaluate_command_gives_a_synthetic_session_its_columns(tmp_path, synth):
    r = run_cli("evaluate", synth.path, "--out", tmp_path, "--limit", "1")
    assert r.exit_code == 0, r.stderr
    assert "| hubble | B2 | 5 | E0 | 1 |" in r.stdout and (tmp_path / "synthetic_table2.csv").is_file()
    # a sweep segmenter is fitted on a HIL session's sweep; here it is refused, saying so
    r = run_cli("evaluate", synth.path, "--out", tmp_path / "sweep", "--segmenter", "spectral-sweep")
    assert r.exit_code == 2 and "view by view" in r.stderr and not (tmp_path / "sweep").exists(), r.output
    r = run_cli("evaluate", synth.path, "--out", tmp_path / "pose", "--segmenter", "spectral-pose")
    assert r.exit_code == 2 and "diffuse light" in r.stderr and not (tmp_path / "pose").exists(), r.output


def test_synth_command_renders_a_session_of_its_own_kind(tmp_path):
    r = run_cli("synth", "--sat", "voyager", "--build", "B1", "--tilts", "E3", "--step", "180",
                "--size", "16", "--root", tmp_path, "--session-id", "syn-voyager-b1")
    assert r.exit_code == 0, r.stderr
    assert "rendered 2 synthetic views of voyager B1" in r.stdout
    with SessionStore.open(tmp_path, "syn-voyager-b1") as st:
        assert st.kind == "synthetic" and st.state == "completed" and planned_views(st) == 2
        assert [pose_key(f.meta) for f in st.frames()] == [("E3", 0), ("E3", 180)]
        summary = st.summary()
    assert summary["planned_frames"] == summary["frames"] == 2 and summary["planned_darks"] == 0


def test_a_stopped_render_keeps_its_views_and_says_why(tmp_path):
    rig = small_rig()
    bands = rig.camera.model.bands_nm
    run = SynthRun(tmp_path, rig, SynthPlan("iss", "B2", elevations=("E0",), azimuth_step_deg=90, size=16),
                   band_colours(bands, gamma=0.8), camera_weights(bands), session_id="syn-stopped")
    assert run.total == 4
    seen: list[str] = []
    res = run.run(progress=lambda done, total, ev: seen.append(ev.event_id),
                  stop=lambda: "enough" if len(seen) == 2 else None)
    assert res.state == "aborted" and res.views == 2 and res.planned == 4
    assert seen == ["synthetic/E0/az000/f0", "synthetic/E0/az090/f0"]
    with SessionStore.open(tmp_path, "syn-stopped") as st:
        assert st.state == "aborted" and len(st.frames()) == 2 and st.verify() == []
        stopped = [e["payload"] for e in st.events() if e["kind"] == "synthetic_stopped"]
    assert stopped == [{"reason": "enough", "views": 2, "of": 4}]


def test_a_bad_plan_or_mesh_is_refused_before_any_session_exists(tmp_path):
    from m2s2hil.simulators.meshes import MeshFileError

    from m2s2hil.twin.simulated import rig_with

    bands = small_rig().camera.model.bands_nm
    lights, weights = band_colours(bands, gamma=0.8), camera_weights(bands)
    rig = rig_with(64, mockups={"hubble": {"B2": {"mesh": str(tmp_path / "gone.3mf")}}})
    with pytest.raises(MeshFileError, match=r"gone.3mf: no such file or folder"):
        SynthRun(tmp_path / "root", rig, SynthPlan("hubble", "B2", size=16), lights, weights)
    for plan, match in ((SynthPlan("hubble", "B9"), "unknown build of Hubble 'B9'"),
                        (SynthPlan("hubble", "B2", light="sunny"), "unknown lighting condition 'sunny'"),
                        (SynthPlan("hubble", "B2", azimuth_step_deg=0.0), "azimuth step 0.0 deg is outside")):
        with pytest.raises(UsageError, match=match):
            SynthRun(tmp_path / "root", small_rig(), plan, lights, weights)
    assert not (tmp_path / "root").exists() or not any((tmp_path / "root").iterdir())


# ------------------------------------------------------------------------ through the daemon
def _wait_finished(d, sid: str, timeout: float = 60.0) -> dict:
    """The status once the render has ended (polled at 10 Hz: a render of a few views takes ~1 s)."""
    deadline = time.monotonic() + timeout
    while (st := d.client.get(f"/sessions/{sid}").json())["state"] in ("queued", "running", "aborting"):
        assert time.monotonic() < deadline, st
        time.sleep(0.1)
    return st


SYNTH_BODY = {"satellite": "hubble", "build": "B2", "tilts": ["E0", "E3"], "azimuth_step_deg": 180,
              "size": 16}


def test_daemon_renders_a_synthetic_session_watched_like_a_capture(tmp_path):
    from api_support import daemon, parse_sse

    from m2s2hil.api.routes.synthetic import jobs_of

    with daemon(tmp_path / "data") as d:
        r = d.client.post("/synthetic", json=SYNTH_BODY)
        assert r.status_code == 202, r.text
        body = r.json()
        sid = body["session_id"]
        assert body["planned_events"] == 4 and r.headers["location"] == f"/sessions/{sid}" == body["url"]
        st = _wait_finished(d, sid)
        assert st["state"] == "completed" and st["mode"] == "synthetic" and st["live"] is True
        assert st["done"] == st["total"] == st["planned_frames"] == 4 and st["planned_darks"] == 0
        assert st["last_event_id"] == "synthetic/E3/az180/f0" and st["progress"] == 1.0
        msgs = parse_sse(d.client.get(f"/sessions/{sid}/events").text)
        kinds = [m["event"] for m in msgs]
        assert kinds == ["state", "state", *["frame", "progress"] * 4, "finished"]
        assert [m["id"] for m in msgs] == [f"1-{n}" for n in range(1, 12)]
        frames = [json.loads(m["data"]) for m in msgs if m["event"] == "frame"]
        assert [(f["elevation"], f["azimuth_deg"]) for f in frames] == [
            ("E0", 0.0), ("E0", 180.0), ("E3", 0.0), ("E3", 180.0)]
        assert json.loads(msgs[-1]["data"])["state"] == "completed"
        again = parse_sse(d.client.get(f"/sessions/{sid}/events", headers={"Last-Event-ID": "1-9"}).text)
        assert [m["id"] for m in again] == ["1-10", "1-11"]
        listed = d.client.get("/sessions").json()["items"]
        assert [(s["mode"], s["total"]) for s in listed if s["session_id"] == sid] == [("synthetic", 4)]
        page = d.client.get(f"/sessions/{sid}/frames").json()
        assert page["total"] == 4 and {"rgb", "band_09", "truth_labels"} <= set(page["items"][0]["files"])
        for action in ("pause", "resume"):
            r = d.client.post(f"/sessions/{sid}/{action}")
            assert r.status_code == 409 and "synthetic render" in r.json()["detail"]
        job = d.client.post(f"/sessions/{sid}/export/jobs", json={"layout": "m2s2"}).json()
        done = None
        for _ in range(600):
            done = d.client.get(f"/exports/jobs/{job['job_id']}").json()
            if done["state"] != "running":
                break
            time.sleep(0.1)
        assert done is not None and done["state"] == "done", done
        exported = d.root / "exports" / sid / "m2s2"
        assert len(list((exported / "Synthetic" / "Hubble" / "b2" / "e3").glob("band10_*.png"))) == 2
        jobs_of(d.manager)._jobs.clear()  # forgotten, as after a restart: read from the journal
        disk = d.client.get(f"/sessions/{sid}").json()
        assert disk["live"] is False and disk["mode"] == "synthetic" and disk["state"] == "completed"
        assert disk["done"] == disk["total"] == 4
        r = d.client.post(f"/sessions/{sid}/resume")  # never handed to the capture engine
        assert r.status_code == 409 and "render it again" in r.json()["detail"]
    with SessionStore.open(tmp_path / "data", sid) as stored:
        assert stored.kind == "synthetic" and stored.state == "completed" and stored.verify() == []


@pytest.mark.parametrize("change, status, match", [
    ({"satellite": "apollo"}, 422, "unknown satellite 'apollo'"),
    ({"tilts": ["E7"]}, 422, "unknown elevation 'E7'"),
    ({"size": 8}, 422, "body.size"),
    ({"azimuth_step_deg": 1.0, "tilts": []}, 422, "1440 views of 16² (1440 frames of 512²); this daemon "
                                                  "accepts at most 100"),
    ({"azimuth_step_deg": 90, "size": 2048}, 422, "8 views of 2048² (128 frames of 512²)"),
    ({"colour": "red"}, 422, "body.colour"),
])
def test_daemon_refuses_a_bad_render_with_the_reason(tmp_path, change, status, match):
    from api_support import daemon

    with daemon(tmp_path / "data", start=False, max_plan_frames=100) as d:
        r = d.client.post("/synthetic", json={**SYNTH_BODY, **change})
        assert r.status_code == status and match in r.json()["detail"], r.text
    assert not (tmp_path / "data").exists() or not any(p.is_dir() for p in (tmp_path / "data").iterdir())


def test_daemon_aborts_a_render_and_cancels_a_waiting_one(tmp_path):
    from api_support import daemon

    long = {**SYNTH_BODY, "tilts": [], "azimuth_step_deg": 5}  # 4 elevations × 72 azimuths
    with daemon(tmp_path / "data", queue_limit=1) as d:
        first = d.client.post("/synthetic", json=long).json()["session_id"]
        # the render thread takes the first off the queue (later on a loaded machine): only then
        # is the one place in the queue free for the second
        d.wait(first, lambda st: st["state"] != "queued")
        second = d.client.post("/synthetic", json=long).json()
        assert second["state"] == "queued" and second["queue_position"] == 1, second
        full = d.client.post("/synthetic", json=long)
        assert full.status_code == 429 and "already wait to render (limit 1)" in full.json()["detail"]
        r = d.client.post(f"/sessions/{second['session_id']}/abort")
        assert r.status_code == 200 and r.json()["state"] == "cancelled"
        d.wait(first, lambda st: st["done"] >= 1)
        assert d.client.post(f"/sessions/{first}/abort").json()["state"] in ("aborting", "aborted")
        st = d.wait_done(first)
        assert st["state"] == "aborted" and 1 <= st["done"] < 288 and st["total"] == 288
        third = d.client.post("/synthetic", json=long).json()["session_id"]
        d.wait(third, lambda st: st["done"] >= 1)
    # The daemon's shutdown stopped the third at its next view.
    from m2s2hil.api.routes.synthetic import jobs_of

    job = jobs_of(d.manager).job(third)
    assert job is not None and job.finished.wait(30)
    with SessionStore.open(tmp_path / "data", third) as st3, \
            SessionStore.open(tmp_path / "data", second["session_id"]) as st2:
        assert st3.state == "aborted" and st2.state == "cancelled" and not st2.frames()
        assert [e["payload"]["reason"] for e in st3.events() if e["kind"] == "synthetic_stopped"] == [
            "daemon shutdown"]


def test_serve_resume_leaves_a_killed_render_alone(tmp_path):
    from api_support import daemon, small_rig_config

    cfg = small_rig_config(64)
    bands = cfg.camera.model.bands_nm
    run = SynthRun(tmp_path / "data", cfg, SynthPlan("hubble", "B2", elevations=("E0",), azimuth_step_deg=180,
                                                     size=16),
                   band_colours(bands, gamma=0.8), camera_weights(bands), session_id="syn-killed")
    run.store.close()  # as a killed process leaves it: queued, nothing rendered
    with daemon(tmp_path / "data", rig_config=cfg, start=False) as d:
        resumed = d.manager.start(resume_interrupted=True)
        if resumed:
            d.wait_done("syn-killed")
    with SessionStore.open(tmp_path / "data", "syn-killed") as st:
        assert not any("raw" in f.files for f in st.frames()), "HIL frames captured into a synthetic session"
    assert resumed == []


@pytest.mark.slow  # a real process: its start-up is most of it
@pytest.mark.timeout(120)
def test_ctrl_c_ends_a_render_after_its_view_keeping_what_is_stored(tmp_path):
    import os
    import signal
    import subprocess
    import sys

    cmd = [sys.executable, "-c", "from m2s2hil.cli import main; main()", "synth", "--sat", "iss", "--build",
           "B1", "--step", "1", "--size", "16", "--root", str(tmp_path), "--session-id", "syn-ctrl-c"]
    env = {k: v for k, v in os.environ.items() if k != "M2S2HIL_DATA"}
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
    assert proc.stderr is not None
    for line in proc.stderr:  # the first progress line: rendering has begun
        if "/1440 views" in line:
            break
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "what is rendered is kept" in err and "(aborted)" in err
    with SessionStore.open(tmp_path, "syn-ctrl-c") as st:
        assert st.state == "aborted" and 36 <= len(st.frames()) < 1440 and st.verify() == []
        assert [e["payload"]["reason"] for e in st.events() if e["kind"] == "synthetic_stopped"] == [
            "interrupted (Ctrl-C)"]


def test_a_render_is_guarded_like_any_change(tmp_path):
    from api_support import TOKEN, daemon

    with daemon(tmp_path / "data", token=TOKEN, start=False) as d:
        r = d.client.post("/synthetic", json=SYNTH_BODY, headers={"Authorization": ""})
        assert r.status_code == 401
        r = d.client.post("/synthetic", json=SYNTH_BODY, headers={"Origin": "http://elsewhere.example"})
        assert r.status_code == 403 and "cross-site" in r.json()["detail"]
    assert not (tmp_path / "data").exists() or not any(p.is_dir() for p in (tmp_path / "data").iterdir())


def test_a_render_left_by_a_killed_daemon_can_be_aborted_not_resumed(tmp_path):
    from api_support import daemon

    rig = small_rig()
    bands = rig.camera.model.bands_nm
    run = SynthRun(tmp_path / "data", rig, SynthPlan("hubble", "B1", elevations=("E3",), size=16),
                   band_colours(bands, gamma=0.8), camera_weights(bands), session_id="syn-left")
    run.store.close()  # queued on disk, no daemon renders it
    with daemon(tmp_path / "data", start=False) as d:
        st = d.client.get("/sessions/syn-left").json()
        got = (st["state"], st["mode"], st["live"], st["done"], st["total"])
        assert got == ("queued", "synthetic", False, 0, 36)
        r = d.client.post("/sessions/syn-left/resume")
        assert r.status_code == 409 and "synthetic render (queued)" in r.json()["detail"]
        r = d.client.post("/sessions/syn-left/abort")
        assert r.status_code == 200 and r.json()["state"] == "aborted"
        assert d.client.post("/sessions/syn-left/abort").status_code == 409
