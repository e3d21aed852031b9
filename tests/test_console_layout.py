"""The operator console on any screen, in headless Chromium under the page's real Content Security
Policy: no view is wider than a phone (390×844), a narrow tablet (768×1024) or a desktop, and STOP
stays on screen wherever the page is scrolled; Esc stops the rig except where it means "close",
Shift+Esc and F2 always stop, Release appears next to STOP; every control has an accessible name;
the canvases have text alternatives; the error banner can be dismissed.

With ``M2S2HIL_SCREENSHOTS=DIR`` (``docs/images`` for the documentation) the phone and tablet
views are photographed into DIR."""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from api_support import daemon, uvicorn_thread
from browser_support import browser

from m2s2hil.api import create_app

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]  # a browser and a daemon

SIZES = {"phone": (390, 844), "tablet": (768, 1024), "desktop": (1400, 1000)}
VIEWS = ("setup", "sessions", "browser", "calibration")

# Controls (visible or not) without an accessible name: aria-label, aria-labelledby, a <label>,
# a button's text or a title. A placeholder is no label.
UNNAMED_JS = """() => [...document.querySelectorAll('input, select, textarea, button')].filter((e) => {
  const by = (e.getAttribute('aria-labelledby') || '').split(/\\s+/).filter(Boolean)
    .map((i) => document.getElementById(i)?.textContent || '').join('');
  const labels = [...(e.labels || [])].map((l) => l.textContent).join('');
  const own = e.tagName === 'BUTTON' ? e.textContent : '';
  return !((e.getAttribute('aria-label') || '') + by + labels + own + (e.title || '')).trim();
}).map((e) => e.outerHTML.slice(0, 120))"""

MEASURE_JS = """() => { window.scrollTo(0, document.documentElement.scrollHeight);
  const r = document.getElementById('estop').getBoundingClientRect();
  return { scroll: document.documentElement.scrollWidth, client: document.documentElement.clientWidth,
           y: window.scrollY, top: r.top, bottom: r.bottom, left: r.left, right: r.right }; }"""


@pytest.fixture(scope="module")
def console(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Any, Any, list[str]]]:
    """(daemon, page, errors): one daemon, browser and page for the module (a page costs CPU:
    the console polls); the list collects page errors and CSP violations. Desktop size."""
    from playwright.sync_api import expect

    root = tmp_path_factory.mktemp("layout")
    with daemon(root / "data") as d, uvicorn_thread(create_app(d.manager)) as base, browser() as b:
        page = b.new_page(viewport=dict(zip(("width", "height"), SIZES["desktop"], strict=True)))
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.on("console", lambda m: errors.append(m.text) if "Content Security Policy" in m.text else None)
        page.goto(base + "/")
        expect(page.locator("#rig-status")).to_contain_text("idle")
        yield d, page, errors
        page.set_viewport_size(dict(zip(("width", "height"), SIZES["desktop"], strict=True)))
        assert not errors, errors


def resize(page: Any, size: str) -> tuple[int, int]:
    w, h = SIZES[size]
    page.set_viewport_size({"width": w, "height": h})
    return w, h


