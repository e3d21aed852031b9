"""What a sweep must pass before the daemon creates a session for it, cheapest check first:
a bounded size (from the sweep's parameters, nothing expanded), a known processing method,
room on the disk (estimated from the same counts), and only then the expanded plan, which
must be one the rig can do.

Expanding a large sweep scores about a hundred candidate orders of up to
``max_plan_frames`` frames: seconds of CPU. The API calls this from its thread pool (never
on the event loop), and :data:`EXPANDING` lets one expansion run at a time, so several
large submissions at once cost one core, not all of them, and the daemon keeps answering."""

from __future__ import annotations

import math
import threading
from pathlib import Path

from m2s2hil.atomic import DiskFull, check_free_space
from m2s2hil.config import RigConfig
from m2s2hil.errors import UsageError
from m2s2hil.plan import Sweep
from m2s2hil.processing.demosaic import check_method
from m2s2hil.store.estimates import estimate_frame_bytes

from .errors import PlanTooLarge

#: One plan expansion at a time (see the module docstring).
EXPANDING = threading.BoundedSemaphore(1)


def planned_frame_count(sweep: Sweep) -> float:
    """Frames a sweep asks for, without expanding it (inf when absurdly many):
    tilts × azimuths × frames per pose × exposures per pose (a bracket's), summed over lightings."""
    ratio = 360.0 / sweep.azimuth_step_deg
    if not math.isfinite(ratio) or ratio > 1e9:
        return math.inf
    n_az = math.ceil(ratio - 1e-9)
    return float(len(sweep.tilts) * n_az * sum(sweep.frames_per_pose_of(c) for c in sweep.lighting))


def planned_dark_count(sweep: Sweep) -> int:
    """Master darks: one per distinct exposure of the conditions used, a bracket's included (the gain
    is one per sweep)."""
    if sweep.dark.frames <= 0:
        return 0
    return len({t for c in sweep.lighting for t in sweep.pose_exposures(c).values()})


def estimate_bytes(sweep: Sweep, cfg: RigConfig, frames: int) -> int:
    """Bytes the session will need, from the counts (the same figures as
    :func:`m2s2hil.store.estimates.estimate_session_bytes`, which expands the plan)."""
    m = cfg.camera.model
    return frames * estimate_frame_bytes(cfg, sweep.processing) + planned_dark_count(sweep) * (
        m.width * m.height * 4 + 65536)


def check_size(sweep: Sweep, max_plan_frames: int) -> int:
    """The frames a sweep asks for, counted without expanding it; :class:`PlanTooLarge` above
    ``max_plan_frames``. Every endpoint that expands a plan asks this first."""
    n = planned_frame_count(sweep)
    if n > max_plan_frames:
        shown = "too many" if math.isinf(n) else f"{int(n)}"
        raise PlanTooLarge(
            f"the sweep asks for {shown} frames; this daemon accepts at most {max_plan_frames} "
            "per session (raise azimuth_step_deg, or lower frames_per_pose, lighting or tilts)"
        )
    return int(n)


def check_sweep(sweep: Sweep, cfg: RigConfig, max_plan_frames: int, root: Path | None = None
                ) -> tuple[int, int]:
    """(planned events, bytes the session will need); :class:`PlanTooLarge`, ``UsageError``,
    :class:`DiskFull` (when ``root`` is given and lacks the room) or ``PlanError`` (the rig
    cannot do it) otherwise. Everything but the last is decided before expanding."""
    n = check_size(sweep, max_plan_frames)
    try:
        check_method(sweep.processing)
    except UsageError as exc:
        raise UsageError(f"body.processing: {exc}") from None
    need = estimate_bytes(sweep, cfg, n)
    if root is not None:
        check_room(root, need)
    with EXPANDING:
        events = sweep.expand(cfg)  # PlanError (422) when the rig cannot do it
    return len(events), need


def check_room(root: Path, need: int) -> None:
    """Create the data root if needed; :class:`DiskFull` when it lacks ``need`` bytes."""
    root.mkdir(parents=True, exist_ok=True)
    try:
        check_free_space(root, need)
    except DiskFull as exc:
        raise DiskFull("the data root", needed=exc.needed, free=exc.free) from None
