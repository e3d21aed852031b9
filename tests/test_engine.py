"""The capture engine on the simulated rig: a session end to end, control, QC hook, disk space."""

from __future__ import annotations

import shutil
import threading
import time

import numpy as np
import pytest
from engine_helpers import assert_rig_safe, session, small_sweep, wait_for_state

from m2s2hil.engine.state import (
    Captured,
    FrameStored,
    IllegalTransition,
    Progress,
    RunState,
    SessionFinished,
    StateChanged,
)
from m2s2hil.store.frame_files import decode_image

S = RunState


def test_session_end_to_end(tmp_path) -> None:
    with session(tmp_path) as (rig, store, engine, events):
        cfg = rig.config
        status = engine.run()
        assert status.state is S.COMPLETED
        planned = engine.events
        assert status.done == status.total == len(planned) == 5  # 1 dark + 4 frames
        assert status.progress == 1.0 and status.eta_s == 0.0 and status.skipped == 0
        assert 0.5 < status.efficiency <= 1.0
        assert store.verify() == []
        assert store.state == "completed"
        frames = sorted(store.frames(), key=lambda f: f.index)  # two writers: commit order varies
        assert [f.event_id for f in frames] == [e.event_id for e in planned if e.kind == "frame"]
        weak = cfg.lamp_channels("weak")
        for f, ev in zip(frames, [e for e in planned if e.kind == "frame"], strict=True):
            m = f.meta
            assert m["exposure_s"] == pytest.approx(ev.exposure_s)
            assert m["gain"] == ev.gain and m["temperature_c"] == pytest.approx(35.0)
            assert abs(m["pose"]["turntable_deg"] - ev.azimuth_deg) <= cfg.axes["turntable"].tolerance_deg
            assert abs(m["pose"]["tilt_deg"] - ev.tilt_deg) <= cfg.axes["tilt"].tolerance_deg
            assert tuple(m["lamps_on"]) == weak
            # lamps had their warm-up before the exposure
            assert min(m["lamp_on_s"].values()) >= max(cfg.lamps[n].warmup_s for n in cfg.lighting["weak"])
            assert m["dark_id"] == ev.dark_id and m["dark"]["n_frames"] == 2
            assert m["processing_method"] == "superpixel" and m["software_version"]
            assert m["rig_digest"] == cfg.digest and isinstance(m["block_id"], int)
            assert m["timestamp"] > 1e9 and m["clock_s"] > 0
            # the simulator's ground truth travels with the frame
            labels = decode_image(store.read_file(f.files["truth_labels"]))
            assert labels.shape == (cfg.camera.model.height, cfg.camera.model.width)
            assert labels.max() > 0 and m["truth"]["class_names"][0] == "background"
            assert m["truth"]["azimuth_deg"] == pytest.approx(ev.azimuth_deg, abs=0.1)
        assert [d.dark_id for d in store.darks()] == ["dark/8000us/g1"]
        assert_rig_safe(rig)
    seqs = [e.seq for e in events]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    assert isinstance(events[-1], SessionFinished) and events[-1].state is S.COMPLETED
    assert sum(isinstance(e, FrameStored) for e in events) == 4
    dones = [e.done for e in events if isinstance(e, Progress)]
    assert dones == sorted(dones) and dones[-1] == 5
    states = [(e.old, e.new) for e in events if isinstance(e, StateChanged)]
    assert states == [(S.IDLE, S.RUNNING), (S.RUNNING, S.COMPLETED)]


def test_illegal_control_is_rejected(tmp_path) -> None:
    with session(tmp_path) as (_rig, _store, engine, _events):
        for action in (engine.pause, engine.resume):
            with pytest.raises(IllegalTransition):
                action()
        assert engine.state is S.IDLE
        engine.run()
        for action in (engine.pause, engine.resume, engine.abort, engine.run):
            with pytest.raises(IllegalTransition):
                action()
        assert engine.state is S.COMPLETED


# A pause or abort is honoured at the first boundary after it is asked for; with 12 poses
# and at most 1 + 1 + 1 + 2 frames in the pipeline, that is always mid-session.
MID = dict(process_depth=1, store_depth=1, store_workers=1)


