"""Continuous-rotation mode on the simulated rig: frames matched to the azimuth marks, blur reported."""

from __future__ import annotations

import pytest
from engine_helpers import assert_rig_safe, session, small_sweep, wait_for_state

from m2s2hil.engine.state import Captured, RunState, StateChanged

S = RunState
SPEED = 30.0  # deg/s; the camera streams at 65 frames/s, so frames are 0.46 deg apart
FPS = 65.0


def _passes(store) -> list[dict]:
    return [e["payload"] for e in store.events() if e["kind"] == "continuous_pass"]


@pytest.mark.slow  # ~2 s
def test_frames_are_matched_to_the_marks_and_blur_is_reported(tmp_path) -> None:
    sweep = small_sweep(mode="continuous", azimuth_step_deg=90)
    with session(tmp_path, sweep, speed_dps=SPEED) as s:
        st = s.engine.run()
        assert st.state is S.COMPLETED and st.done == st.total and st.efficiency is not None
        exposure = sweep.exposure_for("weak")
        frames = s.store.frames()
        assert sorted(f.event_id for f in frames) == sorted(
            e.event_id for e in s.engine.events if e.kind == "frame")
        half_spacing = SPEED / FPS / 2
        for f in frames:
            nominal = f.meta["event"]["nominal_azimuth_deg"]
            c = f.meta["continuous"]
            assert c["mark_deg"] == nominal
            assert abs(c["error_deg"]) <= half_spacing + 1e-3  # the nearest frame was kept
            assert f.meta["pose"]["turntable_deg"] == pytest.approx(c["angle_deg"])
            assert c["speed_dps"] == pytest.approx(SPEED, abs=0.5)  # measured from the read-back
            assert c["blur_deg"] == pytest.approx(SPEED * exposure)
            assert c["blur_px"] > 0
            # The simulated camera exposes over its exposure interval and shows the pose at
            # mid-exposure: the engine's angle (read-back interpolated at mid-exposure) is that
            # pose up to the read-back's interpolation (it used to render the pose at read-out,
            # ω·(t_exp/2 + readout) = 0.58 deg later).
            assert f.meta["truth"]["azimuth_deg"] == pytest.approx(c["angle_deg"], abs=0.01)
            # the recorded uncertainty is small and covers the real error of the interpolated pose
            assert 0 <= c["pose_uncertainty_deg"] < 0.1  # 0 when read-backs take no clock time
            assert abs(f.meta["truth"]["azimuth_deg"] - c["angle_deg"]) <= c["pose_uncertainty_deg"] + 2e-3
            assert abs(f.meta["truth"]["azimuth_deg"] - nominal) <= half_spacing + 0.01
        (p,) = _passes(s.store)
        assert p["dropped"] == 0 and p["matched"] == p["marks"] == 4 and p["missing_marks"] == []
        assert p["measured_speed_dps"] == pytest.approx(SPEED, abs=0.5)
        (fin,) = [e["payload"] for e in s.store.events() if e["kind"] == "run_finished"]
        assert fin["blur_deg"]["max"] == pytest.approx(SPEED * exposure)
        # the physical floor beside the mode's bound: below both it and the run
        assert 0 < fin["physical_floor_s"] <= fin["lower_bound_s"] <= fin["duration_s"]
        assert fin["physical_efficiency"] == pytest.approx(fin["physical_floor_s"] / fin["duration_s"])
        assert s.store.verify() == []
        assert_rig_safe(s.rig)


