"""The emergency stop's hardware side and the safety check (read-back of lamps and axes).

The stop talks to the devices from a request thread while the engine thread may still own
them: switching the lamps off is safe beside it (the relay driver serialises its own I/O);
motion is stopped once the engine had ``grace_s`` to reach its own teardown."""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

from m2s2hil.rig.opened import Rig

from .engine_requests import request, wait_terminal
from .jobqueue import Job

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SafeCheck:
    safe: bool
    lamps_on: list[int]
    moving: dict[str, bool]
    errors: list[str]


def check_safe(rig: Rig) -> SafeCheck:
    """Read the devices back: which lamps are on, which axis moves."""
    errors: list[str] = []
    lamps: list[int] = []
    moving: dict[str, bool] = {}
    try:
        lamps = sorted(rig.lights.state())
    except Exception as exc:
        errors.append(f"lamps read-back: {type(exc).__name__}: {exc}")
    for role, ax in (("turntable", rig.turntable), ("tilt", rig.tilt)):
        try:
            moving[role] = bool(ax.is_moving())
        except Exception as exc:
            errors.append(f"{role} read-back: {type(exc).__name__}: {exc}")
    safe = not errors and not lamps and not any(moving.values())
    return SafeCheck(safe, lamps, moving, errors)


def make_safe(rig: Rig) -> list[str]:
    """Lamps off and axes stopped; what went wrong doing it."""
    return [f"{type(e).__name__}: {e}" for e in rig.safe()]


def lamps_off(rig: Rig) -> list[str]:
    """Every lamp off, the stop's first step; what went wrong doing it."""
    try:
        rig.lights.set(())
    except Exception as exc:
        return [f"lamps off: {type(exc).__name__}: {exc}"]
    return []


def stop_rig(rig: Rig, hw: threading.Lock, job: Job | None, *,
             grace_s: float, timeout_s: float) -> tuple[SafeCheck, list[str]]:
    """After :func:`lamps_off`: abort ``job``'s engine, if it runs, and give it ``grace_s`` to
    reach its own teardown (which stops motion too), then stop the axes from this thread
    anyway (a move is not waited out); once the engine has ended, make safe again (holding
    ``hw``, the request threads' device lock) and read the devices back to confirm.
    Returns the read-back and every error met."""
    errors: list[str] = []
    eng = job.engine if job is not None else None
    if eng is None:
        # Nothing runs: stop the axes now, not after a request thread's conversation (a live-view
        # grab) gives ``hw`` back; the drivers serialise their own I/O, as beside an engine.
        errors += make_safe(rig)
    if eng is not None and not eng.state.terminal:
        request(eng, "abort")
        if not wait_terminal(eng, grace_s):
            errors += make_safe(rig)
            if not wait_terminal(eng, timeout_s):
                errors.append(f"session {job.session_id} did not end within {timeout_s:g} s")
    with hw:
        errors += make_safe(rig)
    check = check_safe(rig)
    errors += check.errors
    if check.safe:
        log.warning("emergency stop done: lamps off, motion stopped")
    else:
        log.error("emergency stop could NOT confirm a safe rig: %s", errors)
    return check, errors
