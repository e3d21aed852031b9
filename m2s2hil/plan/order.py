"""The order search: which nesting of the sweep's loops, and which order of its lighting
conditions and tilts, the duration model finds cheapest.

With ``axis_order="auto"`` every nesting of the three loops (light, tilt, azimuth) and the
order of lighting conditions and tilts are scored with :func:`~m2s2hil.plan.estimate.estimate`
(continuous sweeps: :func:`~m2s2hil.plan.estimate.estimate_continuous`, whose cost is the waits
a continuous run cannot hide: lamp warm-ups longer than a turn, turn-backs, tilt moves) and the
cheapest wins (ties go to the earlier candidate, so the choice is deterministic).
Inner loops run as a snake (boustrophedon): each pass runs the opposite way of the one
before, so the turntable goes 0→350 then 350→0 and never winds its cables past
``cable_wrap_limit_deg``. Dark frames come first (lens cap on).
"""

from __future__ import annotations

import itertools
import threading
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

from m2s2hil.config import RigConfig
from m2s2hil.plan.estimate import estimate, estimate_continuous, turntable_range
from m2s2hil.plan.floor import PhysicalFloor, physical_floor
from m2s2hil.plan.model import (
    AXES,
    DEFAULT_AXIS_ORDER,
    CaptureEvent,
    PlanError,
    dark_event,
    dark_event_id,
    frame_event_id,
)

if TYPE_CHECKING:
    from m2s2hil.plan.sweep import Sweep


def commanded_azimuths(nominal: Sequence[float], rig: RigConfig) -> list[float]:
    """Turntable angles for the nominal azimuths of one ascending pass.

    Prefer one contiguous run (start, start+step, ...) shifted by whole turns to fit the
    allowed range, nearest zero; if the range is narrower than the pass, unwind once where
    needed. A nominal azimuth with no representative in range is a PlanError.
    """
    lo, hi = turntable_range(rig)
    eps = 1e-9
    if not nominal:
        return []
    base = nominal[0]
    unwrapped = [base]
    for a in nominal[1:]:
        step = (a - unwrapped[-1]) % 360.0
        unwrapped.append(unwrapped[-1] + step)
    span = unwrapped[-1] - unwrapped[0]
    shifts = [m * 360.0 for m in range(-3, 4)]
    fits = [s for s in shifts if base + s >= lo - eps and base + s + span <= hi + eps]
    if fits:
        s = min(fits, key=lambda s: (abs(base + s + span / 2), s))
        return [round(u + s, 6) for u in unwrapped]
    out: list[float] = []
    for a in nominal:
        cands = sorted(a + s for s in shifts if lo - eps <= a + s <= hi + eps)
        if not cands:
            raise PlanError(
                "sweep", "azimuth_step_deg",
                f"azimuth {a:g} deg cannot be reached within the turntable range [{lo:g}, {hi:g}] deg "
                "(soft limits and cable-wrap limit)",
            )
        if not out:
            pick = min(cands, key=abs)
        else:
            up = [c for c in cands if c >= out[-1]]
            pick = up[0] if up else cands[0]
        out.append(round(pick, 6))
    return out


def _snake(seq: Sequence, forward: bool) -> list:
    return list(seq) if forward else list(reversed(seq))


class _Step(NamedTuple):
    """A candidate event, cheap to build while ~100 orderings are scored (duck-types the
    fields :func:`estimate` reads)."""

    kind: str
    lighting: str | None
    elevation: str | None
    tilt_deg: float | None
    azimuth_deg: float | None
    nominal_azimuth_deg: float | None
    azimuth_index: int | None
    frame: int
    n_frames: int
    exposure_s: float
    dark_id: str | None
    settle_s: float | None
    pass_index: int
    exposure_factor: float = 1.0


def _build_steps(sweep: Sweep, rig: RigConfig, order: Sequence[str], lights: Sequence[str],
                 tilts: Sequence[str]) -> list[_Step]:
    nominal = sweep.azimuths()
    commanded = commanded_azimuths(nominal, rig)
    values = {"light": list(lights), "tilt": list(tilts), "azimuth": list(range(len(nominal)))}
    out: list[_Step] = []
    # condition -> (factor, exposure, dark id) of each frame of a pose: its own, then its bracket's
    shots = {c: [(f, t, dark_event_id(t, sweep.gain) if sweep.dark.frames > 0 else None)
                 for f, t in sweep.pose_exposures(c).items()] for c in lights}
    if sweep.dark.frames > 0:
        for e in sorted({t for per in shots.values() for _, t, _ in per}):
            out.append(_Step("dark", None, None, None, None, None, None, 0, sweep.dark.frames, e, None,
                             None, 0))
    # Nested loops with a snake: a loop runs backwards every other time it restarts.
    n_mid = 0
    pass_index = -1
    last_pass_key: tuple | None = None
    for i0, v0 in enumerate(values[order[0]]):
        for v1 in _snake(values[order[1]], i0 % 2 == 0):
            n_mid += 1
            for v2 in _snake(values[order[2]], n_mid % 2 == 1):
                pick = dict(zip(order, (v0, v1, v2), strict=True))
                cond, elev, ai = pick["light"], pick["tilt"], pick["azimuth"]
                key = (cond, elev) if order[2] == "azimuth" else (v0, v1)
                if key != last_pass_key:
                    pass_index += 1
                    last_pass_key = key
                for k in range(sweep.frames_per_pose):
                    for f, exp, did in shots[cond]:
                        out.append(_Step("frame", cond, elev, rig.elevations[elev], commanded[ai],
                                         nominal[ai], ai, k, 1, exp, did, sweep.settle_s, pass_index, f))
    return out


