"""Motion on a slow, heavy or stuck rig: waits that follow the move, stalls caught, stuck holds reset.

The simulators are slowed or stuck through their fault plans (``slow_motion``, ``hang``,
``hold_stuck``: simulators/fault_injection.py), so the drivers meet a rig slower than its
rig file says through their real transports (``sim://`` on the virtual clock).
"""

from __future__ import annotations

import itertools
import logging

import pytest
from engine_helpers import assert_rig_safe, session, small_rig_config
from m2s2hil.drivers.errors import MoveStalled
from m2s2hil.drivers.grbl import GrblController
from m2s2hil.drivers.motion_watch import PLAN_MARGIN, trapezoid_s
from m2s2hil.drivers.zaber import ZaberDevice
from m2s2hil.simulators import registry
from m2s2hil.simulators.grbl import GrblSimulator
from m2s2hil.simulators.grbl_settings import GrblAxisSettings
from m2s2hil.simulators.zaber import ZaberSimulator

from m2s2hil.engine.state import RunState
from m2s2hil.rig.factory import open_simulated_rig
from m2s2hil.rig.operations import RigOps

_names = itertools.count()
SLOW = {"kind": "slow_motion", "factor": 5.0, "count": -1}  # every move, five times slower
TURNTABLE = dict(
    units_per_degree=1.0, min_deg=-370, max_deg=370, max_speed_dps=60, accel_dps2=120, tolerance_deg=0.05
)
UPD = 4266.6667  # Zaber microsteps per degree
ROT = {**TURNTABLE, "units_per_degree": UPD, "tolerance_deg": 0.01}


def _slowed_s(distance: float, factor: float = 5.0) -> float:
    """The trapezoid of a move whose speed is ``factor`` and acceleration ``factor²`` times lower."""
    return trapezoid_s(distance, 60 / factor, 120 / factor**2)


@pytest.fixture
def grbl(vclock):
    made = []

    def make(timeout_s: float = 1.0):
        name = f"slow-grbl-{next(_names)}"
        sim = GrblSimulator(name, vclock, axes={"X": GrblAxisSettings(max_rate=3600, accel=120)})
        registry.register(name, sim)
        ctl = GrblController(f"sim://{name}", clock=vclock, timeout_s=timeout_s)
        ctl.connect()
        made.append((name, ctl))
        return sim, ctl, ctl.axis("X", name="turntable", **TURNTABLE)

    yield make
    for name, ctl in made:
        ctl.close()
        registry.unregister(name)


@pytest.fixture
def zaber(vclock):
    made = []

    def make(timeout_s: float = 1.0):
        name = f"slow-zaber-{next(_names)}"
        sim = ZaberSimulator(name, vclock)
        registry.register(name, sim)
        zd = ZaberDevice(f"sim://{name}", clock=vclock, timeout_s=timeout_s)
        zd.connect()
        made.append((name, zd))
        axis = zd.axis(1, name="turntable", **ROT)
        axis.home()
        return sim, zd, axis

    yield make
    for name, zd in made:
        zd.close()
        registry.unregister(name)


# -- GRBL ----------------------------------------------------------------------------------
def test_grbl_move_five_times_slower_than_configured_is_waited_out_and_verified(grbl, vclock):
    sim, ctl, axis = grbl()
    sim.faults.add(**SLOW)
    t0 = vclock.monotonic()
    assert axis.move_to(300.0) == pytest.approx(300.0)
    took = vclock.monotonic() - t0
    # Far past the planned duration and its margin: the wait went on because the axis progressed.
    assert took > PLAN_MARGIN * trapezoid_s(300, 60, 120) + 2 * ctl.timeout_s
    assert took == pytest.approx(_slowed_s(300), abs=0.2)


def test_grbl_hung_axis_fails_fast_with_a_typed_stall_error_and_is_stopped(grbl, vclock):
    sim, _ctl, axis = grbl()
    sim.faults.add("hang", fraction=0.25)
    t0 = vclock.monotonic()
    with pytest.raises(MoveStalled) as exc:
        axis.move_to(200.0)
    err = exc.value
    assert (err.axis, err.start, err.target) == ("turntable", 0.0, 200.0)
    assert err.actual == pytest.approx(50.0)
    assert "turntable: stalled at 50.0000° (Run) on the way from 0.0000° to 200.0000°" in str(err)
    assert err.fault_class == "alarm" and err.device == "stage"
    # Caught within the stall window of the freeze, long before the planned time ran out.
    assert vclock.monotonic() - t0 < PLAN_MARGIN * trapezoid_s(200, 60, 120)
    assert sim.state == "Idle" and sim.axis_position("X") == pytest.approx(50.0)  # stopped there
    assert axis.move_to(100.0) == pytest.approx(100.0)


def test_grbl_hold_that_never_completes_is_reset_once_then_unlocked(grbl, vclock, caplog):
    sim, ctl, axis = grbl()
    sim.faults.add("hold_stuck")
    axis.move_to(300.0, wait=False)
    vclock.advance(1.0)
    with caplog.at_level(logging.WARNING, logger="m2s2hil.drivers.grbl"):
        st = ctl.stop()
    escalations = [r.getMessage() for r in caplog.records if "soft reset (0x18)" in r.getMessage()]
    assert escalations == ["stage: feed hold (!) did not complete; soft reset (0x18) to stop the motion"]
    assert st is not None and st.state == "Alarm" and int(ctl.last_alarm or 0) == 3  # reset during Hold:1
    stood = sim.axis_position("X")
    assert sim.state == "Alarm" and not axis.is_moving()
    # The axis has no switches here: unlocked ($X), never homed; the position is kept.
    assert ctl.clear_alarm(home=False).state == "Idle"
    assert axis.position() == pytest.approx(stood)
    assert axis.move_to(0.0) == pytest.approx(0.0)


