"""A synthetic session across a daemon restart: never resumed by the capture engine, a render a
killed process left unfinished ended as ``aborted`` by ``serve --resume`` (views kept), and the
listing counting its views, not the HIL sweep stored with it."""

from __future__ import annotations

import pytest
from api_support import daemon, small_rig_config
from shared_sessions import synthetic_session_of

from m2s2hil.analysis.segmenters.rgb import band_colours, camera_weights
from m2s2hil.daemon.errors import Conflict
from m2s2hil.daemon.listing import KILLED_RENDER_REASON, end_killed_renders, interrupted_sessions
from m2s2hil.plan import Sweep
from m2s2hil.store.session import SessionStore
from m2s2hil.twin.synth import SynthPlan, SynthRun


def _killed_after_its_views(root, session_id: str) -> None:
    """A render whose process died after its two views were stored, before it ended."""
    cfg = small_rig_config(64)
    bands = cfg.camera.model.bands_nm
    run = SynthRun(root, cfg, SynthPlan("hubble", "B2", elevations=("E0",), azimuth_step_deg=180, size=16),
                   band_colours(bands, gamma=0.8), camera_weights(bands), session_id=session_id)
    run.store.complete = lambda state="completed": {}  # type: ignore[method-assign]  # killed before it
    run.run()


def test_serve_resume_ends_a_killed_render_as_aborted_keeping_its_views(tmp_path):
    root = tmp_path / "data"
    _killed_after_its_views(root, "syn-running")
    with SessionStore.open(root, "syn-running") as st:
        assert st.state == "running" and len(st.frames()) == 2
    with daemon(root, rig_config=small_rig_config(64), start=False) as d:
        assert d.manager.start(resume_interrupted=True) == []
        st = d.client.get("/sessions/syn-running").json()
        assert (st["state"], st["mode"], st["done"], st["total"]) == ("aborted", "synthetic", 2, 2)
        assert KILLED_RENDER_REASON in st["error"]
    with SessionStore.open(root, "syn-running") as st:
        assert st.state == "aborted" and st.verify() == [] and (st.path / "manifest.json").is_file()
        assert not any("raw" in f.files for f in st.frames())
        stopped = [e["payload"] for e in st.events() if e["kind"] == "synthetic_stopped"]
        assert stopped == [{"reason": KILLED_RENDER_REASON, "was": "running", "views": 2, "of": 2,
                            "quarantined": 0}]


def test_a_render_another_process_holds_is_left_alone(tmp_path):
    root = tmp_path / "data"
    cfg = small_rig_config(64)
    bands = cfg.camera.model.bands_nm
    run = SynthRun(root, cfg, SynthPlan("hubble", "B2", elevations=("E0",), azimuth_step_deg=180, size=16),
                   band_colours(bands, gamma=0.8), camera_weights(bands), session_id="syn-live")
    try:  # its owner lock held, as by a `m2s2hil synth` still rendering on this root
        assert interrupted_sessions(root) == [] and end_killed_renders(root) == []
        with SessionStore.open(root, "syn-live") as st:
            assert st.state == "queued" and not any(e["kind"] == "synthetic_stopped" for e in st.events())
    finally:
        run.discard()


def test_requeue_refuses_a_synthetic_session(tmp_path):
    root = tmp_path / "data"
    _killed_after_its_views(root, "syn-requeue")
    with daemon(root, rig_config=small_rig_config(64), start=False) as d, \
            pytest.raises(Conflict, match="synthetic render: it is not resumed"):
            d.manager.submissions.requeue("syn-requeue", reason="test")
    with SessionStore.open(root, "syn-requeue") as st:
        assert st.state == "running" and not any(e["kind"] == "requeued" for e in st.events())


def test_a_killed_capture_beside_a_render_is_still_resumed(tmp_path):
    root = tmp_path / "data"
    _killed_after_its_views(root, "syn-beside")
    sweep = Sweep(satellite="hubble", build="B2", lighting=["weak"], tilts=["E1"], azimuth_step_deg=180)
    with SessionStore.create(root, sweep, small_rig_config(64), session_id="hil-killed") as st:
        st.set_state("running")
    assert interrupted_sessions(root) == ["hil-killed"]
    with SessionStore.open(root, "syn-beside") as st:  # listing what to resume changes nothing
        assert st.state == "running"
    assert end_killed_renders(root) == ["syn-beside"] and interrupted_sessions(root) == ["hil-killed"]


def test_the_listing_counts_a_synthetic_sessions_views_after_a_restart(shared_sessions, tmp_path):
    syn = synthetic_session_of(shared_sessions).copy_to(tmp_path / "data")  # 4 views: E0 and E3 × 2
    with daemon(syn.root, start=False) as d:  # a daemon that never rendered it
        rows = d.client.get("/sessions").json()
        items = rows["items"] if isinstance(rows, dict) else rows
        row = next(r for r in items if r["session_id"] == syn.session_id)
        assert (row["done"], row["total"], row["planned_frames"], row["planned_darks"]) == (4, 4, 4, 0)
        assert row["progress"] == 1.0
