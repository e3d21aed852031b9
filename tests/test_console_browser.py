"""The operator console in a real browser (headless Chromium through playwright) against a daemon
on the simulated rig: the live view updates, a jog moves the simulated stage, a session started
from the form completes and shows up in the browser view, the emergency stop stops a session, a
white-reference capture writes the calibration file, and a token-guarded daemon asks for the token.

Screenshots of every view go to the test's temporary folder; with ``M2S2HIL_SCREENSHOTS=DIR`` they
are written to DIR (``docs/images`` for the documentation)."""

from __future__ import annotations

import os
import re
import time
from pathlib import Path

import httpx
import pytest
from api_support import TOKEN, daemon, uvicorn_thread
from browser_support import browser, start_session_from_form

from m2s2hil.api import create_app

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]  # a browser and a daemon


def shots_dir(tmp_path: Path) -> Path:
    out = Path(os.environ.get("M2S2HIL_SCREENSHOTS") or tmp_path / "shots")
    out.mkdir(parents=True, exist_ok=True)
    return out


def stage_deg(d, role: str) -> float:
    dev = {e["name"]: e for e in d.client.get("/rig").json()["devices"]}["stage"]
    return float(dev["state"][f"{role}_deg"])


def wait_for(pred, timeout: float = 60.0, what: str = "condition"):
    deadline = time.monotonic() + timeout
    while True:
        v = pred()
        if v:
            return v
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.1)


def test_console_end_to_end(tmp_path: Path) -> None:
    shots = shots_dir(tmp_path)
    with daemon(tmp_path / "data") as d, uvicorn_thread(create_app(d.manager)) as base, browser() as b:
        # bypass_csp: playwright's wait_for_function evaluates strings, which the console's CSP
        # forbids (the token test below runs under the real policy)
        page = b.new_page(viewport={"width": 1400, "height": 1000}, bypass_csp=True)
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(base + "/")
        page.wait_for_function("document.getElementById('rig-status').textContent.includes('idle')")

        # live view: frames arrive and keep coming
        page.fill("#live-exposure", "4")
        page.dispatch_event("#live-exposure", "change")
        page.click("#live-toggle")
        page.wait_for_function("window.m2s2hilLive && window.m2s2hilLive.frames >= 3", timeout=30000)
        first = page.evaluate("window.m2s2hilLive.seq")
        page.wait_for_function(f"window.m2s2hilLive.seq > {first}", timeout=30000)
        assert page.locator("#st-sat").inner_text().endswith("%")
        # the canvases' text alternatives say what they show
        assert re.match(r"live view, false colour: frame \d+ .* ms",
                        page.get_attribute("#live-canvas", "aria-label"))
        assert re.search(r"[\d.]+ % saturated, 99.9th percentile \d+ / \d+",
                         page.get_attribute("#histogram", "aria-label"))
        # the turntable-axis overlay follows the operator's setting (it travels with the frames)
        page.fill("#live-axis", "0.4")
        page.dispatch_event("#live-axis", "change")
        # (read from the served app: each app keeps its own live view)
        wait_for(lambda: httpx.get(base + "/camera/live").json()["settings"]["axis_x"] == 0.4,
                 what="the axis setting")

        # jog: the simulated stage moves (read back through GET /rig)
        before = stage_deg(d, "turntable")
        page.click("[data-jog='turntable:10']")
        wait_for(lambda: abs(stage_deg(d, "turntable") - (before + 10)) < 0.1, what="the jog")
        page.click("#presets button[data-preset='weak']")
        wait_for(lambda: len(d.rig.lights.state()) == 3, what="the weak preset")
        page.wait_for_function("document.querySelector('#presets button.on') !== null")
        page.screenshot(path=str(shots / "console_setup.png"))
        page.click("#live-toggle")  # stop the live view

        # a session from the form: estimate, start, progress, contact sheet
        start_session_from_form(page, tilts=("E1",), step_deg=90, frames=4)
        page.wait_for_function("document.getElementById('run-state').textContent === 'completed'",
                               timeout=60000)
        page.wait_for_function("document.querySelectorAll('#run-sheet img[src^=\"blob:\"]').length === 4")
        # the stored JPEG previews decode in the browser (not merely fetched)
        page.wait_for_function("[...document.querySelectorAll('#run-sheet img')]"
                               ".every((i) => i.complete && i.naturalWidth > 0)")
        sid = page.inner_text("#run-id")
        st = d.client.get(f"/sessions/{sid}").json()
        assert st["done"] == st["total"] and st["skipped"] == 0
        page.screenshot(path=str(shots / "console_sessions.png"))

        # the session browser lists it; verify and the contact sheet work
        page.click("#tabs button[data-view='browser']")
        row = page.locator("#sessions-table tbody tr", has_text=sid)
        row.click()
        page.click("#b-verify")
        page.wait_for_function("document.getElementById('b-result').textContent.startsWith('verified')")
        page.wait_for_function("document.querySelectorAll('#b-sheet img[src^=\"blob:\"]').length === 4")
        page.screenshot(path=str(shots / "console_browser.png"))

        # emergency stop from the keyboard during a session
        start_session_from_form(page, tilts=("E0", "E1", "E2"), step_deg=10)
        page.wait_for_function("['running'].includes(document.getElementById('run-state').textContent)")
        sid2 = page.inner_text("#run-id")
        page.keyboard.press("Escape")
        page.wait_for_function("document.getElementById('banner').textContent.includes('EMERGENCY STOP')")
        st = d.wait_done(sid2)
        assert st["state"] == "estopped" and st["done"] < st["total"]
        assert d.rig.lights.state() == frozenset()
        page.wait_for_function("document.getElementById('rig-status').textContent.startsWith('held')")
        page.screenshot(path=str(shots / "console_estop.png"))
        page.click("#queue-release")
        page.wait_for_function("document.getElementById('rig-status').textContent.includes('idle')")

        # calibration: a white reference written to the calibration file
        page.click("#tabs button[data-view='calibration']")
        page.select_option("#w-light", "strong")
        page.fill("#w-exposure", "5")
        page.fill("#w-frames", "4")
        page.click("#white-form button[type=submit]")
        page.wait_for_function("!['', 'capturing…'].includes($('w-result').textContent)",
                               timeout=60000)
        assert page.inner_text("#w-result").startswith("written to"), page.inner_text("#w-result")
        cal = d.client.get("/calibration").json()
        assert cal["exists"] and cal["white_reference"]["provenance"]["lighting"] == "strong"
        page.click("#phase-form button[type=submit]")
        page.wait_for_function("document.getElementById('p-result').textContent.length > 0")
        page.screenshot(path=str(shots / "console_calibration.png"))
        assert not errors, errors


def test_console_asks_for_the_token_and_uses_it(tmp_path: Path) -> None:
    with daemon(tmp_path / "data", token=TOKEN) as d, \
            uvicorn_thread(create_app(d.manager, token=TOKEN)) as base, browser() as b:
        from playwright.sync_api import expect

        page = b.new_page()
        page.goto(base + "/")
        expect(page.locator("#login")).to_be_visible()
        page.fill("#token", "wrong")
        page.click("#login-form button")
        expect(page.locator("#login")).to_be_visible()
        page.fill("#token", TOKEN)
        page.click("#login-form button")
        expect(page.locator("#rig-status")).to_contain_text("idle")
        expect(page.locator("#login")).to_be_hidden()
        before = stage_deg(d, "tilt")
        page.click("[data-jog='tilt:1']")
        wait_for(lambda: abs(stage_deg(d, "tilt") - (before + 1)) < 0.1, what="the jog with a token")
