"""The lens cap for a session's darks on a real rig: the run parks for the operator before the
darks and before the first lit frame after them; a simulated rig caps its own lens.

A "real" rig here is the simulated one as :func:`~m2s2hil.rig.factory.open_rig` leaves a rig
whose camera is not simulated in this process: no frame source, no world, not simulated (the
simulated camera behind it still answers, so the run can go on once the operator confirms).
"""

from __future__ import annotations

import contextlib
import dataclasses
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from m2s2hil.api import create_app
from m2s2hil.commands import capture as capture_cmd
from m2s2hil.daemon.manager import SessionManager
from m2s2hil.engine import build as build_mod
from m2s2hil.engine.darks import LENS_CAP_REASON, LENS_UNCAP_REASON
from m2s2hil.engine.state import IllegalTransition, RunState
from m2s2hil.rig.factory import open_simulated_rig
from m2s2hil.rig.opened import Rig
from m2s2hil.store.catalogue import list_sessions
from m2s2hil.store.session import SessionStore
from tests import api_support
from tests.engine_helpers import make_engine, small_rig_config, small_sweep
from tests.test_capture_cli import small_rig


def as_real(rig: Rig) -> Rig:
    """``rig`` as the factory opens one whose camera is not simulated here."""
    return dataclasses.replace(rig, world=None, frame_source=None, simulated=False)


def until(pred: Callable[[], Any], timeout: float = 30.0) -> Any:
    deadline = time.monotonic() + timeout
    while not (got := pred()):
        if time.monotonic() > deadline:
            raise AssertionError("timed out")
        time.sleep(0.01)
    return got


def lens_and_captures(store: SessionStore) -> list[tuple[str, Any]]:
    """The journal's lens confirmations, darks and frames, in order."""
    return [(e["kind"], e.get("payload", e).get("capped")) for e in store.events()
            if e["kind"] in ("lens", "dark", "frame")]


def order_ok(seq: list[tuple[str, Any]]) -> None:
    """Cap confirmed, then every dark, then uncap confirmed, then every frame."""
    kinds = [k for k, _ in seq]
    assert kinds[0] == "lens" and seq[0][1] is True, seq
    second = kinds.index("lens", 1)
    assert seq[second][1] is False, seq
    assert set(kinds[1:second]) == {"dark"}, seq
    assert kinds[second + 1:] and set(kinds[second + 1:]) == {"frame"}, seq


# ---------------------------------------------------------------------------- engine
@contextlib.contextmanager
def engine_on_real_rig(tmp_path: Path, sweep: Any) -> Iterator[Any]:
    """(rig, store, engine) for session ``s1`` on a rig opened as a real one; all closed after."""
    cfg = small_rig_config()
    rig = as_real(open_simulated_rig(cfg))
    store = SessionStore.create(tmp_path, sweep, cfg, session_id="s1", clock=rig.clock)
    engine = make_engine(rig, store, sweep)
    try:
        yield rig, store, engine
    finally:
        if engine.state.active:
            engine.abort()
            engine.wait(30)
        store.close()
        rig.close()


@pytest.fixture
def real_engine(tmp_path: Path) -> Iterator[Any]:
    with engine_on_real_rig(tmp_path, small_sweep()) as got:
        yield got


def test_real_rig_waits_for_the_operator_around_the_darks(real_engine):
    rig, store, engine = real_engine
    assert rig.lens_needs_operator
    engine.start()
    until(lambda: engine.lens_wait is True)
    st = engine.status()
    assert st.state is RunState.PAUSED and st.pause_reason == LENS_CAP_REASON
    assert st.lamps_on == () and not store.darks()  # parked safe, nothing taken before the cap
    with pytest.raises(IllegalTransition):
        engine.resume()  # a plain resume is not the operator's word on the cap
    with pytest.raises(IllegalTransition):
        engine.confirm_lens(False)
    engine.confirm_lens(True)
    until(lambda: engine.lens_wait is False)
    assert engine.status().pause_reason == LENS_UNCAP_REASON
    assert len(store.darks()) == 1 and not store.frames()
    engine.confirm_lens(False)
    assert engine.wait(30).state is RunState.COMPLETED
    order_ok(lens_and_captures(store))


def test_abort_while_waiting_for_the_cap(real_engine):
    _, store, engine = real_engine
    engine.start()
    until(lambda: engine.lens_wait is True)
    engine.abort()
    assert engine.wait(30).state is RunState.ABORTED
    assert not store.darks() and not store.frames()


