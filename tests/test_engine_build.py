"""One builder of a run (capture, daemon, benchmarks) and the capabilities the rig records once."""

from __future__ import annotations

import dataclasses

import pytest
from api_support import daemon, sweep
from engine_helpers import assert_rig_safe, make_engine, small_rig_config, small_sweep

from m2s2hil.analysis.qc import capture_qc_hook
from m2s2hil.engine.build import build_run
from m2s2hil.engine.continuous_steps import ContinuousSteps
from m2s2hil.engine.runner import SessionFailed
from m2s2hil.engine.stop_and_go import StopAndGoSteps
from m2s2hil.errors import UsageError
from m2s2hil.rig.factory import open_simulated_rig
from m2s2hil.rig.operations import RigOps
from m2s2hil.store.session import SessionStore


def test_a_session_started_through_the_rest_api_gets_capture_time_qc(tmp_path) -> None:
    with daemon(tmp_path / "data") as d:
        sid = d.client.post("/sessions", json=sweep()).json()["session_id"]
        assert d.wait_done(sid)["state"] == "completed"
        items = d.client.get(f"/sessions/{sid}/frames").json()["items"]
        assert len(items) == 4
        scores = [i["meta"]["qc"]["score"] for i in items]
        assert all(isinstance(s, float) and 0.0 <= s <= 1.0 for s in scores)
        with SessionStore.open(d.root, sid) as store:
            (finished,) = [e["payload"] for e in store.events() if e["kind"] == "run_finished"]
        qc = finished["qc"]
        assert qc["frames"] == qc["scored"] == len(items)
        assert qc["min"] == pytest.approx(min(scores)) and qc["mean"] == pytest.approx(sum(scores) / 4)


def test_build_run_takes_exactly_one_source_of_the_session(tmp_path) -> None:
    rig = open_simulated_rig(small_rig_config())
    try:
        with pytest.raises(UsageError, match="exactly one of sweep, resume or store"):
            build_run(rig, tmp_path, sweep=small_sweep(), resume="x")
        with pytest.raises(UsageError, match="exactly one"):
            build_run(rig, tmp_path)
        engine = build_run(rig, tmp_path, sweep=small_sweep(mode="continuous"))
        assert isinstance(engine.steps, ContinuousSteps) and engine.qc is None
        engine.store.close()
        hook = capture_qc_hook()  # the front end's (the engine does not import the analysis)
        engine = build_run(rig, tmp_path, sweep=small_sweep(), qc=hook)
        assert isinstance(engine.steps, StopAndGoSteps) and engine.qc is hook
        engine.store.close()
    finally:
        rig.close()


def test_the_rig_records_each_devices_capabilities_once() -> None:
    rig = open_simulated_rig(small_rig_config())
    try:
        by_device = {link.device: link for link in rig.links}
        stage, relays, camera = by_device["stage"], by_device["relays"], by_device["camera"]
        assert set(stage.roles) == {"turntable", "tilt"}  # one GRBL controller serves both axes
        assert stage.alarm is not None and stage.reconnect is not None and stage.homing is not None
        assert relays.roles == ("lights",) and relays.alarm is None and relays.reconnect is not None
        assert camera.roles == ("camera",) and camera.reconnect is not None and camera.alarm is None
        assert rig.rotation is rig.turntable
        ops = RigOps(rig)
        assert ops.roles_named("stage") == {"turntable", "tilt"} and ops.roles_named("nobody") == set()
    finally:
        rig.close()


def test_homing_goes_through_the_controllers_alarm_clearing_once(tmp_path) -> None:
    rig = open_simulated_rig(small_rig_config())
    try:
        sim = rig.sims["stage"]
        before = len(sim.received)  # type: ignore[attr-defined]
        assert RigOps(rig).home("turntable") == ["turntable", "tilt"]
        sent = bytes(sim.received[before:])  # type: ignore[attr-defined]
        assert sent.count(b"$H") == 1 and b"\x18" in sent  # soft reset, then one homing cycle
    finally:
        rig.close()


def test_continuous_capture_on_a_turntable_that_cannot_rotate_fails_before_moving(tmp_path) -> None:
    rig = open_simulated_rig(small_rig_config())
    try:
        stiff = dataclasses.replace(rig, rotation=None)
        sweep_ = small_sweep(mode="continuous")
        store = SessionStore.create(tmp_path / "data", sweep_, rig.config, clock=rig.clock)
        engine = make_engine(stiff, store, sweep_)
        pose = rig.world.pose()
        with pytest.raises(SessionFailed) as ei:
            engine.run()
        assert isinstance(ei.value.cause, UsageError) and "cannot rotate continuously" in str(ei.value.cause)
        assert store.frames() == [] and rig.world.pose() == pose
        assert_rig_safe(rig)
        store.close()
    finally:
        rig.close()