def test_pause_parks_safely_and_resume_finishes(tmp_path) -> None:
    with session(tmp_path, small_sweep(azimuth_step_deg=30), **MID) as (rig, store, engine, events):
        parked = threading.Event()

        def pause_after_first_frame(e) -> None:
            if isinstance(e, FrameStored) and e.index == 1:
                engine.pause()
            if isinstance(e, StateChanged) and e.new is S.PAUSED:
                parked.set()

        engine.subscribe(pause_after_first_frame)
        engine.start()
        assert parked.wait(timeout=30), f"never paused: {engine.state.value}"
        st = engine.status()
        assert st.pause_reason == "operator" and st.done < st.total
        assert_rig_safe(rig)
        n_stored = len(store.frames())
        with pytest.raises(IllegalTransition):
            engine.pause()
        engine.resume()
        final = engine.wait(timeout=60)
        assert final.state is S.COMPLETED and final.done == final.total
        assert store.verify() == []
        assert_rig_safe(rig)
    transitions = [e.new for e in events if isinstance(e, StateChanged)]
    assert transitions == [S.RUNNING, S.PAUSING, S.PAUSED, S.RUNNING, S.COMPLETED]
    # Nothing was captured or stored while parked: between "paused" and "running" again the
    # event stream (in the engine's own order) holds no capture and no stored frame.
    seq = [type(e).__name__ if not isinstance(e, StateChanged) else e.new for e in events]
    paused_at, resumed_at = seq.index(S.PAUSED), seq.index(S.RUNNING, seq.index(S.PAUSED))
    assert not {"Captured", "FrameStored"} & set(seq[paused_at:resumed_at])
    # ... and what was stored when it parked is exactly what the events reported before it.
    assert sum(1 for e in events[:paused_at] if isinstance(e, FrameStored)) == n_stored


def test_abort_at_a_boundary_leaves_the_rig_safe(tmp_path) -> None:
    with session(tmp_path, small_sweep(azimuth_step_deg=30), **MID) as (rig, store, engine, events):
        engine.subscribe(lambda e: engine.abort() if isinstance(e, FrameStored) and e.index == 1 else None)
        st = engine.run()
        assert st.state is S.ABORTED and st.done < st.total
        assert store.state == "aborted"
        assert store.verify() == []  # what was captured is complete and checksummed
        assert {f.event_id for f in store.frames()} <= {e.event_id for e in engine.events}
        assert_rig_safe(rig)
    assert isinstance(events[-1], SessionFinished) and events[-1].state is S.ABORTED


def test_abort_while_paused(tmp_path) -> None:
    with session(tmp_path, small_sweep(azimuth_step_deg=30), **MID) as (rig, _store, engine, _events):
        engine.subscribe(lambda e: engine.pause() if isinstance(e, FrameStored) and e.index == 2 else None)
        engine.start()
        wait_for_state(engine, S.PAUSED)
        engine.abort()
        assert engine.wait(timeout=30).state is S.ABORTED
        assert_rig_safe(rig)


def test_qc_hook_scores_each_frame_and_a_broken_hook_loses_nothing(tmp_path) -> None:
    def qc(pf, ev, meta):
        if ev.azimuth_deg == 180:
            raise ValueError("qc bug")
        return {"score": float(np.mean(pf.cube)), "n_bands": int(pf.cube.shape[0])}

    with session(tmp_path, qc=qc) as (_rig, store, engine, events):
        engine.run()
        by_az = {f.meta["event"]["azimuth_deg"]: f.meta for f in store.frames()}
        assert len(by_az) == 4
        assert by_az[180]["qc"] is None and "qc bug" in by_az[180]["qc_error"]
        for az in (0, 90, 270):
            assert by_az[az]["qc"]["n_bands"] == 10 and by_az[az]["qc"]["score"] > 0
    scores = [e.qc_score for e in events if isinstance(e, FrameStored)]
    assert sum(s is not None for s in scores) == 3


def test_slow_disk_keeps_the_pipeline_bounded(tmp_path) -> None:
    with session(tmp_path, process_depth=1, store_depth=1, store_workers=1) as (_rig, store, engine, _events):
        write = store.write_frame

        def slow_write(*a, **kw):
            time.sleep(0.05)
            return write(*a, **kw)

        store.write_frame = slow_write
        assert engine.run().state is S.COMPLETED
        st = engine.pipeline_stats()
        assert st.max_in_flight <= st.bound == 5 and st.stored == 4
        assert st.max_process_depth <= 1 and st.max_store_depth <= 1


def test_disk_space_is_checked_before_anything_moves(tmp_path, monkeypatch) -> None:
    """Too little disk at the start: the session pauses, resumable (issue 12, F6), not fails."""
    with session(tmp_path) as (rig, store, engine, _events):
        usage = shutil.disk_usage(tmp_path)
        monkeypatch.setattr("m2s2hil.atomic.shutil.disk_usage",
                            lambda p: usage._replace(free=10 * 1024 * 1024))
        engine.start()
        wait_for_state(engine, RunState.PAUSED)
        st = engine.status()
        assert st.pause_reason.startswith("disk_full") and "disk full" in st.pause_reason
        assert [f.fault_class for f in st.faults] == ["disk_full"]
        assert store.state == "paused" and store.frames() == [] and store.darks() == []
        assert rig.world.lamps_on() == frozenset()


