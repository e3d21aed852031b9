"""Shared fixtures."""

from __future__ import annotations

import m2s2hil.simulators  # noqa: F401  (registers sim:// with pyserial)
import pytest
from m2s2hil.simulators.clock import VirtualClock
from numba_cache import use_private_numba_cache


def pytest_configure(config: pytest.Config) -> None:
    use_private_numba_cache()  # before any test module imports numba: see tests/numba_cache.py


@pytest.fixture
def vclock() -> VirtualClock:
    return VirtualClock()
