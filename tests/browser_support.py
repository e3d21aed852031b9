"""Headless Chromium for the browser tests: Debian's ``chromium`` driven by playwright through
``executable_path`` (playwright's own browser download does not work here). ``.ci/run`` installs
the package; without it the browser tests are skipped with the reason.

One browser serves every browser test of a test process (each ``-n`` worker): playwright's
driver and Chromium take about a second of CPU to start, which each browser module paid before.
Tests stay apart through browser contexts of their own (cookies, storage, cache, viewport): the
``new_page`` fixture opens one per page and closes it after the test, also a failed one, so no
page left behind polls a daemon while later tests run.

``tests/conftest.py`` loads this module as a plugin, for the fixtures and for one more duty.
Playwright's sync API marks its event loop as the main thread's running loop between its calls,
so while playwright runs, ``asyncio.run`` in the main thread fails ("cannot be called from a
running event loop"). Before each test that uses no browser the mark is taken off (the loop
itself stays suspended, untouched), and it is put back before anything here talks to the
browser."""

from __future__ import annotations

import asyncio
import contextlib
import os
import shutil
from collections.abc import Callable, Iterator
from typing import Any

import pytest

CHROMIUM_ARGS = ["--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--disable-dev-shm-usage"]
NO_CHROMIUM = "no chromium on PATH (Debian package 'chromium'; .ci/run installs it)"
FIXTURE = "chromium"  # a test whose fixtures include this one talks to the browser


def chromium_path() -> str | None:
    for name in (os.environ.get("M2S2HIL_CHROMIUM"), "chromium", "chromium-browser"):
        if name and (path := shutil.which(name)):
            return path
    return None


class SharedChromium:
    """The process's playwright and browser, started by the first test that needs them and
    closed when the test session ends."""

    def __init__(self) -> None:
        self._playwright: Any = None
        self._browser: Any = None
        self._loop: asyncio.AbstractEventLoop | None = None

    def get(self) -> Any:
        """The browser (skips the calling test when there is no Chromium or no playwright)."""
        if self._browser is not None:
            self.mark()
            return self._browser
        exe = chromium_path()
        if exe is None:
            pytest.skip(NO_CHROMIUM)
        sync_api = pytest.importorskip("playwright.sync_api")
        playwright = sync_api.sync_playwright().start()
        try:
            browser = playwright.chromium.launch(executable_path=exe, args=CHROMIUM_ARGS, headless=True)
        except BaseException:
            playwright.stop()
            raise
        self._playwright, self._browser = playwright, browser
        self._loop = asyncio.events._get_running_loop()  # marked by playwright's last call
        return browser

    def mark(self) -> None:
        """Playwright's loop as the running loop again, as its sync API expects between calls."""
        if self._loop is not None and not self._loop.is_closed():
            asyncio.events._set_running_loop(self._loop)

    def unmark(self) -> None:
        if self._loop is not None and asyncio.events._get_running_loop() is self._loop:
            asyncio.events._set_running_loop(None)

    def close(self) -> None:
        if self._playwright is None:
            return
        self.mark()
        try:
            self._browser.close()
        finally:
            self._playwright.stop()  # (its loop ends and unmarks itself)
            self._playwright = self._browser = self._loop = None


SHARED = SharedChromium()


# ------------------------------------------------------------------- plugin hooks (tests/conftest.py)
def _uses_browser(item: pytest.Item) -> bool:
    return FIXTURE in getattr(item, "fixturenames", ())


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    if _uses_browser(item):
        SHARED.mark()
    else:
        SHARED.unmark()


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_teardown(item: pytest.Item) -> None:
    if _uses_browser(item):
        SHARED.mark()  # its fixtures close pages; a test may have run asyncio.run in between


def pytest_sessionfinish(session: pytest.Session) -> None:
    SHARED.close()


# -------------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="session")
def chromium() -> Any:
    """The process's playwright Browser on the system's Chromium (skips without one). Open pages
    through ``new_page`` (or :func:`own_page` in a wider-scoped fixture), not on this directly."""
    return SHARED.get()


@pytest.fixture
def new_page(chromium: Any) -> Iterator[Callable[..., Any]]:
    """``new_page(**context_options)``: a page in a browser context of its own (``viewport``,
    ``bypass_csp``, ...), closed after the test whatever its outcome."""
    contexts: list[Any] = []

    def make(**options: Any) -> Any:
        ctx = chromium.new_context(**options)
        contexts.append(ctx)
        return ctx.new_page()

    yield make
    SHARED.mark()
    for ctx in contexts:
        ctx.close()


@contextlib.contextmanager
def own_page(browser: Any, **options: Any) -> Iterator[Any]:
    """A page in a browser context of its own for a module- or class-scoped fixture; closed on
    leaving (with the loop marked: a wider fixture's teardown may follow a test without browser)."""
    SHARED.mark()
    ctx = browser.new_context(**options)
    try:
        yield ctx.new_page()
    finally:
        SHARED.mark()
        ctx.close()


@contextlib.contextmanager
def browser() -> Iterator[Any]:
    """The shared browser for a test that does not take the fixture (skips the test when there is
    no Chromium); the pages and contexts opened on it are closed on leaving."""
    b = SHARED.get()
    before = set(b.contexts)
    try:
        yield b
    finally:
        SHARED.mark()
        for ctx in set(b.contexts) - before:
            ctx.close()


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
