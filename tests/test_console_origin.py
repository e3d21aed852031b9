"""Homing or setting the origin from the console, as each axis's policy says: a factory GRBL
(no switches) on a pseudo-terminal, opened by the daemon, gets its origin through the daemon's own
connection; the built-in rig's axes (switches) home and refuse an origin."""

from __future__ import annotations

import json
import time

from api_support import daemon
from fastapi.testclient import TestClient
from m2s2hil.simulators.clock import VirtualClock
from rig_files import write_rig

from m2s2hil.api import create_app
from m2s2hil.config import load_rig
from m2s2hil.daemon.manager import SessionManager
from m2s2hil.rig.factory import open_rig
from m2s2hil.rig.origin import set_origin, state_path
from m2s2hil.rig.pty_serve import SimServer


def _idle(client: TestClient, role: str, clock: VirtualClock | None = None) -> dict:
    """The axis once it stands. On a virtual ``clock`` simulated time goes on meanwhile: it moves
    only when someone sleeps on it, so a move would crawl at the pace of these polls."""
    deadline = time.monotonic() + 20
    while True:
        ax = {a["role"]: a for a in client.get("/rig/axes").json()["axes"]}[role]
        if not ax["moving"]:
            return ax
        assert time.monotonic() < deadline
        if clock is not None:
            clock.advance(0.05)
        time.sleep(0.02)


def test_origin_from_the_console_on_a_factory_grbl(tmp_path) -> None:
    cfg = load_rig(write_rig(tmp_path / "src.toml", homing="none"))
    with SimServer(cfg) as srv:
        rig_file = tmp_path / "bench.toml"
        rig_file.write_text(srv.rig_toml())
        config = load_rig(rig_file)
        for role in ("turntable", "tilt"):
            set_origin(config, role)  # commissioned once from the command line
        rig = open_rig(load_rig(rig_file))
        mgr = SessionManager(rig, tmp_path / "data")
        mgr.start()
        try:
            with TestClient(create_app(mgr), base_url="http://127.0.0.1:8750",
                            headers={"X-M2S2HIL": "1"}) as client:
                axes = client.get("/rig/axes").json()["axes"]
                assert [a["homing"] for a in axes] == ["none", "none"]
                assert not any(a["can_home"] for a in axes)
                assert client.post("/rig/axes/turntable/home").status_code == 409  # no switches
                assert client.post("/rig/axes/turntable/jog", json={"delta_deg": 15}).status_code == 202
                assert _idle(client, "turntable")["position_deg"] == 15.0
                r = client.post("/rig/axes/turntable/origin")
                assert r.status_code == 200, r.text
                assert _idle(client, "turntable")["position_deg"] == 0.0
                assert srv.sims["stage"].coord_data[54][0] == 15.0  # G10 L20 reached the controller
                doc = json.loads(state_path(config).read_text())
                assert doc["origins"]["turntable"]["offset_units"] == 15.0
                # moves count from the new origin
                client.post("/rig/axes/turntable/goto", json={"position_deg": 5})
                assert _idle(client, "turntable")["position_deg"] == 5.0
                assert srv.sims["stage"].axis_position("X") == 20.0
        finally:
            mgr.close(abort=True, timeout=30)
            rig.close()


def test_builtin_rig_homes_and_refuses_an_origin(tmp_path) -> None:
    with daemon(tmp_path / "data") as d:
        axes = d.client.get("/rig/axes").json()["axes"]
        assert all(a["homing"] == "switches" and a["can_home"] for a in axes)
        r = d.client.post("/rig/axes/tilt/origin")
        assert r.status_code == 422 and "switches" in r.json()["detail"]
        d.client.post("/rig/axes/tilt/goto", json={"position_deg": 10})
        if d.client.get("/rig/axes").json()["axes"][1]["moving"]:
            r = d.client.post("/rig/axes/tilt/home")
            assert r.status_code == 422 and "moving" in r.json()["detail"]
        assert _idle(d.client, "tilt", d.rig.clock)["position_deg"] == 10.0
        r = d.client.post("/rig/axes/tilt/home")
        assert r.status_code == 200, r.text
        assert abs(r.json()["position_deg"]) < 0.05