def test_run_resumed_after_the_darks_asks_for_the_cap_off_first(real_engine, tmp_path):
    rig, store, engine = real_engine
    engine.start()
    until(lambda: engine.lens_wait is True)
    engine.confirm_lens(True)
    until(lambda: engine.lens_wait is False)
    engine.abort()  # e.g. the operator walked away: the run ends with the cap on
    assert engine.wait(30).state is RunState.ABORTED
    [finished] = [e for e in store.events() if e["kind"] == "run_finished"]
    assert finished["payload"]["lens_cap_on"] is True
    store.close()
    again = SessionStore.open(tmp_path, "s1", clock=rig.clock, mode="write")
    try:
        resumed = make_engine(rig, again)
        resumed.start()
        until(lambda: resumed.lens_wait is not None)
        assert resumed.lens_wait is False  # the darks are stored: only the cap off is asked for
        resumed.confirm_lens(False)
        assert resumed.wait(30).state is RunState.COMPLETED
        assert len(again.darks()) == 1 and len(again.frames()) == 4
    finally:
        again.close()


def test_simulated_rig_caps_its_own_lens(tmp_path):
    cfg = small_rig_config()
    rig = open_simulated_rig(cfg)
    capped: list[bool] = []
    real_cap = rig.world.set_lens_cap  # type: ignore[union-attr]
    rig.world.set_lens_cap = lambda on: (capped.append(on), real_cap(on))  # type: ignore[union-attr]
    sweep = small_sweep()
    store = SessionStore.create(tmp_path, sweep, cfg, session_id="s1", clock=rig.clock)
    engine = make_engine(rig, store, sweep)
    try:
        assert not rig.lens_needs_operator
        assert engine.run().state is RunState.COMPLETED  # in this thread: nothing may wait
        assert capped == [True, False]
        assert not [e for e in store.events() if e["kind"] == "lens"]
    finally:
        store.close()
        rig.close()


# ---------------------------------------------------------------------------- daemon
@pytest.fixture
def real_daemon(tmp_path: Path) -> Iterator[tuple[SessionManager, TestClient]]:
    rig = as_real(open_simulated_rig(api_support.small_rig_config()))
    try:
        mgr = SessionManager(rig, tmp_path)
        mgr.start()
        app = create_app(mgr)
        with TestClient(app, base_url="http://127.0.0.1:8750", headers={"X-M2S2HIL": "1"}) as client:
            yield mgr, client
        mgr.close(abort=True, timeout=30)
    finally:
        rig.close()


def test_daemon_session_waits_and_the_lens_endpoint_continues_it(real_daemon):
    mgr, client = real_daemon
    sid = client.post("/sessions", json=api_support.sweep()).json()["session_id"]

    def status() -> dict:
        return client.get(f"/sessions/{sid}").json()

    st = until(lambda: (s := status())["state"] == "paused" and s)
    assert st["pause_reason"] == LENS_CAP_REASON and st["lamps_on"] == []
    assert client.post(f"/sessions/{sid}/resume").status_code == 409
    assert client.post(f"/sessions/{sid}/lens", json={"capped": False}).status_code == 409
    assert client.post(f"/sessions/{sid}/lens", json={"capped": "yes"}).status_code == 422
    r = client.post(f"/sessions/{sid}/lens", json={"capped": True}, headers={"X-M2S2HIL": ""})
    assert r.status_code == 200, r.text  # a JSON body passes the cross-site guard on its own
    st = until(lambda: (s := status())["state"] == "paused" and s)
    assert st["pause_reason"] == LENS_UNCAP_REASON
    assert client.post(f"/sessions/{sid}/lens", json={"capped": True}).status_code == 409
    assert client.post(f"/sessions/{sid}/lens", json={"capped": False}).status_code == 200
    st = until(lambda: (s := status())["state"] in api_support.TERMINAL and s)
    assert st["state"] == "completed", st
    assert client.post(f"/sessions/{sid}/lens", json={"capped": True}).status_code == 409
    with mgr.reads.reading(sid) as store:
        order_ok(lens_and_captures(store))


def test_lens_endpoint_unknown_session_404_and_needs_json(real_daemon):
    _, client = real_daemon
    assert client.post("/sessions/20261201T000000-nope/lens", json={"capped": True}).status_code == 404
    r = client.post("/sessions/20261201T000000-nope/lens", content=b"capped=1",
                    headers={"Content-Type": "application/x-www-form-urlencoded", "X-M2S2HIL": ""})
    assert r.status_code == 403, r.text  # neither JSON nor the marker header: maybe cross-site


# ---------------------------------------------------------------------------- CLI
@pytest.fixture
def cli_real_rig(monkeypatch):
    """``capture`` opening the rig as a real one, with a terminal to prompt on."""
    opener = build_mod.open_capture_rig
    monkeypatch.setattr(build_mod, "open_capture_rig", lambda *a, **k: as_real(opener(*a, **k)))
    monkeypatch.setattr(capture_cmd, "_stdin_is_terminal", lambda: True)


