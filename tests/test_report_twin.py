"""The session report and the twin: a synthetic session's report (its renders and masks, no QC),
and a HIL session's twin registration and flags in its report; ``sessions show`` on a synthetic
session (its kind, its views as its plan)."""

from __future__ import annotations

import json
import re

import numpy as np
from cli_support import run_cli
from shared_sessions import N, export_session_of, small_rig, synthetic_session_of

from m2s2hil.analysis.report.session_html import write_session_report
from m2s2hil.analysis.segmenters.rgb import band_colours, camera_weights
from m2s2hil.plan import Sweep
from m2s2hil.store.catalogue import SYNTHETIC_PLAN_EVENT
from m2s2hil.store.session import SessionStore
from m2s2hil.twin.synth import PLAN_EVENT, SynthPlan, SynthRun


def test_report_of_a_synthetic_session_shows_its_renders_and_masks(shared_sessions, tmp_path):
    syn = synthetic_session_of(shared_sessions)  # E0 and E3 × azimuths 0 and 180
    out = tmp_path / "r.html"
    r = run_cli("report", syn.session_id, "--root", syn.root, "--out", out)
    assert r.exit_code == 0, r.stderr
    assert "synthetic: 4 of 4 view(s), 0 incomplete, 0 with an empty mask" in r.stdout
    assert "QC" not in r.stdout  # a render has no QC to have "no scores" of
    text = out.read_text()
    assert "Synthetic session" in text and "4 of 4 planned" in text
    assert len(re.findall(r"<figcaption>band \d+ · \d+ nm", text)) == 20  # ten per elevation
    assert len(re.findall(r"<img alt='synthetic/E[03]/az\d+/f0 (rgb|mask)'", text)) == 8
    assert "views whose mask has no mockup: 0" in text and "pro_silver" in text
    assert "QC per pose" not in text  # a render has no capture QC


def test_report_of_a_stopped_render_says_what_is_missing_and_why(tmp_path):
    rig = small_rig()
    bands = rig.camera.model.bands_nm
    run = SynthRun(tmp_path, rig, SynthPlan("iss", "B1", elevations=("E3",), azimuth_step_deg=90, size=16),
                   band_colours(bands, gamma=0.8), camera_weights(bands), session_id="syn-stopped")
    res = run.run(stop=lambda: "aborted by the operator" if len(run.store.frames()) >= 1 else None)
    assert res.state == "aborted"
    with SessionStore.open(tmp_path, "syn-stopped") as st:
        path, summary = write_session_report(st, tmp_path / "r.html", thumb_px=0)
    text = path.read_text()
    assert summary["views"] == 1 and summary["missing_views"] == 3 and summary["kind"] == "synthetic"
    assert "1 of 4 planned" in text and "stopped: aborted by the operator" in text
    assert "Contact sheet" not in text  # thumb 0: no pictures


def test_report_shows_a_hil_sessions_registration_and_twin_flags(tmp_path):
    sweep = Sweep(satellite="hubble", build="B2", lighting=["weak"], tilts=["E0"], azimuth_step_deg=180,
                  dark={"frames": 1})
    rng = np.random.default_rng(3)
    with SessionStore.create(tmp_path, sweep, small_rig(), session_id="hil-twin") as st:
        for ev in sweep.expand(st.rig):
            if ev.kind == "dark":
                st.write_dark(ev, np.full((N, N), 3.0, np.float32))
                continue
            flags = ["wrong_build", "lamp_dim"] if ev.nominal_azimuth_deg == 180 else []
            st.write_frame(ev, rng.integers(0, 1024, (N, N), dtype=np.uint16),
                           meta={"qc": {"score": 0.97, "flags": flags, "twin": {"flags": flags}}})
        st.record_event("twin_registration", {
            "placement": {"dx_mm": 2.5, "dy_mm": -1.25, "yaw_deg": 3.0, "tilt_bias_deg": -0.5, "scale": 1.01},
            "residual": 0.071, "frames": 2, "azimuth_span_deg": 180.0})
        path, summary = write_session_report(st, tmp_path / "r.html", thumb_px=0)
    text = path.read_text()
    assert summary["flag_counts"]["wrong_build"] == 1
    twin = text[text.index("<h2>Twin</h2>"):]
    for shown in ("(+2.50, -1.25) mm", "+3.00°", "-0.50°", "1.010", "0.071 (1 − mean IoU)", "2 over 180°"):
        assert shown in twin, shown
    assert re.search(r"Twin flags: <span class=flags>wrong_build</span> 1, "
                     r"<span class=flags>lamp_dim</span> 1", twin)


def test_report_of_a_hil_session_without_registration_says_so(tmp_path):
    sweep = Sweep(satellite="hubble", build="B2", lighting=["weak"], tilts=["E0"], azimuth_step_deg=180,
                  dark={"frames": 1})
    with SessionStore.create(tmp_path, sweep, small_rig(), session_id="hil-plain") as st:
        for ev in sweep.expand(st.rig):
            if ev.kind == "dark":
                st.write_dark(ev, np.full((N, N), 3.0, np.float32))
            else:
                st.write_frame(ev, np.full((N, N), 200, np.uint16), meta={"qc": {"score": 0.99, "flags": []}})
        path, _ = write_session_report(st, tmp_path / "r.html", thumb_px=0)
    text = path.read_text()
    assert "No registration stored" in text and "Twin flags: none." in text


def test_sessions_show_prints_a_synthetic_sessions_kind_and_planned_views(tmp_path):
    rig = small_rig()
    bands = rig.camera.model.bands_nm
    run = SynthRun(tmp_path, rig, SynthPlan("hubble", "B2", elevations=("E0", "E3"), azimuth_step_deg=90,
                                            size=16),
                   band_colours(bands, gamma=0.8), camera_weights(bands), session_id="syn-show")
    run.run(stop=lambda: "daemon shutdown" if len(run.store.frames()) >= 3 else None)
    r = run_cli("sessions", "show", "syn-show", "--root", tmp_path, "--json")
    assert r.exit_code == 0, r.stderr
    s = json.loads(r.stdout)
    got = (s["kind"], s["planned_frames"], s["planned_darks"], s["frames"], s["frames_planned_stored"],
           s["missing"])
    assert got == ("synthetic", 8, 0, 3, 3, 5)  # the HIL sweep stored with it would plan E0 only
    r = run_cli("sessions", "show", "syn-show", "--root", tmp_path)
    assert re.search(r"kind\s*│\s*synthetic", r.stdout), r.stdout


def test_a_hil_sessions_summary_says_hil(shared_sessions):
    with export_session_of(shared_sessions).open() as st:
        s = st.summary()
    assert s["kind"] == "hil" and s["planned_darks"] > 0 and s["planned_frames"] == s["frames_planned_stored"]


def test_the_store_reads_the_plan_event_the_twin_writes():
    assert SYNTHETIC_PLAN_EVENT == PLAN_EVENT


def test_the_reports_mask_colours_are_the_consoles():
    from m2s2hil.analysis.report.synthetic_html import PALETTE
    from m2s2hil.api.console.pictures import PALETTE as CONSOLE

    assert PALETTE == CONSOLE


def test_the_consoles_report_of_a_synthetic_session_is_its_renders(shared_sessions, tmp_path):
    from api_support import daemon

    syn = synthetic_session_of(shared_sessions).copy_to(tmp_path / "data")
    with daemon(syn.root, start=False) as d:
        r = d.client.get(f"/sessions/{syn.session_id}/report.html")
    assert r.status_code == 200, r.text
    assert "Synthetic session" in r.text and "4 of 4 planned" in r.text and "<h2>Contact sheet</h2>" in r.text