def test_grbl_stop_waits_out_a_slow_deceleration(grbl, vclock):
    sim, ctl, axis = grbl(timeout_s=0.2)  # a fixed 10 x timeout would give the braking 2 s
    sim.faults.add(**SLOW)
    axis.move_to(300.0, wait=False)
    vclock.advance(5.0)  # cruising at 12 °/s: braking at 4.8 °/s² takes 2.5 s
    st = ctl.stop()
    assert st is not None and st.state == "Idle" and ctl.last_alarm is None  # Hold:0 reached, no alarm
    assert sim.state == "Idle"


# -- Zaber ---------------------------------------------------------------------------------
def test_zaber_move_five_times_slower_than_configured_is_waited_out_and_verified(zaber, vclock):
    sim, _zd, axis = zaber()
    sim.faults.add(**SLOW)
    t0 = vclock.monotonic()
    assert axis.move_to(300.0) == pytest.approx(300.0, abs=1e-3)
    assert vclock.monotonic() - t0 == pytest.approx(_slowed_s(300), abs=0.2)


def test_zaber_hung_axis_fails_fast_with_a_typed_stall_error_and_is_stopped(zaber, vclock):
    sim, _zd, axis = zaber()
    sim.faults.add("hang", fraction=0.5)
    t0 = vclock.monotonic()
    with pytest.raises(MoveStalled) as exc:
        axis.move_to(-100.0)
    err = exc.value
    assert (err.axis, err.target) == ("turntable", -100.0) and err.actual == pytest.approx(-50.0, abs=1e-3)
    assert "(BUSY)" in str(err)
    assert vclock.monotonic() - t0 < PLAN_MARGIN * trapezoid_s(100, 60, 120) + 2.0
    assert not axis.is_moving() and sim.axis_position(1) / UPD == pytest.approx(-50.0, abs=1e-3)


def test_zaber_stop_waits_out_a_slow_deceleration(zaber, vclock):
    sim, _zd, axis = zaber(timeout_s=0.1)  # a fixed 10 x timeout would give the braking 1 s
    sim.faults.add(**SLOW)
    axis.move_to(300.0, wait=False)
    vclock.advance(5.0)
    axis.stop()
    assert not axis.is_moving()


# -- the rig: parking and a capture --------------------------------------------------------
def _short_timeouts(timeout_s: float):
    cfg = small_rig_config()
    devices = {**cfg.devices, "stage": cfg.devices["stage"].model_copy(update={"timeout_s": timeout_s})}
    return cfg.model_copy(update={"devices": devices})


def test_a_rig_file_can_slow_its_simulated_stage(tmp_path):
    from importlib import resources

    from m2s2hil.config import load_rig

    text = resources.files("m2s2hil").joinpath("data/default_rig.toml").read_text()
    rig_file = tmp_path / "slow.toml"
    rig_file.write_text(
        text + '\n[[simulation.faults.stage]]\nkind = "slow_motion"\nfactor = 5.0\ncount = -1\n'
    )
    rig = open_simulated_rig(load_rig(rig_file))
    try:
        t0 = rig.clock.monotonic()
        assert rig.turntable.move_to(90.0) == pytest.approx(90.0, abs=0.05)
        assert rig.clock.monotonic() - t0 == pytest.approx(_slowed_s(90), abs=0.2)
    finally:
        rig.close()


def test_parking_a_slow_rig_mid_move_waits_until_it_is_at_rest():
    rig = open_simulated_rig(_short_timeouts(0.2), faults={"stage": [SLOW]})
    try:
        rig.turntable.move_to(300.0, wait=False)
        rig.clock.sleep(5.0)
        report = RigOps(rig).make_safe()
        assert report.safe and report.attempts == 1 and report.errors == []
        assert_rig_safe(rig)
    finally:
        rig.close()


def test_capture_on_a_rig_five_times_slower_reads_back_every_pose(tmp_path):
    with session(tmp_path, faults={"stage": [SLOW]}) as (rig, store, engine, _events):
        st = engine.run()
        assert st.state is RunState.COMPLETED and not st.faults and st.skipped == 0 and st.done == st.total
        frames = store.frames()
        assert len(frames) == 4  # every azimuth, none skipped
        tol = rig.config.axes["turntable"].tolerance_deg
        for f in frames:
            az = float(f.event_id.split("/")[2].removeprefix("az"))
            assert f.meta["pose"]["turntable_deg"] == pytest.approx(az, abs=tol)
        assert_rig_safe(rig)


def test_capture_with_a_hung_axis_and_a_stuck_hold_recovers_with_one_reset(tmp_path, caplog):
    faults = {"stage": [{"kind": "hang", "after": 1}, {"kind": "hold_stuck"}]}
    with caplog.at_level(logging.WARNING), session(tmp_path, faults=faults) as (rig, store, engine, _events):
        st = engine.run()
        assert st.state is RunState.COMPLETED and st.skipped == 0
        assert [f.fault_class for f in st.faults] == ["alarm"]  # the stall, recovered once
        assert len(store.frames()) == 4
        assert_rig_safe(rig)
    text = [r.getMessage() for r in caplog.records]
    assert sum("soft reset (0x18)" in t for t in text) == 1
    assert not any("feed hold did not complete" in t for t in text)