def test_every_view_fits_and_stop_stays_visible(console) -> None:
    from playwright.sync_api import expect

    _, page, _ = console
    shots = os.environ.get("M2S2HIL_SCREENSHOTS")  # (screenshots cost CPU: only when asked)
    for size in SIZES:
        w, h = resize(page, size)
        for view in VIEWS:
            page.click(f"#tabs button[data-view='{view}']")
            if view == "calibration":
                expect(page.locator("#c-file")).not_to_be_empty()  # the long server paths are in
            if view == "sessions":
                expect(page.locator("#estimate")).to_contain_text("frames")
            m = page.evaluate(MEASURE_JS)
            assert m["scroll"] <= m["client"] == w, (size, view, m)
            # STOP on screen after scrolling to the very bottom (a sticky header)
            assert m["top"] >= 0 and m["bottom"] <= h and m["left"] >= 0 and m["right"] <= w, (size, view, m)
            if shots and size != "desktop" and view in ("setup", "sessions"):
                page.evaluate("() => window.scrollTo(0, 0)")
                page.screenshot(path=str(Path(shots) / f"console_{size}_{view}.png"))
    resize(page, "phone")  # scrolled down the setup view, STOP is still there
    page.click("#tabs button[data-view='setup']")
    page.evaluate("() => document.getElementById('lamps').scrollIntoView()")
    assert page.evaluate("() => window.scrollY") > 200
    expect(page.locator("#estop")).to_be_in_viewport()
    if shots:
        page.screenshot(path=str(Path(shots) / "console_phone_scrolled.png"))
    page.evaluate("() => window.scrollTo(0, 0)")
    resize(page, "desktop")


def test_esc_stops_except_where_it_closes_and_release_is_beside_stop(console) -> None:
    from playwright.sync_api import expect

    d, page, _ = console
    page.click("#tabs button[data-view='setup']")

    def held() -> bool:
        return d.client.get("/queue").json()["held"] is not None

    def release() -> None:
        page.click("#estop-release")
        expect(page.locator("#estop-release")).to_be_hidden()
        expect(page.locator("#banner")).to_be_hidden()
        assert not held()

    # Esc in a number field, a drop-down, or with the token dialog open: no stop
    page.focus("#live-exposure")
    page.keyboard.press("Escape")
    page.focus("#live-view")
    page.keyboard.press("Escape")
    d.client.get("/queue")  # (the key presses' handlers have run: they are synchronous)
    assert not held()
    expect(page.locator("#estop-release")).to_be_hidden()

    # Shift+Esc in the field stops; Release is focused next to STOP; the stop is announced
    page.focus("#live-exposure")
    page.keyboard.press("Shift+Escape")
    expect(page.locator("#banner")).to_contain_text("EMERGENCY STOP")
    expect(page.locator("#announce")).to_contain_text("EMERGENCY STOP")
    expect(page.locator("#estop-release")).to_be_focused()
    assert held()
    stop, rel = page.locator("#estop").bounding_box(), page.locator("#estop-release").bounding_box()
    assert abs(rel["y"] - stop["y"]) < stop["height"] and abs(rel["x"] - (stop["x"] + stop["width"])) < 40
    release()

    # Esc on a button (not a field) stops; F2 from a field stops
    page.focus("#live-toggle")
    page.keyboard.press("Escape")
    expect(page.locator("#estop-release")).to_be_visible()
    release()
    page.focus("#snap-note")
    page.keyboard.press("F2")
    expect(page.locator("#estop-release")).to_be_visible()
    release()

    # an error banner: shown, announced, dismissed by its button
    page.fill("[data-goto='tilt']", "999")
    page.click("[data-goto='tilt'] ~ button")
    expect(page.locator("#banner")).to_be_visible()
    expect(page.locator("#announce")).not_to_be_empty()
    page.click("#banner-close")
    expect(page.locator("#banner")).to_be_hidden()


def test_every_control_is_named_and_canvases_say_what_they_show(console) -> None:
    from playwright.sync_api import expect

    _, page, _ = console
    resize(page, "phone")
    expect(page.locator("#axes .axis")).to_have_count(2)  # the controls built from GET /rig/axes
    expect(page.locator("#f-tilts input")).not_to_have_count(0)
    assert page.evaluate(UNNAMED_JS) == []
    for cv in page.query_selector_all("canvas"):
        assert cv.get_attribute("role") == "img" and cv.get_attribute("aria-label"), cv.get_attribute("id")
    # (what they say while the live view runs: tests/test_console_browser.py)



def stage_deg(d: Any, role: str) -> float:
    dev = {e["name"]: e for e in d.client.get("/rig").json()["devices"]}["stage"]
    return float(dev["state"][f"{role}_deg"])