def test_full_disk_mid_session_suspends_then_resumes_cleanly(tmp_path, monkeypatch) -> None:
    """The store reports the full disk (its own free-space check); the engine parks cleanly."""
    real = shutil.disk_usage
    full = {"on": False}

    def usage(p):
        u = real(p)
        return u._replace(free=1024) if full["on"] else u

    monkeypatch.setattr("m2s2hil.atomic.shutil.disk_usage", usage)
    with session(tmp_path, small_sweep(azimuth_step_deg=30), **MID) as (rig, store, engine, _events):
        def fill_disk(e) -> None:
            if isinstance(e, FrameStored) and e.index == 1:
                full["on"] = True

        engine.subscribe(fill_disk)
        engine.start()
        wait_for_state(engine, S.PAUSED)
        st = engine.status()
        assert st.pause_reason.startswith("disk_full")
        assert any(f.fault_class == "disk_full" and f.action.startswith("suspend") for f in st.faults)
        assert_rig_safe(rig)
        assert store.skips() == []  # a full disk is not a gap
        full["on"] = False  # the operator freed some space
        engine.resume()
        final = engine.wait(timeout=60)
        assert final.state is S.COMPLETED and final.done == final.total
        ids = [f.event_id for f in store.frames()]
        assert sorted(ids) == sorted(e.event_id for e in engine.events if e.kind == "frame")
        assert store.verify() == []


def test_auto_exposure_finds_the_longest_safe_exposure_in_few_frames(tmp_path) -> None:
    sweep = small_sweep(lighting=["strong"], azimuth_step_deg=180, exposure="auto")
    with session(tmp_path, sweep) as (rig, store, engine, _events):
        assert engine.run().state is S.COMPLETED
        rec = [e["payload"] for e in store.events() if e["kind"] == "auto_exposure"]
        assert len(rec) == 1 and rec[0]["lighting"] == "strong" and rec[0]["converged"]
        assert rec[0]["frames"] <= 4
        t = rec[0]["exposure_s"]
        frames = store.frames()
        assert all(f.meta["exposure_s"] == pytest.approx(t) for f in frames)
        assert any(d.exposure_s == pytest.approx(t) for d in store.darks())  # its own dark
        # Check the answer on the simulated camera, at the pose it was metered at.
        cfg = rig.config
        first = next(e for e in engine.events if e.kind == "frame")
        rig.lights.set(cfg.lamp_channels("strong"))
        rig.turntable.move_to(first.azimuth_deg)
        rig.clock.sleep(5.0)
        fs = cfg.camera.model.full_scale

        def p999(exposure: float) -> float:
            rig.camera.configure(exposure_s=exposure, gain=1.0)
            return float(np.percentile(rig.camera.snap(timeout=5).data, 99.9))

        assert p999(t) < 0.9 * fs  # below the limit ...
        assert p999(t * 1.12) >= 0.9 * fs  # ... and within ~12 % of the longest such exposure
        rig.lights.set(())


def test_sensor_warming_up_gets_a_fresh_dark(tmp_path) -> None:
    with session(tmp_path) as s:
        def warm_up(e) -> None:
            if isinstance(e, Captured) and e.index == 2:
                s.rig.world.sensor_temperature_c = 41.0  # beyond the 2 °C tolerance

        s.engine.subscribe(warm_up)
        assert s.engine.run().state is S.COMPLETED
        darks = {d.dark_id: d for d in s.store.darks()}
        assert set(darks) == {"dark/8000us/g1", "dark/8000us/g1/t1"}
        assert darks["dark/8000us/g1/t1"].meta["temperature_c"] == pytest.approx(41.0)
        for f in s.store.frames():
            want = "dark/8000us/g1/t1" if f.meta["temperature_c"] > 40 else "dark/8000us/g1"
            assert f.meta["dark_id"] == want
        assert any(f.meta["dark_id"].endswith("/t1") for f in s.store.frames())
        assert s.engine.status().done == s.engine.status().total  # extra darks are not plan events


def test_ctrl_c_aborts_cleanly_and_is_reraised(tmp_path) -> None:
    with session(tmp_path, small_sweep(azimuth_step_deg=30), **MID) as s:
        pressed = []

        def interrupt(e) -> None:  # the operator presses Ctrl-C once, mid-session
            if isinstance(e, FrameStored) and not pressed:
                pressed.append(e)
                raise KeyboardInterrupt

        s.engine.subscribe(interrupt)
        with pytest.raises(KeyboardInterrupt):
            s.engine.run()
        assert s.engine.state is S.ABORTED and s.store.state == "aborted"
        assert_rig_safe(s.rig)