def _materialise(sweep: Sweep, steps: Sequence[_Step]) -> list[CaptureEvent]:
    out = []
    for i, st in enumerate(steps):
        if st.kind == "dark":
            out.append(dark_event(st.exposure_s, sweep.gain, st.n_frames, index=i))
            continue
        assert st.lighting and st.elevation and st.nominal_azimuth_deg is not None
        out.append(CaptureEvent(
            event_id=frame_event_id(st.lighting, st.elevation, st.nominal_azimuth_deg, st.frame,
                                    st.exposure_factor),
            index=i, kind="frame", lighting=st.lighting, elevation=st.elevation, tilt_deg=st.tilt_deg,
            azimuth_deg=st.azimuth_deg, nominal_azimuth_deg=st.nominal_azimuth_deg,
            azimuth_index=st.azimuth_index, frame=st.frame, exposure_s=st.exposure_s, gain=sweep.gain,
            auto_exposure=sweep.auto_exposure, dark_id=st.dark_id, settle_s=st.settle_s,
            pass_index=st.pass_index, exposure_factor=st.exposure_factor,
        ))
    return out


_PLAN_CACHE: OrderedDict[tuple[str, str], tuple[tuple[CaptureEvent, ...], str]] = OrderedDict()
_FLOOR_CACHE: OrderedDict[tuple[str, str], PhysicalFloor] = OrderedDict()
_PLAN_CACHE_SIZE = 16
_PLAN_LOCK = threading.Lock()


def _cached(cache: OrderedDict, sweep: Sweep, rig: RigConfig, compute: Callable[[], Any]) -> Any:
    # Scoring ~100 candidate orders takes a fraction of a second; the engine, store and API
    # all expand the same sweep, so keep the last few results (events are frozen).
    key = (sweep.model_dump_json(), rig.digest)
    with _PLAN_LOCK:
        hit = cache.get(key)
        if hit is not None:
            cache.move_to_end(key)
    if hit is None:
        hit = compute()
        with _PLAN_LOCK:
            cache[key] = hit
            while len(cache) > _PLAN_CACHE_SIZE:
                cache.popitem(last=False)
    return hit


def best_plan(sweep: Sweep, rig: RigConfig) -> tuple[list[CaptureEvent], str]:
    def compute() -> tuple[tuple[CaptureEvent, ...], str]:
        events, order = _search_plan(sweep, rig)
        return tuple(events), order

    hit = _cached(_PLAN_CACHE, sweep, rig, compute)
    return list(hit[0]), hit[1]


def sweep_floor(sweep: Sweep, rig: RigConfig) -> PhysicalFloor:
    """The sweep's physical floor: the least of :func:`physical_floor` over every nesting and
    condition/tilt order the search knows, whatever the sweep's own order settings (so no
    capture of these frames on this rig can take less). Computed when asked, then cached."""
    def compute() -> PhysicalFloor:
        floors = (physical_floor(steps, rig) for _o, steps in _candidates(sweep, rig, every=True))  # type: ignore[arg-type]
        return min(floors, key=lambda f: f.total_s)

    return _cached(_FLOOR_CACHE, sweep, rig, compute)


def _candidates(sweep: Sweep, rig: RigConfig, *, every: bool = False) -> Iterator[tuple[str, list[_Step]]]:
    """The candidate event lists: loop nestings x condition orders x tilt orders (only those
    the sweep allows unless ``every``)."""
    if sweep.axis_order == "auto" or every:
        orders = [o for o in itertools.permutations(AXES)
                  if every or sweep.mode != "continuous" or o[2] == "azimuth"]
        # Listed first = preferred on ties: the paper's nesting.
        orders.sort(key=lambda o: ">".join(o) != DEFAULT_AXIS_ORDER)
    else:
        orders = [tuple(sweep.axis_order.split(">"))]
    if sweep.reorder or every:
        light_orders = list(itertools.permutations(sweep.lighting))
        by_angle = sorted(sweep.tilts, key=lambda e: rig.elevations[e])
        tilt_orders = [list(sweep.tilts)] + [t for t in (by_angle, by_angle[::-1]) if t != list(sweep.tilts)]
    else:
        light_orders = [tuple(sweep.lighting)]
        tilt_orders = [list(sweep.tilts)]
    for order in orders:
        for lights in light_orders:
            for tilts in tilt_orders:
                yield ">".join(order), _build_steps(sweep, rig, order, lights, tilts)


def _search_plan(sweep: Sweep, rig: RigConfig) -> tuple[list[CaptureEvent], str]:
    best: tuple[float, list[_Step], str] | None = None
    for order, steps in _candidates(sweep, rig):
        if sweep.mode == "continuous":  # the waits a continuous run cannot hide (warm-ups, turns, tilt)
            cost = estimate_continuous(sweep, rig, radius_px=400.0, events=steps).total_s  # type: ignore[arg-type]
        else:
            cost = estimate(steps, rig).total_s  # type: ignore[arg-type]
        if best is None or cost < best[0] - 1e-9:
            best = (cost, steps, order)
    assert best is not None
    return _materialise(sweep, best[1]), best[2]
