"""What a sweep must pass before the daemon creates a session for it: a bounded size, a known
processing method, a plan the rig can do, and room on the disk."""

from __future__ import annotations

import math
from pathlib import Path

from m2s2hil.config import RigConfig
from m2s2hil.errors import UsageError
from m2s2hil.plan import Sweep
from m2s2hil.processing.demosaic import check_method
from m2s2hil.store.atomic import DiskFull, check_free_space
from m2s2hil.store.session import estimate_session_bytes

from .errors import PlanTooLarge


def planned_frame_count(sweep: Sweep) -> float:
    """Frames a sweep asks for, without expanding it (inf when absurdly many)."""
    ratio = 360.0 / sweep.azimuth_step_deg
    if not math.isfinite(ratio) or ratio > 1e9:
        return math.inf
    n_az = math.ceil(ratio - 1e-9)
    return float(len(sweep.lighting) * len(sweep.tilts) * n_az * sweep.frames_per_pose)


def check_sweep(sweep: Sweep, cfg: RigConfig, max_plan_frames: int) -> tuple[int, int]:
    """(planned events, bytes the session will need); :class:`PlanTooLarge`, ``UsageError`` or
    ``PlanError`` (the rig cannot do it) otherwise. The size is checked before expanding."""
    n = planned_frame_count(sweep)
    if n > max_plan_frames:
        shown = "too many" if math.isinf(n) else f"{int(n)}"
        raise PlanTooLarge(
            f"the sweep asks for {shown} frames; this daemon accepts at most {max_plan_frames} "
            "per session (raise azimuth_step_deg, or lower frames_per_pose, lighting or tilts)"
        )
    try:
        check_method(sweep.processing)
    except UsageError as exc:
        raise UsageError(f"body.processing: {exc}") from None
    events = sweep.expand(cfg)  # PlanError (422) when the rig cannot do it
    return len(events), estimate_session_bytes(sweep, cfg)


def check_room(root: Path, need: int) -> None:
    """Create the data root if needed; :class:`DiskFull` when it lacks ``need`` bytes."""
    root.mkdir(parents=True, exist_ok=True)
    try:
        check_free_space(root, need)
    except DiskFull as exc:
        raise DiskFull("the data root", needed=exc.needed, free=exc.free) from None
