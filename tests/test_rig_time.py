"""Overlapped stop-and-go on the simulated rig: the stage leaves for the next pose during the
readout, nothing is lost, every frame keeps its own pose, and the run reports its floor."""

from __future__ import annotations

import pytest
from engine_helpers import session, small_sweep

from m2s2hil.engine.state import RunState


def _run(tmp_path, overlap: bool) -> tuple[float, list, dict, object]:
    sweep = small_sweep(azimuth_step_deg=120, dark={"frames": 1})  # 3 azimuths, one condition: 2 moves
    with session(tmp_path / str(overlap), sweep, overlap=overlap) as s:
        st = s.engine.run()
        assert st.state is RunState.COMPLETED and st.done == st.total
        (fin,) = [e["payload"] for e in s.store.events() if e["kind"] == "run_finished"]
        return st.elapsed_s, s.store.frames(), fin, s.rig.config


@pytest.mark.slow  # two small sessions, ~2 s
def test_overlap_saves_the_readouts_and_keeps_every_frame_at_its_pose(tmp_path) -> None:
    plain_s, plain_frames, _, _ = _run(tmp_path, overlap=False)
    over_s, frames, fin, cfg = _run(tmp_path, overlap=True)
    assert sorted(f.event_id for f in frames) == sorted(f.event_id for f in plain_frames)
    readout = 1 / cfg.camera.model.max_fps
    # each of the 2 moves hides the readout of the frame before it (the last frame's is not hidden)
    assert plain_s - over_s >= 1.5 * readout
    tol = cfg.axes["turntable"].tolerance_deg
    for f in frames:
        # the pose recorded is the one read back before the exposure, and the frame shows it
        assert abs(f.meta["pose"]["turntable_deg"] - f.meta["event"]["azimuth_deg"]) <= tol
        assert abs(f.meta["truth"]["azimuth_deg"] - f.meta["pose"]["turntable_deg"]) <= tol
    assert 0 < fin["physical_floor_s"] <= fin["lower_bound_s"] <= fin["duration_s"]
    assert fin["efficiency"] <= 1.0


def _time_to_rest(ask_moving, clock, expect_s: float, step_s: float = 1e-3) -> float:
    """Seconds from now until ``ask_moving()`` (a status over the wire) first says at rest; jumps to
    20 ms before ``expect_s`` (still moving there, or the move ended early), then steps."""
    t0 = clock.monotonic()
    clock.advance(max(0.0, expect_s - 0.02))
    assert ask_moving(), "the move ended early"
    while ask_moving():
        clock.advance(step_s)
        assert clock.monotonic() - t0 < expect_s + 0.1, "the move ended late"
    return clock.monotonic() - t0


def _closed_form(d: float, v: float, a: float) -> float:
    """Rest to rest at v and a: a triangle below v²/a, a trapezoid above (written out here,
    independently of the code under test)."""
    return 2 * (d / a) ** 0.5 if d < v * v / a else d / v + v / a


@pytest.mark.parametrize("role,distance", [("turntable", 0.5), ("turntable", 10.0), ("tilt", 30.0)])
def test_simulated_grbl_moves_take_the_plans_time(vclock, role, distance) -> None:
    """Over the wire (a G0, then `?` every ms), a rest-to-rest move of the built-in rig's GRBL takes
    what the plan's duration model says, triangle (0.5°) and trapezoid alike."""
    from m2s2hil.protocols.grbl import GrblReceiver
    from m2s2hil.simulators.grbl import grbl_sim_for

    from m2s2hil.config import default_rig
    from m2s2hil.plan.estimate import move_time_s

    cfg = default_rig()
    axes = {r: cfg.axes[r] for r in ("turntable", "tilt")}
    sim = grbl_sim_for("stage", axes, vclock, None, None, {})
    rx = GrblReceiver()
    rx.feed(sim.take())
    ax = cfg.axes[role]
    sim.receive(f"G0 {ax.axis}{distance}\n".encode())

    def moving() -> bool:
        sim.receive(b"?")
        (st,) = [e for e in rx.feed(sim.take()) if hasattr(e, "state")]
        return st.state != "Idle"

    expect = _closed_form(distance, ax.max_speed_dps, ax.accel_dps2)
    took = _time_to_rest(moving, vclock, expect)
    assert took == pytest.approx(expect, abs=2e-3)
    assert took == pytest.approx(move_time_s(distance, ax), abs=2e-3)


@pytest.mark.parametrize("distance", [0.5, 10.0])
def test_simulated_zaber_moves_take_the_plans_time(vclock, distance) -> None:
    """The same for a Zaber rotary axis driven by `move abs` in microsteps: the simulator's
    `maxspeed`/`accel` come from the rig's axis (rounded to the protocol's data units)."""
    from types import SimpleNamespace

    from m2s2hil.protocols.zaber import Command, ZaberReceiver, encode_command
    from m2s2hil.simulators.zaber import zaber_sim_for

    from m2s2hil.config import AxisConfig
    from m2s2hil.plan.estimate import move_time_s

    ax = AxisConfig.model_validate(dict(device="stage", axis="1", units_per_degree=4266.6667, min_deg=-370,
                                        max_deg=370, max_speed_dps=60.0, accel_dps2=120.0))
    sim = zaber_sim_for("stage", SimpleNamespace(unit=1), {"turntable": ax}, vclock, None, None)
    rx = ZaberReceiver()

    def ask(text: str):
        sim.receive(encode_command(Command(1, 1, None, text), with_checksum=False))
        (reply,) = rx.feed(sim.take())
        return reply

    ask("home")  # it powers up on its home sensor: done at once
    vclock.advance(0.01)
    assert not ask("").busy
    ask(f"move abs {round(distance * ax.units_per_degree)}")
    expect = _closed_form(distance, 60.0, 120.0)
    took = _time_to_rest(lambda: ask("").busy, vclock, expect)
    assert took == pytest.approx(expect, abs=3e-3)
    assert took == pytest.approx(move_time_s(distance, ax), abs=3e-3)