@pytest.mark.slow  # ~3 s
def test_pause_mid_revolution_stops_the_turntable_and_resume_finishes_the_marks(tmp_path) -> None:
    sweep = small_sweep(mode="continuous", azimuth_step_deg=30)
    with session(tmp_path, sweep, speed_dps=SPEED) as s:
        first = {"seen": False}

        def pause_on_first_capture(e) -> None:
            if isinstance(e, Captured) and not first["seen"]:
                first["seen"] = True
                s.engine.pause()

        s.engine.subscribe(pause_on_first_capture)
        s.engine.start()
        wait_for_state(s.engine, S.PAUSED)
        assert_rig_safe(s.rig)
        passes = _passes(s.store)
        assert passes and passes[0]["stopped_early"] and passes[0]["matched"] < 12
        s.engine.resume()
        final = s.engine.wait(timeout=60)
        assert final.state is S.COMPLETED and final.done == final.total
        ids = [f.event_id for f in s.store.frames()]
        assert len(ids) == len(set(ids)) == 12
        assert sum(p["matched"] for p in _passes(s.store)) == 12  # no mark captured twice
        assert s.store.verify() == []
    assert [e.new for e in s.events if isinstance(e, StateChanged)] == [
        S.RUNNING, S.PAUSING, S.PAUSED, S.RUNNING, S.COMPLETED]


@pytest.mark.slow  # ~2 s
def test_a_lost_stream_frame_at_a_mark_is_retried(tmp_path) -> None:
    """A frame dropped in the camera right at a mark: the pass reports it, the mark is redone."""
    sweep = small_sweep(mode="continuous", azimuth_step_deg=90)
    # Lose a run of stream frames around the first mark (darks: 2 frames, then the run-up).
    faults = {"toucan": [{"kind": "frame_timeout", "count": 40, "after": 2 + 20}]}
    with session(tmp_path, sweep, speed_dps=SPEED, faults=faults) as s:
        st = s.engine.run()
        assert st.state is S.COMPLETED and st.done == st.total
        passes = _passes(s.store)
        assert passes[0]["dropped"] > 0
        redone = [f for f in st.faults if f.fault_class == "frame_incomplete"]
        assert redone and redone[0].action == "retry"
        assert len(passes) == 2 and passes[1]["missing_marks"] == []
        assert len({f.event_id for f in s.store.frames()}) == 4


@pytest.mark.slow  # ~1.5 s
def test_the_run_up_overlaps_the_lamps_warm_up_but_no_frame_is_taken_before_it(tmp_path) -> None:
    """The turntable repositions and starts its run-up while the lamps warm (3 s here, longer than
    the tilt move), timed so that the first frame's exposure starts once they are warm."""
    from engine_helpers import small_rig_config

    cfg = small_rig_config(128)  # a whole revolution is streamed: small frames keep it cheap
    warm = 3.0
    cfg = cfg.model_copy(update={"lamps": {n: lamp.model_copy(update={"warmup_s": warm})
                                           for n, lamp in cfg.lamps.items()}})
    sweep = small_sweep(mode="continuous", azimuth_step_deg=90, dark={"frames": 1})
    with session(tmp_path, sweep, config=cfg, speed_dps=60.0) as s:
        clock, seen = s.rig.clock, {"lit": [], "rotate": []}
        lights_set, rotate = s.rig.lights.set, s.rig.rotation.rotate

        def set_spy(channels, *a, **kw):
            out = lights_set(channels, *a, **kw)
            if channels:
                seen["lit"].append(clock.monotonic())  # verified on: the warm-up counts from here
            return out

        def rotate_spy(*a, **kw):
            seen["rotate"].append(clock.monotonic())
            return rotate(*a, **kw)

        s.rig.lights.set, s.rig.rotation.rotate = set_spy, rotate_spy
        st = s.engine.run()
        assert st.state is S.COMPLETED and st.done == st.total
        ready = seen["lit"][0] + warm
        assert seen["rotate"][0] < ready - 0.05  # the run-up began while the lamps warmed
        readout = 1 / s.rig.config.camera.model.max_fps
        first = min(f.meta["clock_s"] - f.meta["exposure_s"] - readout for f in s.store.frames())
        assert first >= ready - 1e-6  # ... and no kept frame was exposed before they were warm
        (fin,) = [e["payload"] for e in s.store.events() if e["kind"] == "run_finished"]
        assert fin["lower_bound_s"] <= fin["duration_s"]