def _capture(tmp_path: Path, stdin: str) -> Any:
    args = ["--sat", "voyager", "--build", "B3", "--light", "weak", "--tilt", "E1", "--azimuth-step", "90",
            "--rig", str(small_rig(tmp_path)), "--out", str(tmp_path / "data")]
    return CliRunner().invoke(capture_cmd.app, args, input=stdin)


def test_cli_prompts_for_the_cap_and_takes_darks_after_it(tmp_path, cli_real_rig):
    res = _capture(tmp_path, "\n\n")
    assert res.exit_code == 0, res.output
    assert "Put the lens cap on, then press Enter" in res.output
    assert "Take the lens cap off, then press Enter" in res.output
    [info] = list_sessions(tmp_path / "data")
    store = SessionStore.open(tmp_path / "data", info.session_id)
    try:
        order_ok(lens_and_captures(store))
    finally:
        store.close()


def test_cli_without_an_answer_leaves_the_session_paused(tmp_path, cli_real_rig):
    res = _capture(tmp_path, "")  # end of input at the first prompt
    assert res.exit_code == capture_cmd.EXIT_PAUSED, res.output
    assert LENS_CAP_REASON in res.output
    [info] = list_sessions(tmp_path / "data")
    assert info.state == "paused"


def test_cli_non_interactive_real_camera_refused(tmp_path):
    rig_file = small_rig(tmp_path)
    rig_file.write_text(rig_file.read_text().replace('port = "sim://toucan"', 'port = "usb://"'))
    code = "import sys; from m2s2hil.cli import capture_main; sys.argv[0] = 'capture'; capture_main()"
    args = ["--sat", "voyager", "--build", "B3", "--light", "weak", "--rig", str(rig_file),
            "--out", str(tmp_path / "data")]
    res = subprocess.run([sys.executable, "-c", code, *args], stdin=subprocess.DEVNULL, capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 2, res.stderr
    assert "darks need an operator" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert not list_sessions(tmp_path / "data")  # refused before any session or device


def test_dark_needed_mid_unit_is_capped_and_the_unit_captured_again(tmp_path):
    """Auto exposure picks exposures the planned darks do not cover: each such dark parks for
    the cap and the uncap, then its unit is captured again (lamps and pose re-commanded)."""
    waits: list[bool] = []
    with engine_on_real_rig(tmp_path, small_sweep(exposure="auto")) as (_rig, store, engine):
        engine.start()
        while engine.state.active:
            wait = engine.lens_wait
            if wait is None:
                time.sleep(0.005)
                continue
            assert engine.status().lamps_on == ()
            waits.append(wait)
            engine.confirm_lens(wait)  # running again at once: the next wait is a new one
        assert engine.wait(30).state is RunState.COMPLETED, engine.status().error
        darks = {d.dark_id for d in store.darks()}
        frames = store.frames()
        assert len(darks) > 1, darks  # the planned one and at least one for an exposure found later
        assert waits == [True, False] * len(darks)
        assert {f.dark_id for f in frames} <= darks
        for f in frames:  # every frame's dark is at its own exposure, lamps were on again for it
            assert f.dark_id.startswith(f"dark/{round(f.meta['exposure_s'] * 1e6):d}us"), f
            assert f.meta["lamps_on"], f.meta


@pytest.mark.slow
@pytest.mark.timeout(600)  # generous: a loaded machine stretches it, it does not fail it
def test_console_shows_the_wait_and_confirms_the_lens(tmp_path):
    """The console's Sessions view: the pause reason and one button per confirmation."""
    from browser_support import browser, start_session_from_form

    rig = as_real(open_simulated_rig(api_support.small_rig_config()))
    try:
        mgr = SessionManager(rig, tmp_path / "data")
        mgr.start()
        with api_support.uvicorn_thread(create_app(mgr)) as base, browser() as b:
            page = b.new_page(viewport={"width": 1400, "height": 1000}, bypass_csp=True)
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(base + "/")
            start_session_from_form(page, tilts=("E1",), step_deg=90, frames=4)
            lens_button = "(b => !b.hidden && b.textContent === '{}')(document.getElementById('run-lens'))"
            page.wait_for_function(lens_button.format("Lens cap is on — continue"), timeout=30000)
            assert LENS_CAP_REASON in page.inner_text("#run-reason")
            assert page.is_disabled("#run-resume")
            page.click("#run-lens")
            page.wait_for_function(lens_button.format("Lens cap is off — continue"), timeout=30000)
            assert LENS_UNCAP_REASON in page.inner_text("#run-reason")
            page.click("#run-lens")
            page.wait_for_function("document.getElementById('run-state').textContent === 'completed'",
                                   timeout=60000)
            assert page.is_hidden("#run-lens") and page.is_hidden("#run-reason")
            assert not errors, errors
        mgr.close(abort=True, timeout=30)
    finally:
        rig.close()
