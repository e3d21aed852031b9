"""Shared fixtures, the numba cache of each test process, and which tests share an xdist worker."""

from __future__ import annotations

import sys
from collections.abc import Iterator

import m2s2hil.simulators  # noqa: F401  (registers sim:// with pyserial)
import pytest
from m2s2hil.simulators.clock import VirtualClock
from numba_cache import use_private_numba_cache
from shared_sessions import SharedSessions

# The machine's PYTHONDONTWRITEBYTECODE (the daemon image's setting) would have every worker
# assertion-rewrite the test modules anew at each run (8 s of its collection) and every daemon
# or CLI process a test starts compile our modules from source. Bytecode goes to __pycache__.
sys.dont_write_bytecode = False

# the browser tests' one Chromium per process, and its event loop kept out of the other tests' way
pytest_plugins = ["browser_support"]


def _is_xdist_controller(config: pytest.Config) -> bool:
    """The process that hands tests to ``-n`` workers (it runs none itself)."""
    distributing = getattr(config.option, "dist", "no") != "no" and bool(getattr(config.option, "tx", None))
    return distributing and not hasattr(config, "workerinput")


def pytest_configure(config: pytest.Config) -> None:
    # before any test module imports numba: see tests/numba_cache.py. The controller of an
    # xdist run claims no slot, or its workers would inherit it and share one cache.
    if not _is_xdist_controller(config):
        use_private_numba_cache(worker=hasattr(config, "workerinput"))


@pytest.hookimpl(optionalhook=True)  # a hook of pytest-xdist (the test extra): ignored without it
def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object | None:
    """With ``-n N`` (``--dist load``): tests that share a module's fixture, or compile the
    same numba kernels, run on one worker (tests/xdist_groups.py)."""
    if config.getvalue("dist") != "load":
        return None  # an explicit --dist loadfile, each, ... is xdist's own
    from xdist_groups import GroupedScheduling

    return GroupedScheduling(config, log)


@pytest.fixture
def vclock() -> VirtualClock:
    return VirtualClock()


@pytest.fixture(scope="session")
def shared_sessions(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SharedSessions]:
    """Sessions written once per test process, for tests that only read them (see
    tests/shared_sessions.py); fails the run if a test wrote to one."""
    shared = SharedSessions(tmp_path_factory.mktemp("shared-sessions"))
    yield shared
    changed = shared.changed()
    assert not changed, f"a test wrote to a shared session (use copy_to): {changed[:5]}"
