"""The duration model of a plan: how long its events take on a rig, and the physics floor.

Stop-and-go (:func:`estimate`): a trapezoidal velocity profile per axis
(``t = 2·sqrt(d/a)`` if ``d < v²/a`` else ``d/v + v/a``), settle after each move,
exposure + readout (1/max_fps) per frame, lamp warm-up per switch (only lamps that
were off need to warm up), dark frames. The lower bound keeps only physics: both axes
moving together, lamps warming while the stage moves, no settling. Continuous rotation
(:func:`estimate_continuous`): one constant-ω sweep per pass from rest where the last pass's
turntable stopped (the snake turns back, no repositioning); the next lamps warm while it brakes,
the tilt moves after it stops, and the run-up is timed to end as lamps and tilt are ready.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING

from pydantic import Field

from m2s2hil.config import AxisConfig, RigConfig
from m2s2hil.errors import UsageError
from m2s2hil.plan.model import CaptureEvent, PlanModel
from m2s2hil.simulators.motion_kit import rest_to_rest_s

if TYPE_CHECKING:
    from m2s2hil.plan.sweep import Sweep


def turntable_range(rig: RigConfig) -> tuple[float, float]:
    """Commandable turntable angles: the soft limits intersected with the cable-wrap limit."""
    ax = rig.axes["turntable"]
    lo, hi = ax.min_deg, ax.max_deg
    if ax.cable_wrap_limit_deg is not None:
        lo, hi = max(lo, -ax.cable_wrap_limit_deg), min(hi, ax.cable_wrap_limit_deg)
    return lo, hi


def move_time_s(distance_deg: float, axis: AxisConfig) -> float:
    """Point-to-point time of a trapezoidal (or triangular) velocity profile: the very profile
    the simulated GRBL and Zaber controllers move by, as the firmware and the vendor's
    protocol manual document it (:func:`m2s2hil.simulators.motion_kit.rest_to_rest_s`, whose
    docstring cites them), so the plan and the virtual clock cannot drift apart."""
    d = abs(distance_deg)
    if d <= 0:
        return 0.0
    return rest_to_rest_s(d, axis.max_speed_dps, axis.accel_dps2)


def rest_to_speed_s(distance_deg: float, speed_dps: float, accel_dps2: float) -> float:
    """Time from rest to cover ``distance_deg`` accelerating at ``accel_dps2`` up to ``speed_dps``
    (the continuous run-up; the same profile as ``engine.marks.reach_s``)."""
    d, v = max(0.0, distance_deg), abs(speed_dps)
    ramp = v * v / (2 * accel_dps2)
    return math.sqrt(2 * d / accel_dps2) if d <= ramp else v / accel_dps2 + (d - ramp) / v


def switch_warmup_s(rig: RigConfig, previous: str | None, new: str) -> float:
    """Warm-up after switching lighting from ``previous`` to ``new``: only lamps that were
    off need to stabilise (a lamp that stays on is already warm)."""
    was_on = set(rig.lighting[previous]) if previous else set()
    return max((rig.lamps[n].warmup_s for n in rig.lighting[new] if n not in was_on), default=0.0)


class PlanEstimate(PlanModel):
    total_s: float
    lower_bound_s: float  # the stop-and-go floor of this order (see estimate)
    breakdown: dict[str, float]  # seconds per component of total_s
    counts: dict[str, int] = Field(default_factory=dict)
    #: The least rig time of any mode (m2s2hil.plan.floor), when the caller computed it.
    physical_floor_s: float | None = None


def _settle(ev: CaptureEvent, rig: RigConfig, moved: Iterable[str]) -> float:
    moved = list(moved)
    if not moved:
        return 0.0
    if ev.settle_s is not None:
        return ev.settle_s
    return max(rig.axes[m].settle_s for m in moved)


def estimate(events: Sequence[CaptureEvent], rig: RigConfig, *,
             start_pose: tuple[float, float] = (0.0, 0.0), parallel_axes: bool = False,
             overlap: bool = False) -> PlanEstimate:
    """Duration of a stop-and-go event list from ``start_pose`` (turntable, tilt).

    ``total_s`` models the engine: axes moved one after the other unless
    ``parallel_axes``, then settle, then lamp warm-up, then exposure + readout.
    ``lower_bound_s`` is the physics floor of the same order: axes in parallel, warm-up
    overlapping the move, no settle.

    ``overlap`` models the overlapped engine (``EngineOptions.overlap``): the move to the
    next pose starts when an exposure ends, so a frame's readout runs during the next move;
    the lamps switch once the frame is read, so their warm-up runs from the end of the
    readout, alongside the rest of the move. Only the readout no move hides is counted.
    """
    tt, tl = rig.axes["turntable"], rig.axes["tilt"]
    readout = 1.0 / rig.camera.model.max_fps
    pos = {"turntable": start_pose[0], "tilt": start_pose[1]}
    light: str | None = None
    b = dict(motion=0.0, settle=0.0, warmup=0.0, exposure=0.0, readout=0.0, dark=0.0)
    lower = 0.0
    carry = 0.0  # overlap: the last frame's readout, still under way when the next move starts
    n = dict(frames=0, darks=0, dark_frames=0, moves=0, switches=0)
    for ev in events:
        if ev.kind == "dark":
            t = ev.n_frames * (ev.exposure_s + readout) + carry
            b["dark"] += t
            lower += t
            carry = 0.0
            n["darks"] += 1
            n["dark_frames"] += ev.n_frames
            continue
        assert ev.azimuth_deg is not None and ev.tilt_deg is not None and ev.lighting is not None
        d_tt = ev.azimuth_deg - pos["turntable"]
        d_tl = ev.tilt_deg - pos["tilt"]
        t_tt, t_tl = move_time_s(d_tt, tt), move_time_s(d_tl, tl)
        moved = [a for a, d in (("turntable", d_tt), ("tilt", d_tl)) if abs(d) > 1e-9]
        move = max(t_tt, t_tl) if parallel_axes else t_tt + t_tl
        warm = 0.0
        if ev.lighting != light:
            warm = switch_warmup_s(rig, light, ev.lighting)
            light = ev.lighting
            n["switches"] += 1
        settle = _settle(ev, rig, moved)
        b["motion"] += move
        b["settle"] += settle
        b["exposure"] += ev.exposure_s
        if overlap:
            base = move + settle
            b["readout"] += max(0.0, carry - base)  # the part of the last readout no move hid
            b["warmup"] += max(0.0, carry + warm - max(base, carry))
            lower += max(max(t_tt, t_tl), carry + warm, carry) + ev.exposure_s
            carry = readout
        else:
            b["warmup"] += warm
            b["readout"] += readout
            lower += max(max(t_tt, t_tl), warm) + ev.exposure_s + readout
        n["frames"] += 1
        n["moves"] += bool(moved)
        pos["turntable"], pos["tilt"] = ev.azimuth_deg, ev.tilt_deg
    b["readout"] += carry  # the last frame's
    lower += carry
    total = sum(b.values())
    return PlanEstimate(total_s=total, lower_bound_s=min(lower, total), breakdown=b, counts=n)


class ContinuousEstimate(PlanModel):
    """Continuous rotation: the turntable sweeps each pass at a constant ω while the camera
    streams, and the frame nearest each nominal azimuth is kept."""

    omega_dps: dict[str, float]  # per lighting condition
    frame_interval_s: dict[str, float]
    blur_deg: dict[str, float]  # ω · t_exp
    blur_px: dict[str, float]  # at radius_px from the rotation axis
    runup_deg: dict[str, float]  # ω²/2a before the first and after the last azimuth
    within_cable_limit: bool
    total_s: float
    lower_bound_s: float
    breakdown: dict[str, float]

    def as_plan_estimate(self, physical_floor_s: float | None = None) -> PlanEstimate:
        return PlanEstimate(total_s=self.total_s, lower_bound_s=self.lower_bound_s, breakdown=self.breakdown,
                            physical_floor_s=physical_floor_s)


def estimate_continuous(sweep: Sweep, rig: RigConfig, *, radius_px: float,
                        max_blur_px: float | None = None,
                        events: Sequence[CaptureEvent] | None = None,
                        speed_dps: float | None = None,
                        start_pose_deg: float = 0.0) -> ContinuousEstimate:
    """ω per condition: as fast as the turntable allows, but one azimuth step must take at
    least ``frames_per_pose`` frame intervals (frame interval = max(1/max_fps, exposure))
    and, if given, the blur at ``radius_px`` must stay under ``max_blur_px``. ``speed_dps``
    fixes ω for every condition instead (the engine's speed override)."""
    if radius_px <= 0:
        raise UsageError(f"radius_px must be positive, not {radius_px}")
    tt, tl = rig.axes["turntable"], rig.axes["tilt"]
    fps = rig.camera.model.max_fps
    step = sweep.azimuth_step_deg
    omega: dict[str, float] = {}
    interval: dict[str, float] = {}
    blur_deg: dict[str, float] = {}
    blur_px: dict[str, float] = {}
    runup: dict[str, float] = {}
    for c in sweep.lighting:
        exp = sweep.exposure_for(c)
        fi = max(1.0 / fps, exp)
        w = min(tt.max_speed_dps, step / (sweep.frames_per_pose * fi))
        if max_blur_px is not None:
            w = min(w, math.degrees(max_blur_px / radius_px) / exp)
        if speed_dps is not None:
            w = speed_dps
        omega[c], interval[c] = w, fi
        blur_deg[c] = w * exp
        blur_px[c] = radius_px * math.radians(blur_deg[c])
        runup[c] = w * w / (2 * tt.accel_dps2)
    if events is None:
        events = sweep.expand(rig)
    lo, hi = turntable_range(rig)
    a = tt.accel_dps2
    b = dict(motion=0.0, sweep=0.0, braking=0.0, settle=0.0, warmup=0.0, dark=0.0)
    lower = 0.0
    for ev in events:
        if ev.kind == "dark":
            t = ev.n_frames * (ev.exposure_s + 1.0 / fps)
            b["dark"] += t
            lower += t
    passes: dict[int, list[CaptureEvent]] = {}
    for ev in events:
        if ev.kind == "frame":
            passes.setdefault(ev.pass_index, []).append(ev)
    # The engine (engine/continuous_steps, marks.run_pass), timed from the moment the last pass's
    # last frame is read: the next lamps switch then and warm while the turntable brakes (ω/a);
    # then the tilt moves and settles; the turntable turns back from where it came to rest when
    # that lies before the first mark (else it repositions to ramp + match window before it); its
    # rotation is timed so the first frame a mark may keep begins once lamps and tilt are ready.
    rest_tt, pos_tl = start_pose_deg, 0.0
    w_prev: float | None = None
    light: str | None = None
    within = True
    for p in sorted(passes):
        evs = passes[p]
        c = evs[0].lighting
        assert c is not None and evs[0].azimuth_deg is not None and evs[0].tilt_deg is not None
        w, fi = omega[c], interval[c]
        a0, a1 = evs[0].azimuth_deg, evs[-1].azimuth_deg
        direction = 1.0 if a1 >= a0 else -1.0
        window = min(step / 2, max(0.1, 1.5 * w * fi))  # SpeedSettings.match_window's default
        brake = w_prev / a if w_prev is not None else 0.0
        warm = switch_warmup_s(rig, light, c) if c != light else 0.0
        light = c
        t_tl = move_time_s(evs[0].tilt_deg - pos_tl, tl)
        settle = _settle(evs[0], rig, ["tilt"] if t_tl > 0 else [])
        dist = direction * (a0 - rest_tt)
        t_tt = 0.0
        if dist < 0:  # rest beyond the first mark: reposition to the run-up's start
            dist = runup[c] + window
            t_tt = move_time_s(a0 - direction * dist - rest_tt, tt)
        if min(a0 - direction * dist, a0) < lo - 1e-9 or max(a0 - direction * dist, a0) > hi + 1e-9:
            within = False
        ready = max(brake + t_tl + settle, warm)  # tilt settled, lamps warm
        now = brake + t_tl + t_tt  # the turntable may start turning
        # The rotation starts ``lead`` before the first keepable frame (the first pass streams
        # first, so the rotation starts once ready).
        lead = max(0.0, rest_to_speed_s(dist - window, w, a) - sweep.exposure_for(c)) if p else 0.0
        rot = max(now, ready - lead)
        wait = rot - now
        b["braking"] += brake
        b["motion"] += t_tl + t_tt
        b["settle" if brake + t_tl + settle >= warm else "warmup"] += wait
        # run-up, the span, the k-1 further frames of the last mark, and the frame past it whose
        # read-out completes the mark (the overrun)
        overrun = 2 * fi + 1.0 / fps
        b["sweep"] += rest_to_speed_s(dist + abs(a1 - a0), w, a) + (sweep.frames_per_pose - 1) * fi + overrun
        lower += max(t_tl, warm, brake + rest_to_speed_s(dist, w, a)) + abs(a1 - a0) / w \
            + (sweep.frames_per_pose - 1) * fi
        rest_tt = a1 + direction * (w * overrun + runup[c])
        if rest_tt < lo - 1e-9 or rest_tt > hi + 1e-9:
            within = False
        pos_tl, w_prev = evs[0].tilt_deg, w
    b["braking"] += (w_prev / a) if w_prev is not None else 0.0  # the last stop: the rig left safe
    total = sum(b.values())
    return ContinuousEstimate(
        omega_dps=omega, frame_interval_s=interval, blur_deg=blur_deg, blur_px=blur_px, runup_deg=runup,
        within_cable_limit=within, total_s=total, lower_bound_s=min(lower, total), breakdown=b,
    )