def wait_for(pred: Any, what: str, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


def test_keyboard_jog_with_the_step_picker(console) -> None:
    from playwright.sync_api import expect

    d, page, _ = console
    resize(page, "desktop")
    page.click("#tabs button[data-view='setup']")
    turn, tilt = stage_deg(d, "turntable"), stage_deg(d, "tilt")
    page.locator("h2", has_text="Axes").click()  # focus on the view, not in a field
    page.keyboard.press("3")
    expect(page.locator("#jog-steps button[data-step='10']")).to_have_attribute("aria-pressed", "true")
    page.keyboard.press("ArrowRight")
    page.keyboard.press("]")
    wait_for(lambda: abs(stage_deg(d, "turntable") - (turn + 20)) < 0.05, "two 10° turntable jogs")
    page.click("#jog-steps button[data-step='0.1']")  # the picker's buttons; the keys still jog
    page.keyboard.press("ArrowUp")
    wait_for(lambda: abs(stage_deg(d, "tilt") - (tilt + 0.1)) < 0.02, "a 0.1° tilt jog")
    # in a number field ↑ is the field's: no jog
    page.focus("[data-goto='tilt']")
    page.keyboard.press("ArrowUp")
    page.click("#jog-steps button[data-step='1']")
    page.keyboard.press("ArrowLeft")
    wait_for(lambda: abs(stage_deg(d, "turntable") - (turn + 19)) < 0.05, "a 1° turntable jog")
    assert abs(stage_deg(d, "tilt") - (tilt + 0.1)) < 0.02


def test_light_and_dark_follow_the_system_and_the_report_matches(console) -> None:
    from m2s2hil.analysis.report.session_html import CSS

    _, page, _ = console
    colours = "() => [getComputedStyle(document.body).backgroundColor, getComputedStyle(document.body).color]"
    report = page.context.browser.new_page()
    report.set_content(f"<!doctype html><html><head><style>{CSS}</style></head><body>report</body></html>")
    seen = {}
    for scheme in ("light", "dark"):
        page.emulate_media(color_scheme=scheme)
        report.emulate_media(color_scheme=scheme)
        seen[scheme] = page.evaluate(colours)
        assert report.evaluate(colours) == seen[scheme], scheme  # the report in the console's colours
        if os.environ.get("M2S2HIL_SCREENSHOTS"):
            page.screenshot(path=str(Path(os.environ["M2S2HIL_SCREENSHOTS"]) / f"console_{scheme}.png"))
    assert seen["light"] != seen["dark"]
    assert seen["light"][0] == "rgb(243, 245, 247)" and seen["dark"][0] == "rgb(21, 24, 28)"
    report.close()
    page.emulate_media(color_scheme="dark")


def test_long_actions_are_busy_and_cannot_be_doubled(console) -> None:
    from playwright.sync_api import expect

    d, page, _ = console
    page.click("#tabs button[data-view='setup']")
    before = len(d.client.get("/snapshots?limit=100").json()["items"])
    # record the button's states as they happen (a snapshot may take less than a poll)
    page.evaluate("""() => { window.seenBusy = [];
      new MutationObserver(() => { const b = document.getElementById('snap');
        window.seenBusy.push(b.classList.contains('busy') && b.disabled && b.ariaBusy === 'true'); })
      .observe(document.getElementById('snap'), { attributes: true }); }""")
    page.evaluate("() => { const b = document.getElementById('snap'); b.click(); b.click(); }")  # 2 clicks
    expect(page.locator("#snap")).to_be_enabled(timeout=60000)
    assert page.locator("#banner").is_hidden() or "snapshot" in page.inner_text("#banner-text"), \
        page.inner_text("#banner-text")
    expect(page.locator("#snapshots li")).to_have_count(before + 1)
    assert page.evaluate("() => window.seenBusy.includes(true)")
    assert len(d.client.get("/snapshots?limit=100").json()["items"]) == before + 1  # one, not two
