"""A captured session ingested into a local Tiled server (started here) by bluesky's TiledWriter;
every raw mosaic and master dark read back through Tiled equals the stored one exactly."""

from __future__ import annotations

import numpy as np
import pytest
from engine_helpers import session, small_rig_config, small_sweep

# Each test starts a local Tiled server and captures a session: seconds each.
pytestmark = pytest.mark.slow


@pytest.fixture(autouse=True)
def tiled_extra():
    """Tiled and bluesky, imported when a test here runs, not when every worker collects (1.4 s of CPU)."""
    pytest.importorskip("tiled.server", reason="the tiled extra (tiled[server]) is not installed")
    pytest.importorskip("bluesky.callbacks.tiled_writer", reason="the tiled extra needs bluesky")


def ingest_session(*args, **kw):
    from m2s2hil.integrations.tiled import ingest_session

    return ingest_session(*args, **kw)


def start_server(tmp_path, readable):
    """A local Tiled server serving ``readable`` in place, and a client of it."""
    from tiled.client import from_uri
    from tiled.server import SimpleTiledServer

    server = SimpleTiledServer(tmp_path / "tiled", readable_storage=[readable])
    return server, from_uri(server.uri)


@pytest.fixture
def captured(tmp_path):
    with session(tmp_path / "data", small_sweep(), config=small_rig_config(64)) as (_, store, engine, _):
        engine.run()
        yield store


@pytest.fixture
def tiled_server(tmp_path, captured):
    server, client = start_server(tmp_path, captured.path.parent)
    try:
        yield client
    finally:
        server.close()


@pytest.mark.timeout(180)
def test_a_captured_session_is_ingested_and_read_back_exactly(captured, tiled_server):
    store, client = captured, tiled_server
    uid = ingest_session(store, client)
    run = client[uid]
    assert run.metadata["start"]["session_id"] == store.session_id
    assert run.metadata["stop"]["exit_status"] == "success"
    frames = store.frames()
    table = run["primary"].base["internal"].read()
    assert list(table["event_id"]) == [fr.event_id for fr in frames]
    raw = run["primary"]["raw"]
    assert raw.shape == (len(frames), 64, 64) and raw.dtype == np.uint16
    for row, eid in enumerate(table["event_id"]):
        stored, _ = store.read_raw(eid)
        assert np.array_equal(raw[row], stored)  # through the server, bit for bit
        assert table["lighting"][row] == store.frame(eid).meta["event"]["lighting"]
    darks = store.darks()
    assert darks
    master = run["dark"]["master"]
    for row, eid in enumerate(run["dark"].base["internal"].read()["event_id"]):
        stored = store.load_dark(eid)
        assert master.dtype == stored.dtype and np.array_equal(master[row], stored)


@pytest.mark.timeout(180)
def test_frames_are_served_from_the_session_files_in_place(tmp_path, captured, tiled_server):
    store, client = captured, tiled_server
    uid = ingest_session(store, client)
    first = store.frames()[0]
    stored, _ = store.read_raw(first.event_id)
    path = store.path / first.files["raw"].path
    # the server reads the session's own file in place: a frame rewritten on disk is what it serves
    import tifffile

    tifffile.imwrite(path, stored + 1)
    assert np.array_equal(client[uid]["primary"]["raw"][0], stored + 1)


@pytest.mark.timeout(180)
def test_the_bluesky_plan_streams_into_tiled_as_it_runs(tmp_path):
    from bluesky import RunEngine
    from bluesky.callbacks.tiled_writer import TiledWriter
    from ophyd_async.plan_stubs import ensure_connected

    from m2s2hil.integrations.bluesky.devices import rig_devices
    from m2s2hil.integrations.bluesky.plans import m2s2_sweep
    from m2s2hil.integrations.tiled import register_consolidator
    from m2s2hil.rig.factory import open_simulated_rig
    from m2s2hil.store.session import SessionStore

    cfg = small_rig_config(64)
    rig = open_simulated_rig(cfg)
    store = SessionStore.create(tmp_path / "bs", small_sweep(), cfg, session_id="bs", clock=rig.clock)
    server, client = start_server(tmp_path, store.path.parent)
    try:
        d = rig_devices(rig, store)
        RE = RunEngine({}, call_returns_result=True)
        RE(ensure_connected(d.turntable, d.tilt, d.lamps, d.camera))
        register_consolidator()
        RE.subscribe(TiledWriter(client))
        result = RE(m2s2_sweep("voyager", "B3", "weak", turntable=d.turntable, tilt=d.tilt, lamps=d.lamps,
                               camera=d.camera, sweep=small_sweep()))
        run = client[result.run_start_uids[0]]
        table = run["primary"].base["internal"].read()
        raw = run["primary"]["camera_raw"]
        assert len(table) == len(store.frames()) == 4
        for row, eid in enumerate(table["camera_event_id"]):
            assert np.array_equal(raw[row], store.read_raw(eid)[0])
    finally:
        server.close()
        store.close()
        rig.close()
