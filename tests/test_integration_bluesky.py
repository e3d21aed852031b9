"""The rig as bluesky devices, run by bluesky's RunEngine on the simulated rig; documents validated."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("bluesky", reason="the bluesky extra (bluesky, ophyd-async) is not installed")
pytest.importorskip("ophyd_async", reason="the bluesky extra (bluesky, ophyd-async) is not installed")

from bluesky import RunEngine
from engine_helpers import assert_rig_safe, session, small_rig_config, small_sweep
from ophyd_async.plan_stubs import ensure_connected

from m2s2hil.integrations.bluesky.darks import LensCapNeeded
from m2s2hil.integrations.bluesky.devices import OutOfLimits, rig_devices
from m2s2hil.integrations.bluesky.plans import m2s2_sweep
from m2s2hil.integrations.documents import DocumentCatalogue
from m2s2hil.processing.demosaic import get_demosaicer
from m2s2hil.processing.mosaic import MosaicLayout
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


def _demosaic(store, mosaic: np.ndarray) -> np.ndarray:
    model = store.rig.camera.model
    layout = MosaicLayout.from_pattern(model.layout, model.n_bands)
    demosaicer = get_demosaicer(store.sweep.processing, layout, (model.height, model.width))
    return np.array(demosaicer.process(mosaic), copy=True)


def _expected_cube(store, eid: str) -> np.ndarray:
    """max(raw - dark, 0) of the stored frame, demosaicked with the session's method (from scratch)."""
    raw, _ = store.read_raw(eid)
    dark = store.load_dark(store.frame(eid).meta["dark_id"]).astype(np.int32)
    return _demosaic(store, np.maximum(raw.astype(np.int32) - dark, 0).astype(np.uint16))


@pytest.mark.timeout(180)
def test_sweep_as_a_bluesky_plan_writes_what_capture_writes(tmp_path, bench):
    rig, store, d, RE = bench
    cat = DocumentCatalogue()  # validates every document against event-model's schemas
    RE.subscribe(cat)
    RE(m2s2_sweep("voyager", "B3", "weak", turntable=d.turntable, tilt=d.tilt, lamps=d.lamps, camera=d.camera,
                  sweep=small_sweep()))
    assert_rig_safe(rig)
    assert not rig.world.lens_cap  # the simulated cap came off after the darks
    run, = cat.runs.values()
    assert run.stop["exit_status"] == "success"
    events = run.stream("primary")
    frames = {fr.event_id: fr for fr in store.frames()}
    darks = {dk.dark_id: dk for dk in store.darks()}
    assert len(events) == len(frames) == 4 and len(darks) == 1
    for ev in events:
        eid = ev["data"]["camera_event_id"]
        raw, _ = store.read_raw(eid)
        assert np.array_equal(run.read(ev, "camera_raw"), raw)  # the document leads to the stored frame
        assert abs(ev["data"]["turntable-readback"] - ev["data"]["camera_azimuth_deg"]) <= 0.05
        assert ev["data"]["lamps-preset"] == "weak"
    assert not store.verify()
    # capture of the same sweep: the same events (darks included), each with the same files
    with session(tmp_path / "cap", small_sweep(), config=small_rig_config(64)) as (_, cstore, engine, _):
        engine.run()
        cap = {fr.event_id: fr for fr in cstore.frames()}
        cap_darks = {dk.dark_id: dk for dk in cstore.darks()}
        for eid in cap:  # the reference computation agrees with capture's own cubes
            assert np.array_equal(cstore.read_cube(eid), _expected_cube(cstore, eid))
    assert cap.keys() == frames.keys() and cap_darks.keys() == darks.keys()
    assert store.completed_event_ids() == set(cap) | set(cap_darks)
    for did, dk in darks.items():
        assert dk.files.keys() == cap_darks[did].files.keys()
        assert (dk.exposure_s, dk.gain, dk.n_frames, dk.reduce) == (
            cap_darks[did].exposure_s, cap_darks[did].gain, cap_darks[did].n_frames, cap_darks[did].reduce)
        assert dk.meta.keys() == cap_darks[did].meta.keys()
    for eid, fr in frames.items():
        assert fr.files.keys() == cap[eid].files.keys()
        keys = ("event", "lamp_names", "processing_method", "mode", "dark_id")
        assert {k: fr.meta.get(k) for k in keys} == {k: cap[eid].meta.get(k) for k in keys}
        assert fr.meta["dark_id"] in darks  # every frame names its master dark
        assert fr.meta["dark"].keys() == cap[eid].meta["dark"].keys()
        assert fr.meta["dark"]["n_frames"] == darks[fr.meta["dark_id"]].n_frames
        cube = store.read_cube(eid)
        expected = _expected_cube(store, eid)
        assert np.array_equal(cube, expected)  # dark subtracted, then demosaicked
        assert not np.array_equal(cube, _demosaic(store, store.read_raw(eid)[0]))  # not without its dark


def test_on_a_real_rig_the_plan_stops_for_the_lens_cap(bench):
    rig, store, d, RE = bench
    rig.frame_source = None  # as open_rig leaves a camera it does not simulate: the operator caps the lens
    with pytest.raises(LensCapNeeded, match="operator"):
        RE(m2s2_sweep("voyager", "B3", "weak", turntable=d.turntable, tilt=d.tilt, lamps=d.lamps,
                      camera=d.camera, sweep=small_sweep()))
    assert not store.frames() and not store.darks()  # stopped before any dark or frame
    assert_rig_safe(rig)


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


@pytest.mark.timeout(180)
def test_a_bracketed_sweep_as_a_bluesky_plan_takes_every_exposure_with_its_dark(tmp_path):
    cfg = small_rig_config(64)
    sweep = small_sweep(lighting=["directional"], azimuth_step_deg=180, bracket={"directional": [16.0]})
    rig = open_simulated_rig(cfg)
    store = SessionStore.create(tmp_path / "bs", sweep, cfg, session_id="bs", clock=rig.clock)
    try:
        devs = rig_devices(rig, store)
        RE = RunEngine({}, call_returns_result=True)
        RE(ensure_connected(devs.turntable, devs.tilt, devs.lamps, devs.camera))
        RE(m2s2_sweep("voyager", "B3", "directional", turntable=devs.turntable, tilt=devs.tilt,
                      lamps=devs.lamps, camera=devs.camera, sweep=sweep))
        assert_rig_safe(rig)
        frames = {fr.event_id: fr for fr in store.frames()}
        assert sorted(frames) == ["directional/E1/az000/f0", "directional/E1/az000/f0/x16",
                                  "directional/E1/az180/f0", "directional/E1/az180/f0/x16"]
        darks = {dk.dark_id: dk.exposure_s for dk in store.darks()}
        for eid, fr in frames.items():
            assert fr.meta["exposure_s"] == pytest.approx(0.048 if eid.endswith("x16") else 0.003)
            assert darks[fr.meta["dark_id"]] == pytest.approx(fr.meta["exposure_s"])
            assert np.array_equal(store.read_cube(eid), _expected_cube(store, eid))
    finally:
        store.close()
        rig.close()
