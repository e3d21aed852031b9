"""The physical floor of a sweep: the least rig time any capture mode can take on this rig.

:func:`estimate`'s ``lower_bound_s`` is a stop-and-go floor (every frame at a standstill,
a trapezoidal move between neighbours). This one keeps only what physics imposes whatever
the mode, so it is also the yardstick of overlapped stop-and-go and continuous rotation:

- the camera: every frame occupies the sensor for ``max(exposure, 1/max_fps)`` (a global
  shutter exposes the next frame while the last is read out, so the period is the longer of
  the two);
- the turntable: between the first and last frame of a pass (one lighting, one tilt) it must
  travel the pass's path at no more than ``max_speed_dps``; between passes it must cover the
  distance to the next pass's first azimuth at no more than that speed (from rest at the start);
- the tilt: it stands still while frames are taken, so each tilt change is a rest-to-rest
  trapezoidal move (:func:`move_time_s`);
- the lamps: a lamp switched on must be warm before the next frame and may not be on during
  the previous condition's frames, so a switch's warm-up fills the gap between two passes;
  it overlaps the tilt and turntable moves of that gap (the gap is the longest of the three);
- the darks: lens-capped frames at the camera's rate, taken while the stage moves to the first
  pose and the first lamps warm.

A real run adds what this leaves out (acceleration within a pass, settling, the read-back's
confirmation), so ``physical_floor_s <= lower_bound_s`` and the engine's efficiency
measured against it says how much of the rig time physics did not require.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

from m2s2hil.config import AxisConfig, RigConfig
from m2s2hil.plan.estimate import move_time_s, switch_warmup_s
from m2s2hil.plan.model import CaptureEvent, PlanModel


class PhysicalFloor(PlanModel):
    """The floor and what it is made of (seconds): ``frames`` and ``sweep`` are the passes
    (the longer of the two counts per pass), ``gaps`` the transitions between passes."""

    total_s: float
    passes: int
    breakdown: dict[str, float]


def reach_time_s(distance_deg: float, axis: AxisConfig) -> float:
    """Least time to cover ``distance_deg`` from rest, not stopping at the end (the axis may
    arrive at full speed): accelerate at ``accel_dps2`` up to ``max_speed_dps``."""
    d = abs(distance_deg)
    v, a = axis.max_speed_dps, axis.accel_dps2
    if d <= v * v / (2 * a):
        return math.sqrt(2 * d / a)
    return d / v + v / (2 * a)


def frame_period_s(exposure_s: float, rig: RigConfig) -> float:
    return max(exposure_s, 1.0 / rig.camera.model.max_fps)


def physical_floor(events: Sequence[CaptureEvent], rig: RigConfig, *,
                   start_pose: tuple[float, float] = (0.0, 0.0)) -> PhysicalFloor:
    """The floor of ``events`` in their order (see the module docstring); a pass is a run of
    consecutive frames with the same lighting and tilt."""
    tt, tl = rig.axes["turntable"], rig.axes["tilt"]
    darks = sum(ev.n_frames * frame_period_s(ev.exposure_s, rig) for ev in events if ev.kind == "dark")
    frames = [ev for ev in events if ev.kind == "frame"]
    runs: list[list[CaptureEvent]] = []
    for ev in frames:
        if runs and (runs[-1][-1].lighting, runs[-1][-1].tilt_deg) == (ev.lighting, ev.tilt_deg):
            runs[-1].append(ev)
        else:
            runs.append([ev])
    b = dict(darks_and_first_move=0.0, frames=0.0, sweep=0.0, gaps=0.0)
    pos_tt, pos_tl = start_pose
    light: str | None = None
    for i, run in enumerate(runs):
        first = run[0]
        assert first.azimuth_deg is not None and first.tilt_deg is not None and first.lighting is not None
        warm = switch_warmup_s(rig, light, first.lighting)
        tilt = move_time_s(first.tilt_deg - pos_tl, tl)
        if i == 0:
            b["darks_and_first_move"] = max(darks, warm, tilt, reach_time_s(first.azimuth_deg - pos_tt, tt))
        else:
            b["gaps"] += max(warm, tilt, abs(first.azimuth_deg - pos_tt) / tt.max_speed_dps)
        path = sum(abs(b_.azimuth_deg - a_.azimuth_deg)  # type: ignore[operator]
                   for a_, b_ in itertools.pairwise(run))
        t_frames = sum(frame_period_s(ev.exposure_s, rig) for ev in run)
        t_sweep = path / tt.max_speed_dps
        # The pass lasts as long as the slower of the two; count it once, under its cause.
        b["frames" if t_frames >= t_sweep else "sweep"] += max(t_frames, t_sweep)
        last = run[-1]
        assert last.azimuth_deg is not None
        pos_tt, pos_tl, light = last.azimuth_deg, first.tilt_deg, first.lighting
    if not runs:
        b["darks_and_first_move"] = darks
    return PhysicalFloor(total_s=sum(b.values()), passes=len(runs), breakdown=b)
