"""Shared fixtures, the numba cache of each test process, and how tests share xdist workers."""

from __future__ import annotations

from collections.abc import Iterator

import m2s2hil.simulators  # noqa: F401  (registers sim:// with pyserial)
import pytest
from m2s2hil.simulators.clock import VirtualClock
from numba_cache import use_private_numba_cache
from shared_sessions import SharedSessions


def _is_xdist_controller(config: pytest.Config) -> bool:
    """The process that hands tests to ``-n`` workers (it runs none itself)."""
    distributing = getattr(config.option, "dist", "no") != "no" and bool(getattr(config.option, "tx", None))
    return distributing and not hasattr(config, "workerinput")


def pytest_configure(config: pytest.Config) -> None:
    # before any test module imports numba: see tests/numba_cache.py. The controller of an
    # xdist run claims no slot, or its workers would inherit it and share one cache.
    if not _is_xdist_controller(config):
        use_private_numba_cache(worker=hasattr(config, "workerinput"))


#: Modules that compile the numba kernels of every demosaicing method and calibration (about
#: 45 s on a cold cache, as in CI's fresh clone): one worker compiles them, not both. The
#: kernels of a capture with the default method are compiled by every worker that captures.
KERNEL_MODULES = frozenset({"test_demosaic.py", "test_calibration.py", "test_processing_pipeline.py",
                            "test_processing_stability.py"})


@pytest.hookimpl(tryfirst=True)  # before xdist's own hook reads the groups (--dist loadgroup)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Tests that share a module- or class-scoped fixture go to one xdist worker, so the fixture
    (a simulated capture, a plan expansion) is built once rather than once per worker; so do
    the tests of :data:`KERNEL_MODULES`."""
    for item in items:
        info = getattr(item, "_fixtureinfo", None)
        if info is None or item.get_closest_marker("xdist_group"):
            continue
        if item.path.name in KERNEL_MODULES:
            item.add_marker(pytest.mark.xdist_group("numba-kernels"))
            continue
        shared = any(defs[-1].scope in ("module", "class") and defs[-1].baseid != ""
                     for defs in info.name2fixturedefs.values())
        if shared:
            item.add_marker(pytest.mark.xdist_group(item.nodeid.split("::", 1)[0]))


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
