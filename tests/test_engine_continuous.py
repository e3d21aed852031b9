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
            if nominal == 0:
                # the pass starts turning from rest at its first mark (the homed turntable
                # stands there): that frame is taken at the start of the run-up, slower
                assert c["speed_dps"] < SPEED / 2
            else:
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
    # Lose a run of stream frames around the 90° mark (darks: 2 frames; then the pass turns from
    # rest at 0°, at 30°/s after a 0.25 s ramp: its frame 190 is near 84°, frame 230 near 102°).
    faults = {"toucan": [{"kind": "frame_timeout", "count": 40, "after": 2 + 190}]}
    with session(tmp_path, sweep, speed_dps=SPEED, faults=faults) as s:
        st = s.engine.run()
        assert st.state is S.COMPLETED and st.done == st.total
        passes = _passes(s.store)
        assert passes[0]["dropped"] > 0
        redone = [f for f in st.faults if f.fault_class == "frame_incomplete"]
        assert redone and redone[0].action == "retry"
        assert len(passes) == 2 and passes[1]["missing_marks"] == []
        assert len({f.event_id for f in s.store.frames()}) == 4


@pytest.mark.slow  # ~2 s
def test_the_next_lamps_warm_while_the_turntable_turns_back_but_no_frame_is_taken_before(tmp_path) -> None:
    """Two passes (weak, then strong: bars 4 and 5 come on, warming 3 s here). The strong lamps
    switch once the weak pass has its last frame, before the turntable brakes; the strong pass
    turns back from where the weak one stopped (no move) and starts its run-up while the lamps
    still warm, timed so that no kept frame was exposed before they were warm, and no weak frame
    after they came on."""
    from engine_helpers import small_rig_config

    cfg = small_rig_config(128)  # a whole revolution is streamed: small frames keep it cheap
    warm = 3.0
    cfg = cfg.model_copy(update={"lamps": {n: lamp.model_copy(update={"warmup_s": warm})
                                           for n, lamp in cfg.lamps.items()}})
    sweep = small_sweep(mode="continuous", azimuth_step_deg=90, dark={"frames": 1},
                        lighting=["weak", "strong"], reorder=False)
    strong = frozenset(cfg.lamp_channels("strong"))
    with session(tmp_path, sweep, config=cfg, speed_dps=60.0) as s:
        clock, seen = s.rig.clock, {"lit": [], "rotate": [], "stopped": [], "moves": []}
        lights_set, rotate, stop = s.rig.lights.set, s.rig.rotation.rotate, s.rig.turntable.stop
        move_to = s.rig.turntable.move_to

        def set_spy(channels, *a, **kw):
            out = lights_set(channels, *a, **kw)
            if channels:
                seen["lit"].append((clock.monotonic(), frozenset(channels)))  # verified on
            return out

        def rotate_spy(*a, **kw):
            seen["rotate"].append(clock.monotonic())
            return rotate(*a, **kw)

        def stop_spy(*a, **kw):
            out = stop(*a, **kw)
            seen["stopped"].append(clock.monotonic())
            return out

        def move_spy(target, *a, **kw):
            seen["moves"].append((clock.monotonic(), target))
            return move_to(target, *a, **kw)

        s.rig.lights.set, s.rig.rotation.rotate, s.rig.turntable.stop = set_spy, rotate_spy, stop_spy
        s.rig.turntable.move_to = move_spy
        st = s.engine.run()
        assert st.state is S.COMPLETED and st.done == st.total
        lit_strong = next(t for t, ch in seen["lit"] if ch == strong)
        assert len(seen["rotate"]) == 2
        # the strong lamps came on before the weak pass's turntable had come to rest
        assert lit_strong < seen["stopped"][0] - 0.1
        # the strong pass turned back from where the weak one stopped: no move in between
        assert not [t for t, _ in seen["moves"] if seen["stopped"][0] <= t <= seen["rotate"][1]]
        ready = lit_strong + warm
        assert seen["rotate"][1] < ready - 0.05  # its run-up began while the lamps warmed
        readout = 1 / s.rig.config.camera.model.max_fps
        by_light: dict[str, list[tuple[float, float]]] = {"weak": [], "strong": []}
        for f in s.store.frames():
            began = f.meta["clock_s"] - f.meta["exposure_s"] - readout
            by_light[f.meta["event"]["lighting"]].append((began, began + f.meta["exposure_s"]))
        assert len(by_light["strong"]) == len(by_light["weak"]) == 4
        assert min(b for b, _e in by_light["strong"]) >= ready - 1e-6  # none before they were warm
        assert max(e for _b, e in by_light["weak"]) <= lit_strong + 1e-6  # none under the next lamps
        passes = _passes(s.store)
        assert passes[1]["dropped"] == 0 and passes[1]["matched"] == 4
        (fin,) = [e["payload"] for e in s.store.events() if e["kind"] == "run_finished"]
        assert fin["lower_bound_s"] <= fin["duration_s"]


def test_a_pass_starts_where_the_turntable_rests_when_that_is_before_its_first_mark() -> None:
    from m2s2hil.engine.marks import pass_start

    limits = (-370.0, 370.0)
    back = 60.0**2 / (2 * 120.0) + 1.4  # the ramp plus the match window
    # the snake's turn: stopped beyond 350 going up, the next pass goes down from 350
    assert pass_start(350.0, -1, 60.0, 120.0, 1.4, 367.3, limits) == 367.3
    assert pass_start(0.0, 1, 60.0, 120.0, 1.4, 0.0, limits) == 0.0  # at the mark: from rest there
    # on the wrong side (past the first mark), or not known: back to the run-up's start
    assert pass_start(0.0, 1, 60.0, 120.0, 1.4, 5.0, limits) == pytest.approx(-back)
    assert pass_start(350.0, -1, 60.0, 120.0, 1.4, None, limits) == pytest.approx(350.0 + back)
    assert pass_start(360.0, -1, 60.0, 120.0, 1.4, None, limits) == 370.0  # within the soft limit


def test_the_angle_track_bounds_its_interpolation_in_a_run_up_and_knows_when_it_is_steady() -> None:
    from m2s2hil.engine.marks import AngleTrack

    a = 120.0
    track = AngleTrack(accel_dps2=a)
    times = [0.0, 0.05, 0.1, 0.15]
    for t in times:  # accelerating from rest: x = a t² / 2
        track.add(t, a * t * t / 2)
    assert not track.steady()
    for t in (0.01, 0.025, 0.07, 0.125):
        err = abs(track.angle_at(t) - a * t * t / 2)
        assert 0 < err <= track.uncertainty_at(t) + 1e-12  # the chord is off, and it says by how much
        assert track.uncertainty_at(t) <= a * 0.05**2 / 8 + 1e-9
    cruise = AngleTrack(accel_dps2=a)
    for t in times:
        cruise.add(t, 60.0 * t)
    assert cruise.steady() and cruise.uncertainty_at(0.07) == pytest.approx(0.0, abs=1e-12)
    assert cruise.angle_at(0.2) == pytest.approx(12.0)  # beyond the samples, straight on
