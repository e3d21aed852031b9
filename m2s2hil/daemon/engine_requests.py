"""Asking an engine that runs on its own thread to pause, resume or abort, and waiting for it."""

from __future__ import annotations

import time
from typing import Literal

from m2s2hil.engine.runner import Engine
from m2s2hil.engine.state import IllegalTransition, RunState

Action = Literal["pause", "resume", "abort"]


def request(engine: Engine, action: Action, *, raise_errors: bool = False) -> None:
    """pause/resume/abort an engine; an engine that is still starting (idle) gets a moment."""
    deadline = time.monotonic() + 2.0
    while True:
        try:
            getattr(engine, action)()
            return
        except IllegalTransition:
            if engine.state is RunState.IDLE and time.monotonic() < deadline:
                time.sleep(0.01)
                continue
            if raise_errors:
                raise
            return


def wait_terminal(engine: Engine, timeout: float) -> bool:
    """True once the engine has ended; False when ``timeout`` seconds passed first."""
    deadline = time.monotonic() + timeout
    while not engine.state.terminal:
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.01)
    return True


def wait_safe_boundary(engine: Engine, timeout: float) -> RunState:
    """Wait up to ``timeout`` seconds for the engine to be paused or ended; its state then."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        st = engine.state
        if st.terminal or st is RunState.PAUSED:
            break
        time.sleep(0.02)
    return engine.state
