"""Jogs serialised in the daemon: relative jogs sent together end at their sum (issue 24), through
real HTTP (uvicorn on a port) against the simulated rig; a stop, a refused jog and the emergency
stop leave the next jog starting where it should."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from api_support import daemon, uvicorn_thread


@pytest.fixture(scope="module")
def http(tmp_path_factory: pytest.TempPathFactory) -> Iterator[httpx.Client]:
    root: Path = tmp_path_factory.mktemp("jogs") / "data"
    with (daemon(root) as d, uvicorn_thread(d.client.app) as base,
          httpx.Client(base_url=base, timeout=30, headers={"X-M2S2HIL": "1"}) as client):
        client.clock = d.rig.clock  # type: ignore[attr-defined]  # the rig's virtual clock
        yield client


def axis(http: httpx.Client, role: str) -> dict:
    return {a["role"]: a for a in http.get("/rig/axes").json()["axes"]}[role]


def wait_idle(http: httpx.Client, role: str, timeout: float = 60.0) -> float:
    deadline = time.monotonic() + timeout
    while True:
        a = axis(http, role)
        if not a["moving"]:
            return float(a["position_deg"])
        assert time.monotonic() < deadline, f"the {role} never stopped: {a}"
        http.clock.advance(0.25)  # type: ignore[attr-defined]  # virtual time: the move goes on


def together(http: httpx.Client, role: str, deltas: list[float]) -> list[httpx.Response]:
    """Every jog from its own thread, released at the same instant."""
    gate = threading.Barrier(len(deltas))
    out: list[httpx.Response | None] = [None] * len(deltas)

    def send(i: int, delta: float) -> None:
        gate.wait()
        out[i] = http.post(f"/rig/axes/{role}/jog", json={"delta_deg": delta})

    threads = [threading.Thread(target=send, args=(i, d)) for i, d in enumerate(deltas)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert all(r is not None for r in out)
    return [r for r in out if r is not None]


def test_plus_ten_and_plus_one_together_end_at_eleven(http: httpx.Client) -> None:
    start = wait_idle(http, "turntable")
    rs = together(http, "turntable", [10.0, 1.0])
    assert [r.status_code for r in rs] == [202, 202], [r.text for r in rs]
    # the later of the two was commanded to the sum, whichever came first
    assert max(r.json()["target_deg"] for r in rs) == pytest.approx(start + 11)
    assert wait_idle(http, "turntable") == pytest.approx(start + 11, abs=0.05)


def test_twenty_concurrent_jogs_end_at_their_sum(http: httpx.Client) -> None:
    start = wait_idle(http, "turntable")
    rs = together(http, "turntable", [1.0] * 20)
    assert {r.status_code for r in rs} == {202}, [r.text for r in rs if r.status_code != 202]
    targets = sorted(r.json()["target_deg"] for r in rs)
    assert targets == pytest.approx([start + k for k in range(1, 21)])  # each one degree further
    assert wait_idle(http, "turntable") == pytest.approx(start + 20, abs=0.05)
    assert axis(http, "turntable")["target_deg"] == pytest.approx(start + 20)  # where the next jog starts


def test_a_jog_after_a_stop_or_a_refusal_starts_where_it_should(http: httpx.Client) -> None:
    start = wait_idle(http, "turntable")
    assert http.post("/rig/axes/turntable/jog", json={"delta_deg": 60}).status_code == 202
    stopped = http.post("/rig/axes/turntable/stop").json()["position_deg"]
    assert wait_idle(http, "turntable") == pytest.approx(stopped, abs=0.05)
    r = http.post("/rig/axes/turntable/jog", json={"delta_deg": 1})  # from where it stopped, not start+61
    assert r.json()["target_deg"] == pytest.approx(stopped + 1, abs=0.05)
    here = wait_idle(http, "tilt")
    tilt = axis(http, "tilt")
    r = http.post("/rig/axes/tilt/jog", json={"delta_deg": tilt["max_deg"] - here + 1})
    assert r.status_code == 422 and "soft limits" in r.json()["detail"]
    r = http.post("/rig/axes/tilt/jog", json={"delta_deg": -2})  # the refused jog counted for nothing
    assert r.status_code == 202 and r.json()["target_deg"] == pytest.approx(here - 2)
    assert http.post("/rig/stop").json()["safe"] is True
    http.post("/queue/release")
    now = wait_idle(http, "tilt")
    r = http.post("/rig/axes/tilt/jog", json={"delta_deg": 1})  # after the e-stop: from the read-back
    assert r.status_code == 202 and r.json()["target_deg"] == pytest.approx(now + 1, abs=0.05)
    assert wait_idle(http, "turntable") != pytest.approx(start + 61, abs=1)
