"""The rig as bluesky devices, run by bluesky's RunEngine on the simulated rig; documents validated."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("bluesky", reason="the bluesky extra (bluesky, ophyd-async) is not installed")
pytest.importorskip("ophyd_async", reason="the bluesky extra (bluesky, ophyd-async) is not installed")

from bluesky import RunEngine
from engine_helpers import assert_rig_safe, session, small_rig_config, small_sweep
from ophyd_async.plan_stubs import ensure_connected

from m2s2hil.integrations.bluesky.devices import OutOfLimits, rig_devices
from m2s2hil.integrations.bluesky.plans import m2s2_sweep
from m2s2hil.integrations.documents import DocumentCatalogue
from m2s2hil.rig.factory import open_simulated_rig
from m2s2hil.store.session import SessionStore


@pytest.fixture
def bench(tmp_path):
    cfg = small_rig_config(64)
    rig = open_simulated_rig(cfg)
    store = SessionStore.create(tmp_path / "bs", small_sweep(), cfg, session_id="bs", clock=rig.clock)
    devs = rig_devices(rig, store)
    RE = RunEngine({}, call_returns_result=True)
    RE(ensure_connected(devs.turntable, devs.tilt, devs.lamps, devs.camera))
    try:
        yield rig, store, devs, RE
    finally:
        store.close()
        rig.close()


@pytest.mark.timeout(120)
def test_sweep_as_a_bluesky_plan_writes_what_capture_writes(tmp_path, bench):
    rig, store, d, RE = bench
    cat = DocumentCatalogue()  # validates every document against event-model's schemas
    RE.subscribe(cat)
    RE(m2s2_sweep("voyager", "B3", "weak", turntable=d.turntable, tilt=d.tilt, lamps=d.lamps, camera=d.camera,
                  sweep=small_sweep()))
    assert_rig_safe(rig)
    run, = cat.runs.values()
    assert run.stop["exit_status"] == "success"
    events = run.stream("primary")
    frames = {fr.event_id: fr for fr in store.frames()}
    assert len(events) == len(frames) == 4
    for ev in events:
        eid = ev["data"]["camera_event_id"]
        raw, _ = store.read_raw(eid)
        assert np.array_equal(run.read(ev, "camera_raw"), raw)  # the document leads to the stored frame
        assert abs(ev["data"]["turntable-readback"] - ev["data"]["camera_azimuth_deg"]) <= 0.05
        assert ev["data"]["lamps-preset"] == "weak"
    assert not store.verify()
    # capture of the same sweep: the same frame events, each with the same files
    with session(tmp_path / "cap", small_sweep(), config=small_rig_config(64)) as (_, cstore, engine, _):
        engine.run()
        cap = {fr.event_id: fr for fr in cstore.frames()}
    assert cap.keys() == frames.keys()
    for eid, fr in frames.items():
        assert fr.files.keys() - {"cube"} == cap[eid].files.keys() - {"cube"}
        keys = ("event", "pose", "lamp_names", "processing_method", "mode")
        assert {k: fr.meta.get(k) for k in keys if k != "pose"} == {k: cap[eid].meta.get(k) for k in keys
                                                                    if k != "pose"}


def test_axis_refuses_a_target_beyond_its_limits(bench):
    rig, _, d, RE = bench
    import bluesky.plan_stubs as bps
    from bluesky.utils import FailedStatus

    with pytest.raises((OutOfLimits, FailedStatus)):
        RE(bps.mv(d.tilt, d.tilt.high + 1.0))
    RE(bps.mv(d.tilt, 5.0))
    assert abs(rig.tilt.position() - 5.0) <= rig.config.axes["tilt"].tolerance_deg
    RE(bps.mv(d.lamps, "directional"))
    assert rig.world.lamps_on() == d.lamps.presets["directional"]
