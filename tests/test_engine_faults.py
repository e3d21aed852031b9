"""Each fault class, injected in the simulators, meets its policy; teardown is safe even when it fails.

Faults are injected through the simulators' FaultPlans (``open_simulated_rig(faults=...)``);
``after`` skips the occurrences used while the rig opens (homing, lamps off, camera set-up).
"""

from __future__ import annotations

import dataclasses

import pytest
from engine_helpers import assert_rig_safe, make_engine, session, small_rig_config, small_sweep
from m2s2hil.drivers.errors import DeviceGone, RelayNotSwitched, StageAlarm

from m2s2hil.engine.fault_policy import FaultPolicy
from m2s2hil.engine.recovery import alarm_recovery
from m2s2hil.engine.runner import SessionFailed
from m2s2hil.engine.state import FaultRecorded, FrameStored, RunState, SessionFinished
from m2s2hil.rig.factory import open_simulated_rig
from m2s2hil.store.session import SessionStore

S = RunState
FRAME_IDS = ["weak/E1/az000/f0", "weak/E1/az090/f0", "weak/E1/az180/f0", "weak/E1/az270/f0"]
# The camera's third triggered frame is the first light frame (the two before are darks).
CAM = dict(after=2)


def _actions(status, fault_class):
    return [f.action for f in status.faults if f.fault_class == fault_class]


@pytest.mark.parametrize(
    ("name", "faults", "fault_class", "actions"),
    [
        ("camera frame lost", {"toucan": [{"kind": "frame_timeout", **CAM}]}, "timeout", ["retry"]),
        ("garbled relay answers", {"relays": [{"kind": "garble", "count": 3, "after": 3}]}, "protocol",
         ["retry"]),
        ("stage alarm", {"stage": [{"kind": "alarm", "after": 1}]}, "alarm", ["home+retry"]),
        ("stalled move", {"stage": [{"kind": "stall", "after": 2}]}, "alarm", ["home+retry"]),
        ("short frame", {"toucan": [{"kind": "incomplete", **CAM}]}, "frame_incomplete", ["retry"]),
        ("bad trailer", {"toucan": [{"kind": "trailer_error", **CAM}]}, "frame_incomplete", ["retry"]),
        ("camera unplugged", {"toucan": [{"kind": "unplug", "duration_s": 0.5, **CAM}]}, "device_gone",
         ["reconnect"]),
        ("stage port vanished", {"stage": [{"kind": "vanish", "duration_s": 0.5, "after": 10}]},
         "device_gone", ["reconnect"]),
    ],
)
def test_transient_faults_are_recovered(tmp_path, name, faults, fault_class, actions) -> None:
    with session(tmp_path, faults=faults) as (rig, store, engine, events):
        st = engine.run()
        assert st.state is S.COMPLETED, name
        assert _actions(st, fault_class) == actions
        assert [f.fault_class for f in st.faults] == [fault_class] * len(actions)
        assert sorted(f.event_id for f in store.frames()) == FRAME_IDS
        assert sorted(f.meta["attempt"] for f in store.frames()) == [1, 1, 1, 2]  # one was retried
        assert store.skips() == [] and store.verify() == []
        journal = [e["payload"] for e in store.events() if e["kind"] == "fault"]
        assert [j["fault_class"] for j in journal] == [fault_class] * len(actions)
        assert_rig_safe(rig)
    assert sum(isinstance(e, FaultRecorded) for e in events) == len(actions)


@pytest.mark.parametrize(
    ("faults", "fault_class", "n"),
    [
        ({"toucan": [{"kind": "frame_timeout", "count": 4, **CAM}]}, "timeout", 4),
        ({"relays": [{"kind": "garble", "count": 9, "after": 3}]}, "protocol", 3),
        ({"toucan": [{"kind": "incomplete", "count": 4, **CAM}]}, "frame_incomplete", 4),
    ],
)
def test_persistent_faults_skip_and_record_the_gap(tmp_path, faults, fault_class, n) -> None:
    with session(tmp_path, faults=faults) as (rig, store, engine, events):
        st = engine.run()
        assert st.state is S.COMPLETED_WITH_GAPS and st.skipped == 1 and st.done == st.total - 1
        assert _actions(st, fault_class) == ["retry"] * (n - 1) + ["skip"]
        (skip,) = store.skips()
        assert skip.event_id == FRAME_IDS[0] and skip.fault_class == fault_class
        assert skip.reason  # says what happened
        assert sorted(f.event_id for f in store.frames()) == FRAME_IDS[1:]
        assert store.manifest()["skips"][0]["event_id"] == FRAME_IDS[0]
        assert_rig_safe(rig)
    assert events[-1].skipped == 1


def test_repeated_alarm_aborts_and_keeps_the_alarm(tmp_path) -> None:
    # The first move alarms; so does the homing cycle meant to recover from it.
    with session(tmp_path, faults={"stage": [{"kind": "alarm", "count": 2, "after": 1}]}) as (
            rig, store, engine, events):
        with pytest.raises(SessionFailed) as ei:
            engine.run()
        assert isinstance(ei.value.cause, StageAlarm)
        st = ei.value.status
        assert st.state is S.FAILED and "StageAlarm" in st.error
        assert _actions(st, "alarm") == ["home+retry", "abort"]
        assert store.state == "failed"
        assert_rig_safe(rig)
    assert isinstance(events[-1], SessionFinished) and events[-1].state is S.FAILED


def test_camera_that_does_not_come_back_aborts(tmp_path) -> None:
    faults = {"toucan": [{"kind": "unplug", "duration_s": 1e6, **CAM}]}
    with session(tmp_path, faults=faults) as (rig, _store, engine, _events):
        with pytest.raises(SessionFailed) as ei:
            engine.run()
        assert isinstance(ei.value.cause, DeviceGone)
        assert _actions(ei.value.status, "device_gone") == ["reconnect", "reconnect", "abort"]
        assert_rig_safe(rig)


