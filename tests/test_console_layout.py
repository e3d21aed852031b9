"""The operator console on any screen, in headless Chromium under the page's real Content Security
Policy: no view is wider than a phone (390×844), a narrow tablet (768×1024) or a desktop, and STOP
stays on screen wherever the page is scrolled; Esc stops the rig except where it means "close",
Shift+Esc and F2 always stop, Release appears next to STOP; every control has an accessible name;
the canvases have text alternatives; the error banner can be dismissed.

Screenshots go to the test's temporary folder; with ``M2S2HIL_SCREENSHOTS=DIR`` they are written to
DIR (``docs/images`` for the documentation)."""

from __future__ import annotations

import os
import re
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


def shots_dir(tmp_path: Path) -> Path:
    out = Path(os.environ.get("M2S2HIL_SCREENSHOTS") or tmp_path / "shots")
    out.mkdir(parents=True, exist_ok=True)
    return out


@pytest.fixture(scope="module")
def console(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Any, str, Any]]:
    """(daemon, base URL, playwright browser): one of each for the module."""
    root = tmp_path_factory.mktemp("layout")
    with daemon(root / "data") as d, uvicorn_thread(create_app(d.manager)) as base, browser() as b:
        yield d, base, b


def open_console(b: Any, base: str, size: str, **kw: Any) -> tuple[Any, list[str]]:
    """A page on the console at one of SIZES; the list collects page errors and CSP violations."""
    from playwright.sync_api import expect

    w, h = SIZES[size]
    page = b.new_page(viewport={"width": w, "height": h}, **kw)
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.on("console", lambda m: errors.append(m.text) if "Content Security Policy" in m.text else None)
    page.goto(base + "/")
    expect(page.locator("#rig-status")).to_contain_text("idle")
    return page, errors


@pytest.mark.parametrize("size", list(SIZES))
def test_every_view_fits_and_stop_stays_visible(console, size: str, tmp_path: Path) -> None:
    from playwright.sync_api import expect

    _, base, b = console
    w, h = SIZES[size]
    page, errors = open_console(b, base, size)
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
        if size != "desktop" and view in ("setup", "sessions"):
            page.evaluate("() => window.scrollTo(0, 0)")
            page.screenshot(path=str(shots_dir(tmp_path) / f"console_{size}_{view}.png"))
    if size == "phone":  # scrolled down the setup view, STOP is still there (and so is the shot)
        page.click("#tabs button[data-view='setup']")
        page.evaluate("() => document.getElementById('lamps').scrollIntoView()")
        assert page.evaluate("() => window.scrollY") > 200
        page.screenshot(path=str(shots_dir(tmp_path) / "console_phone_scrolled.png"))
        expect(page.locator("#estop")).to_be_in_viewport()
    page.close()
    assert not errors, errors


def test_esc_stops_except_where_it_closes_and_release_is_beside_stop(console) -> None:
    from playwright.sync_api import expect

    d, base, b = console
    page, errors = open_console(b, base, "desktop")

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
    page.close()
    assert not errors, errors


def test_every_control_is_named_and_canvases_say_what_they_show(console) -> None:
    from playwright.sync_api import expect

    _, base, b = console
    page, errors = open_console(b, base, "phone")
    expect(page.locator("#axes .axis")).to_have_count(2)  # the controls built from GET /rig/axes
    expect(page.locator("#f-tilts input")).not_to_have_count(0)
    assert page.evaluate(UNNAMED_JS) == []
    for cv in page.query_selector_all("canvas"):
        assert cv.get_attribute("role") == "img" and cv.get_attribute("aria-label"), cv.get_attribute("id")
    page.click("#live-toggle")
    live = re.compile(r"^live view, false colour: frame \d+ .* ms")
    expect(page.locator("#live-canvas")).to_have_attribute("aria-label", live)
    hist = re.compile(r"[\d.]+ % saturated, 99.9th percentile \d+ / \d+")
    expect(page.locator("#histogram")).to_have_attribute("aria-label", hist)
    page.click("#live-toggle")
    expect(page.locator("#live-canvas")).to_have_attribute("aria-label", re.compile(r"^live view: stopped"))
    page.close()
    assert not errors, errors

