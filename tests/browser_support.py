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
