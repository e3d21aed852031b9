"""Headless Chromium for the browser tests: Debian's ``chromium`` driven by playwright through
``executable_path`` (playwright's own browser download does not work here). ``.ci/run`` installs
the package; without it the browser tests are skipped with the reason."""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator
from typing import Any

import pytest

CHROMIUM_ARGS = ["--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--disable-dev-shm-usage"]


def chromium_path() -> str | None:
    for name in (os.environ.get("M2S2HIL_CHROMIUM"), "chromium", "chromium-browser"):
        if name and (path := shutil.which(name)):
            return path
    return None


@contextlib.contextmanager
def browser() -> Iterator[Any]:
    """A playwright Browser on the system's Chromium (skips the test when there is none)."""
    exe = chromium_path()
    if exe is None:
        pytest.skip("no chromium on PATH (Debian package 'chromium'; .ci/run installs it)")
    sync_api = pytest.importorskip("playwright.sync_api")
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=exe, args=CHROMIUM_ARGS, headless=True)
        try:
            yield b
        finally:
            b.close()


def start_session_from_form(page: Any, *, tilts: tuple[str, ...] = ("E1",), step_deg: int = 90,
                            frames: int | None = None) -> None:
    """In the console's Sessions view: keep only ``tilts`` ticked, set the azimuth step, wait for
    the form's estimate (``frames`` frames when given) and start the session."""
    page.click("#tabs button[data-view='sessions']")
    page.wait_for_function("document.querySelectorAll('#f-tilts input').length > 0")
    for box in page.query_selector_all("#f-tilts input"):
        if (box.get_attribute("value") in tilts) != box.is_checked():
            box.click()
    page.fill("#f-step", str(step_deg))
    page.dispatch_event("#f-step", "change")
    if frames is not None:
        page.wait_for_function(f"document.getElementById('estimate').textContent.includes('{frames} frames')")
    page.click("#start")