def test_policy_overrides_change_the_outcome(tmp_path) -> None:
    policy = FaultPolicy.model_validate({"timeout": {"action": "skip"}})
    with session(tmp_path, faults={"toucan": [{"kind": "frame_timeout", **CAM}]}, policy=policy) as (
            _rig, store, engine, _events):
        st = engine.run()
        assert st.skipped == 1 and _actions(st, "timeout") == ["skip"]
        assert [s.fault_class for s in store.skips()] == ["timeout"]


class FlakyLights:
    """Wraps the real relay board; switching everything off fails ``failures`` times."""

    def __init__(self, inner, failures: int) -> None:
        self.inner, self.failures, self.name = inner, failures, inner.name
        self.off_calls = 0

    def set(self, on_channels) -> None:
        chans = list(on_channels)
        if not chans:
            self.off_calls += 1
            if self.off_calls <= self.failures:
                raise RelayNotSwitched("read-back shows lamps still on (injected)", device=self.name)
        self.inner.set(chans)

    def state(self):
        return self.inner.state()

    def close(self) -> None:
        self.inner.close()


def test_teardown_that_raises_still_ends_safe_and_keeps_the_original_error(tmp_path) -> None:
    with session(tmp_path, faults={"stage": [{"kind": "alarm", "count": 2, "after": 1}]}) as (
            rig, _store, engine, _events):
        rig.lights = FlakyLights(rig.lights, failures=1)
        with pytest.raises(SessionFailed) as ei:
            engine.run()
        assert isinstance(ei.value.cause, StageAlarm)  # the error that ended the run, not teardown's
        teardown = [f for f in ei.value.status.faults if f.action == "teardown"]
        assert len(teardown) == 1 and "RelayNotSwitched" in teardown[0].message
        assert rig.lights.off_calls == 2  # the failed step was tried again
        assert_rig_safe(rig)


def test_teardown_that_cannot_switch_lamps_off_still_stops_motion_and_says_so(tmp_path) -> None:
    with session(tmp_path) as (rig, _store, engine, _events):
        rig.lights = FlakyLights(rig.lights, failures=99)
        engine.subscribe(lambda e: engine.abort() if isinstance(e, FrameStored) else None)
        with pytest.raises(SessionFailed) as ei:
            engine.run()
        st = ei.value.status
        assert st.state is S.FAILED and "NOT in a safe state" in st.error
        assert sum(f.action == "teardown" for f in st.faults) == 3  # every attempt recorded
        assert not rig.turntable.is_moving() and not rig.tilt.is_moving()  # other steps still ran
        assert rig.world.lamps_on()  # honest: the lamps really are still on
        rig.lights.failures = 0
        rig.lights.set(())


def test_abort_during_a_fault_wins_over_the_recovery(tmp_path) -> None:
    """An emergency stop that causes a fault must not be followed by a re-home and a retry."""
    stall = {"stage": [{"kind": "stall", "after": 2}]}
    with session(tmp_path, faults=stall) as (rig, _store, engine, _events):
        stage = rig.sims["stage"]
        seen: dict[str, int] = {}

        def on_fault(e) -> None:
            if isinstance(e, FaultRecorded) and "bytes" not in seen:
                seen["bytes"] = len(stage.received)
                engine.abort()

        engine.subscribe(on_fault)
        st = engine.run()
        assert st.state is S.ABORTED
        after = bytes(stage.received[seen["bytes"] :])
        assert b"$H" not in after  # no homing after the abort ...
        assert b"G0" not in after and b"G1" not in after  # ... and no further move
        assert_rig_safe(rig)


def _without_switches(cfg):
    axes = {r: a.model_copy(update={"homing": "none"}) for r, a in cfg.axes.items()}
    return cfg.model_copy(update={"axes": axes})


def test_an_alarm_on_axes_without_switches_is_unlocked_and_says_so_never_homed(tmp_path) -> None:
    """The fault line names what is done: an axis without switches is never homed (issue 21)."""
    cfg = small_rig_config()
    opened = open_simulated_rig(cfg, faults={"stage": [{"kind": "alarm", "after": 1}]})
    # The same simulated stage, as a rig file without switches describes it.
    rig = dataclasses.replace(opened, config=_without_switches(cfg))
    store = SessionStore.create(tmp_path, small_sweep(), rig.config, session_id="s1", clock=rig.clock)
    stage = rig.sims["stage"]
    before = len(stage.received)
    try:
        st = make_engine(rig, store).run()
        assert st.state is S.COMPLETED
        assert _actions(st, "alarm") == ["unlock+retry"]
        journal = [e["payload"]["action"] for e in store.events() if e["kind"] == "fault"]
        assert journal == ["unlock+retry"]
        sent = bytes(stage.received[before:])
        assert b"$X" in sent and b"$H" not in sent
        assert_rig_safe(rig)
    finally:
        store.close()
        opened.close()


def test_alarm_recovery_names_what_clearing_the_alarm_does(tmp_path) -> None:
    cfg = small_rig_config()
    rig = open_simulated_rig(cfg)
    try:
        stage = [link for link in rig.links if link.axis_roles]
        assert alarm_recovery(stage, cfg.axes) == "home"  # switches: homed
        assert alarm_recovery(stage, _without_switches(cfg).axes) == "unlock"  # reset and $X
        no_alarm = [dataclasses.replace(link, alarm=None) for link in stage]
        assert alarm_recovery(no_alarm, _without_switches(cfg).axes) == "re-read"  # position only
        assert alarm_recovery(no_alarm, cfg.axes) == "home"  # each axis homed on its switches
    finally:
        rig.close()
