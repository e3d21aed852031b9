"""Shared fixtures."""

from __future__ import annotations

import m2s2hil.simulators  # noqa: F401  (registers sim:// with pyserial)
import pytest
from m2s2hil.simulators.clock import VirtualClock


@pytest.fixture
def vclock() -> VirtualClock:
    return VirtualClock()
