"""Capture plans as data: a serialisable :class:`Sweep` that expands to capture events.

A sweep names what to capture (satellite, build, lighting conditions, elevations,
azimuth grid, frames per pose) and how (exposure policy, gain, settle, dark policy,
processing method, loop nesting, stop-and-go or continuous rotation). It validates
against the catalog, round-trips through JSON, and :meth:`Sweep.expand` turns it into
a deterministic list of frozen :class:`CaptureEvent` objects, each with a stable
``event_id`` so a resumed session can skip what it already has.

Ordering is cost-aware: with ``axis_order="auto"`` every nesting of the three loops
(light, tilt, azimuth) and the order of lighting conditions and tilts are scored with
the duration model and the cheapest wins (ties go to the earlier candidate, so the
choice is deterministic). Inner loops run as a snake (boustrophedon): each pass runs
the opposite way of the one before, so the turntable goes 0→350 then 350→0 and never
winds its cables past ``cable_wrap_limit_deg``. Dark frames come first (lens cap on),
one master dark per distinct (exposure, gain), and frame events point at theirs.

Duration model (:func:`estimate`): a trapezoidal velocity profile per axis
(``t = 2·sqrt(d/a)`` if ``d < v²/a`` else ``d/v + v/a``), settle after each move,
exposure + readout (1/max_fps) per frame, lamp warm-up per switch (only lamps that
were off need to warm up), dark frames. The lower bound keeps only physics: both axes
moving together, lamps warming while the stage moves, no settling.
"""

from __future__ import annotations

import itertools
import json
import math
import threading
from collections import OrderedDict
from collections.abc import Iterable, Sequence
from typing import Annotated, Any, Literal, NamedTuple

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from m2s2hil.catalog import load_catalog
from m2s2hil.config import AxisConfig, RigConfig
from m2s2hil.errors import CatalogError, KeyedError, UsageError, validation_problem

# Starting exposures per condition (seconds): strong diffuse has ~1.7x the light of
# weak diffuse; the spotlight is brighter still on the lit side of the mockup.
DEFAULT_EXPOSURE_S: dict[str, float] = {"weak": 0.008, "strong": 0.005, "directional": 0.003}
MIN_EXPOSURE_S = 100e-6  # TOUCAN limits (paper, 2.1)
MAX_EXPOSURE_S = 5.0
AXES = ("light", "tilt", "azimuth")
DEFAULT_AXIS_ORDER = "light>tilt>azimuth"


class PlanError(KeyedError):
    """A sweep that cannot be used: ``source`` names where it came from, ``key`` the field."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


Seconds = Annotated[float, Field(ge=MIN_EXPOSURE_S, le=MAX_EXPOSURE_S)]


def _condition_key(name: str) -> str:
    # Any case, and the published release's names (solo, all, dir -> weak, strong, directional).
    try:
        return load_catalog().light(str(name)).key
    except CatalogError as exc:
        raise ValueError(str(exc)) from None


def _round_exposure(s: float) -> float:
    # Exposures are planned to the microsecond so darks can be matched exactly.
    return round(float(s), 6)


class FixedExposure(_Model):
    """One exposure per lighting condition; conditions left out get the default."""

    mode: Literal["fixed"] = "fixed"
    seconds: dict[str, Seconds] = Field(default_factory=lambda: dict(DEFAULT_EXPOSURE_S))

    @field_validator("seconds")
    @classmethod
    def _fill(cls, v: dict[str, float]) -> dict[str, float]:
        out = dict(DEFAULT_EXPOSURE_S)
        for k, s in v.items():
            out[_condition_key(k)] = _round_exposure(s)
        return out


class AutoExposureSettings(_Model):
    """Meter each pose: aim the ``percentile`` of the raw mosaic at ``target_fraction``
    of full scale. ``start_s`` are the first guesses (also used to plan the darks)."""

    mode: Literal["auto"] = "auto"
    target_fraction: Annotated[float, Field(gt=0, le=1)] = 0.9
    percentile: Annotated[float, Field(gt=0, le=100)] = 99.9
    start_s: dict[str, Seconds] = Field(default_factory=lambda: dict(DEFAULT_EXPOSURE_S))
    min_s: Seconds = MIN_EXPOSURE_S
    max_s: Seconds = 1.0
    max_iterations: Annotated[int, Field(ge=1, le=20)] = 4

    @field_validator("start_s")
    @classmethod
    def _fill(cls, v: dict[str, float]) -> dict[str, float]:
        out = dict(DEFAULT_EXPOSURE_S)
        for k, s in v.items():
            out[_condition_key(k)] = _round_exposure(s)
        return out

    @model_validator(mode="after")
    def _range(self) -> AutoExposureSettings:
        if self.min_s > self.max_s:
            raise ValueError(f"min_s ({self.min_s}) is above max_s ({self.max_s})")
        return self


class DarkPolicy(_Model):
    """Master darks: ``frames`` lens-capped frames reduced by ``reduce``, one master per
    distinct (exposure, gain), reused by every frame with that setting. ``frames = 0``
    turns dark subtraction off."""

    frames: Annotated[int, Field(ge=0, le=256)] = 8
    reduce: Literal["mean", "median"] = "mean"


class CaptureEvent(_Model):
    """One step of a sweep. ``kind == "dark"``: take ``n_frames`` lens-capped frames at
    ``exposure_s``/``gain`` and store their master as ``event_id``. ``kind == "frame"``:
    switch to ``lighting``, move to (``azimuth_deg``, ``tilt_deg``), settle, take one
    frame, subtract the master dark ``dark_id``."""

    event_id: str
    index: int
    kind: Literal["dark", "frame"]
    lighting: str | None = None
    elevation: str | None = None
    tilt_deg: float | None = None
    azimuth_deg: float | None = None  # commanded turntable angle (cable-wrap aware)
    nominal_azimuth_deg: float | None = None  # 0 <= a < 360
    azimuth_index: int | None = None  # position in the azimuth grid (0..35 for 10 deg)
    frame: int = 0  # k-th frame at this pose
    n_frames: int = 1
    exposure_s: float
    gain: float
    auto_exposure: bool = False  # exposure_s is only the starting guess
    dark_id: str | None = None
    settle_s: float | None = None  # None: the rig's per-axis settle_s
    pass_index: int = 0  # which snake pass (run of azimuths at one light + tilt)


def dark_event_id(exposure_s: float, gain: float) -> str:
    return f"dark/{round(exposure_s * 1e6):d}us/g{gain:g}"


def dark_event(exposure_s: float, gain: float, n_frames: int, index: int = -1) -> CaptureEvent:
    """A dark event outside the plan (e.g. for an exposure found by auto-exposure)."""
    exposure_s = _round_exposure(exposure_s)
    return CaptureEvent(
        event_id=dark_event_id(exposure_s, gain), index=index, kind="dark",
        exposure_s=exposure_s, gain=gain, n_frames=n_frames,
    )


def _az_label(a: float) -> str:
    return f"az{round(a):03d}" if abs(a - round(a)) < 1e-9 else f"az{a:07.3f}"


def frame_event_id(lighting: str, elevation: str, nominal_azimuth_deg: float, frame: int) -> str:
    return f"{lighting}/{elevation}/{_az_label(nominal_azimuth_deg)}/f{frame}"


class Sweep(_Model):
    """A capture plan for one satellite build (see module docstring)."""

    satellite: str
    build: str
    lighting: list[str] = Field(default_factory=lambda: ["weak", "strong", "directional"], min_length=1)
    tilts: list[str] = Field(default_factory=lambda: ["E0", "E1", "E2"], min_length=1)
    # 0.01 deg (36,000 poses) bounds the grid in the schema too; the frame limit is checked apart.
    azimuth_step_deg: Annotated[float, Field(ge=0.01, le=360)] = 10.0
    azimuth_start_deg: Annotated[float, Field(ge=0, lt=360)] = 0.0
    frames_per_pose: Annotated[int, Field(ge=1, le=100)] = 1
    exposure: FixedExposure | AutoExposureSettings = Field(
        default_factory=FixedExposure, discriminator="mode"
    )
    gain: Annotated[float, Field(ge=0, le=48)] = 1.0
    settle_s: Annotated[float, Field(ge=0, le=60)] | None = None
    dark: DarkPolicy = DarkPolicy()
    processing: str = Field(default="superpixel", pattern=r"^[a-z][a-z0-9_-]*$")
    axis_order: str = "auto"
    reorder: bool = True  # choose the order of conditions and tilts by cost
    mode: Literal["stop-and-go", "continuous"] = "stop-and-go"

    @field_validator("satellite")
    @classmethod
    def _sat(cls, v: str) -> str:
        try:
            return load_catalog().satellite(v).key
        except CatalogError as exc:
            raise ValueError(str(exc)) from None

    @field_validator("build")
    @classmethod
    def _build(cls, v: str, info: ValidationInfo) -> str:
        sat = info.data.get("satellite")
        if sat is None:  # the satellite already failed; that error is enough
            return v
        try:
            return load_catalog().build(sat, v).key
        except CatalogError as exc:
            raise ValueError(str(exc)) from None

    @field_validator("lighting")
    @classmethod
    def _lighting(cls, v: list[str]) -> list[str]:
        keys = [_condition_key(x) for x in v]
        dup = sorted({k for k in keys if keys.count(k) > 1})
        if dup:
            raise ValueError(f"lighting condition listed twice: {', '.join(dup)}")
        return keys

    @field_validator("tilts")
    @classmethod
    def _tilts(cls, v: list[str]) -> list[str]:
        try:
            keys = [load_catalog().elevation(str(x)).key for x in v]
        except CatalogError as exc:
            raise ValueError(str(exc)) from None
        dup = sorted({k for k in keys if keys.count(k) > 1})
        if dup:
            raise ValueError(f"elevation listed twice: {', '.join(dup)}")
        return keys

    @field_validator("exposure", mode="before")
    @classmethod
    def _exposure_shorthand(cls, v: Any) -> Any:
        if isinstance(v, str):
            if v.strip().lower() == "auto":
                return {"mode": "auto"}
            raise ValueError(f"exposure must be 'auto' or a table condition -> seconds, not {v!r}")
        if isinstance(v, dict) and "mode" not in v:
            return {"mode": "fixed", "seconds": v}
        return v

    @field_validator("axis_order")
    @classmethod
    def _axis_order(cls, v: str) -> str:
        v = v.replace(" ", "").lower()
        if v == "auto":
            return v
        parts = v.split(">")
        if sorted(parts) != sorted(AXES):
            raise ValueError(
                f"axis_order {v!r} must be 'auto' or name light, tilt and azimuth once each, "
                "outermost first, e.g. 'light>tilt>azimuth'"
            )
        return v

    @model_validator(mode="after")
    def _modes(self) -> Sweep:
        order = self.axis_order
        if self.mode == "continuous" and order != "auto" and not order.endswith(">azimuth"):
            raise ValueError("continuous mode sweeps the turntable: azimuth must be the innermost axis")
        return self

    # ------------------------------------------------------------------ views
    @property
    def auto_exposure(self) -> bool:
        return isinstance(self.exposure, AutoExposureSettings)

    def exposure_for(self, condition: str) -> float:
        """The planned (fixed) or starting (auto) exposure of a condition."""
        exp = self.exposure
        table = exp.start_s if isinstance(exp, AutoExposureSettings) else exp.seconds
        return table[condition]

    def azimuths(self) -> list[float]:
        """Nominal azimuths, 0 <= a < 360, in grid order from ``azimuth_start_deg``."""
        n = math.ceil(360.0 / self.azimuth_step_deg - 1e-9)
        return [round((self.azimuth_start_deg + i * self.azimuth_step_deg) % 360.0, 6) for i in range(n)]

    def to_json(self) -> str:
        return self.model_dump_json(indent=2)

    @classmethod
    def from_json(cls, text: str, source: str = "<sweep json>") -> Sweep:
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise PlanError(source, "", f"not valid JSON: {exc}") from None
        return parse_sweep(data, source)

    # -------------------------------------------------------------- expansion
    def expand(self, rig: RigConfig) -> list[CaptureEvent]:
        """The events of this sweep in capture order (darks first). Deterministic."""
        return _best_plan(self, rig)[0]

    def chosen_order(self, rig: RigConfig) -> str:
        """The axis nesting :meth:`expand` uses (resolves ``"auto"``)."""
        return _best_plan(self, rig)[1]

    def estimate(self, rig: RigConfig, *, radius_px: float = 400.0) -> PlanEstimate:
        events = self.expand(rig)
        if self.mode == "continuous":
            return estimate_continuous(self, rig, radius_px=radius_px, events=events).as_plan_estimate()
        return estimate(events, rig)


def parse_sweep(data: Any, source: str = "<sweep>") -> Sweep:
    """Validate plain data into a :class:`Sweep`, turning pydantic errors into a PlanError."""
    try:
        return Sweep.model_validate(data)
    except ValidationError as exc:
        raise PlanError(source, *validation_problem(exc)) from None


# ---------------------------------------------------------------------- geometry
def turntable_range(rig: RigConfig) -> tuple[float, float]:
    """Commandable turntable angles: the soft limits intersected with the cable-wrap limit."""
    ax = rig.axes["turntable"]
    lo, hi = ax.min_deg, ax.max_deg
    if ax.cable_wrap_limit_deg is not None:
        lo, hi = max(lo, -ax.cable_wrap_limit_deg), min(hi, ax.cable_wrap_limit_deg)
    return lo, hi


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


def move_time_s(distance_deg: float, axis: AxisConfig) -> float:
    """Point-to-point time of a trapezoidal (or triangular) velocity profile."""
    d = abs(distance_deg)
    if d <= 0:
        return 0.0
    v, a = axis.max_speed_dps, axis.accel_dps2
    if d < v * v / a:
        return 2.0 * math.sqrt(d / a)
    return d / v + v / a


def switch_warmup_s(rig: RigConfig, previous: str | None, new: str) -> float:
    """Warm-up after switching lighting from ``previous`` to ``new``: only lamps that were
    off need to stabilise (a lamp that stays on is already warm)."""
    was_on = set(rig.lighting[previous]) if previous else set()
    return max((rig.lamps[n].warmup_s for n in rig.lighting[new] if n not in was_on), default=0.0)


# ---------------------------------------------------------------------- ordering
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


def _build_steps(sweep: Sweep, rig: RigConfig, order: Sequence[str], lights: Sequence[str],
                 tilts: Sequence[str]) -> list[_Step]:
    nominal = sweep.azimuths()
    commanded = commanded_azimuths(nominal, rig)
    values = {"light": list(lights), "tilt": list(tilts), "azimuth": list(range(len(nominal)))}
    out: list[_Step] = []
    if sweep.dark.frames > 0:
        for e in sorted({sweep.exposure_for(c) for c in lights}):
            out.append(_Step("dark", None, None, None, None, None, None, 0, sweep.dark.frames, e, None,
                             None, 0))
    exp_of = {c: sweep.exposure_for(c) for c in lights}
    dark_of = {c: dark_event_id(exp_of[c], sweep.gain) if sweep.dark.frames > 0 else None for c in lights}
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
                exp, did = exp_of[cond], dark_of[cond]
                for k in range(sweep.frames_per_pose):
                    out.append(_Step("frame", cond, elev, rig.elevations[elev], commanded[ai], nominal[ai],
                                     ai, k, 1, exp, did, sweep.settle_s, pass_index))
    return out


def _materialise(sweep: Sweep, steps: Sequence[_Step]) -> list[CaptureEvent]:
    out = []
    for i, st in enumerate(steps):
        if st.kind == "dark":
            out.append(dark_event(st.exposure_s, sweep.gain, st.n_frames, index=i))
            continue
        assert st.lighting and st.elevation and st.nominal_azimuth_deg is not None
        out.append(CaptureEvent(
            event_id=frame_event_id(st.lighting, st.elevation, st.nominal_azimuth_deg, st.frame),
            index=i, kind="frame", lighting=st.lighting, elevation=st.elevation, tilt_deg=st.tilt_deg,
            azimuth_deg=st.azimuth_deg, nominal_azimuth_deg=st.nominal_azimuth_deg,
            azimuth_index=st.azimuth_index, frame=st.frame, exposure_s=st.exposure_s, gain=sweep.gain,
            auto_exposure=sweep.auto_exposure, dark_id=st.dark_id, settle_s=st.settle_s,
            pass_index=st.pass_index,
        ))
    return out


_PLAN_CACHE: OrderedDict[tuple[str, str], tuple[tuple[CaptureEvent, ...], str]] = OrderedDict()
_PLAN_CACHE_SIZE = 16
_PLAN_LOCK = threading.Lock()


def _best_plan(sweep: Sweep, rig: RigConfig) -> tuple[list[CaptureEvent], str]:
    # Scoring ~100 candidate orders takes a fraction of a second; the engine, store and API
    # all expand the same sweep, so keep the last few results (events are frozen).
    key = (sweep.model_dump_json(), rig.digest)
    with _PLAN_LOCK:
        hit = _PLAN_CACHE.get(key)
        if hit is not None:
            _PLAN_CACHE.move_to_end(key)
    if hit is None:
        events, order = _search_plan(sweep, rig)
        hit = (tuple(events), order)
        with _PLAN_LOCK:
            _PLAN_CACHE[key] = hit
            while len(_PLAN_CACHE) > _PLAN_CACHE_SIZE:
                _PLAN_CACHE.popitem(last=False)
    return list(hit[0]), hit[1]


def _search_plan(sweep: Sweep, rig: RigConfig) -> tuple[list[CaptureEvent], str]:
    if sweep.axis_order == "auto":
        orders = [o for o in itertools.permutations(AXES)
                  if sweep.mode != "continuous" or o[2] == "azimuth"]
        # Listed first = preferred on ties: the paper's nesting.
        orders.sort(key=lambda o: ">".join(o) != DEFAULT_AXIS_ORDER)
    else:
        orders = [tuple(sweep.axis_order.split(">"))]
    if sweep.reorder:
        light_orders = list(itertools.permutations(sweep.lighting))
        by_angle = sorted(sweep.tilts, key=lambda e: rig.elevations[e])
        tilt_orders = [list(sweep.tilts)] + [t for t in (by_angle, by_angle[::-1]) if t != list(sweep.tilts)]
    else:
        light_orders = [tuple(sweep.lighting)]
        tilt_orders = [list(sweep.tilts)]
    best: tuple[float, list[_Step], str] | None = None
    for order in orders:
        for lights in light_orders:
            for tilts in tilt_orders:
                steps = _build_steps(sweep, rig, order, lights, tilts)
                cost = estimate(steps, rig).total_s  # type: ignore[arg-type]
                if best is None or cost < best[0] - 1e-9:
                    best = (cost, steps, ">".join(order))
    assert best is not None
    return _materialise(sweep, best[1]), best[2]


# ---------------------------------------------------------------------- duration model
class PlanEstimate(_Model):
    total_s: float
    lower_bound_s: float
    breakdown: dict[str, float]  # seconds per component of total_s
    counts: dict[str, int] = Field(default_factory=dict)


def _settle(ev: CaptureEvent, rig: RigConfig, moved: Iterable[str]) -> float:
    moved = list(moved)
    if not moved:
        return 0.0
    if ev.settle_s is not None:
        return ev.settle_s
    return max(rig.axes[m].settle_s for m in moved)


def estimate(events: Sequence[CaptureEvent], rig: RigConfig, *,
             start_pose: tuple[float, float] = (0.0, 0.0), parallel_axes: bool = False) -> PlanEstimate:
    """Duration of a stop-and-go event list from ``start_pose`` (turntable, tilt).

    ``total_s`` models the engine: axes moved one after the other unless
    ``parallel_axes``, then settle, then lamp warm-up, then exposure + readout.
    ``lower_bound_s`` is the physics floor of the same order: axes in parallel, warm-up
    overlapping the move, no settle.
    """
    tt, tl = rig.axes["turntable"], rig.axes["tilt"]
    readout = 1.0 / rig.camera.model.max_fps
    pos = {"turntable": start_pose[0], "tilt": start_pose[1]}
    light: str | None = None
    b = dict(motion=0.0, settle=0.0, warmup=0.0, exposure=0.0, readout=0.0, dark=0.0)
    lower = 0.0
    n = dict(frames=0, darks=0, dark_frames=0, moves=0, switches=0)
    for ev in events:
        if ev.kind == "dark":
            t = ev.n_frames * (ev.exposure_s + readout)
            b["dark"] += t
            lower += t
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
        b["warmup"] += warm
        b["exposure"] += ev.exposure_s
        b["readout"] += readout
        lower += max(max(t_tt, t_tl), warm) + ev.exposure_s + readout
        n["frames"] += 1
        n["moves"] += bool(moved)
        pos["turntable"], pos["tilt"] = ev.azimuth_deg, ev.tilt_deg
    total = sum(b.values())
    return PlanEstimate(total_s=total, lower_bound_s=min(lower, total), breakdown=b, counts=n)


class ContinuousEstimate(_Model):
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

    def as_plan_estimate(self) -> PlanEstimate:
        return PlanEstimate(total_s=self.total_s, lower_bound_s=self.lower_bound_s, breakdown=self.breakdown)


def estimate_continuous(sweep: Sweep, rig: RigConfig, *, radius_px: float,
                        max_blur_px: float | None = None,
                        events: Sequence[CaptureEvent] | None = None) -> ContinuousEstimate:
    """ω per condition: as fast as the turntable allows, but one azimuth step must take at
    least ``frames_per_pose`` frame intervals (frame interval = max(1/max_fps, exposure))
    and, if given, the blur at ``radius_px`` must stay under ``max_blur_px``."""
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
        omega[c], interval[c] = w, fi
        blur_deg[c] = w * exp
        blur_px[c] = radius_px * math.radians(blur_deg[c])
        runup[c] = w * w / (2 * tt.accel_dps2)
    if events is None:
        events = sweep.expand(rig)
    lo, hi = turntable_range(rig)
    b = dict(motion=0.0, sweep=0.0, settle=0.0, warmup=0.0, dark=0.0)
    lower = 0.0
    pos_tt, pos_tl = 0.0, 0.0
    light: str | None = None
    within = True
    frames = [e for e in events if e.kind == "frame"]
    for ev in events:
        if ev.kind == "dark":
            t = ev.n_frames * (ev.exposure_s + 1.0 / fps)
            b["dark"] += t
            lower += t
    passes: dict[int, list[CaptureEvent]] = {}
    for ev in frames:
        passes.setdefault(ev.pass_index, []).append(ev)
    for p in sorted(passes):
        evs = passes[p]
        c = evs[0].lighting
        assert c is not None and evs[0].azimuth_deg is not None and evs[0].tilt_deg is not None
        w, r = omega[c], runup[c]
        a0, a1 = evs[0].azimuth_deg, evs[-1].azimuth_deg
        direction = 1.0 if a1 >= a0 else -1.0
        start, end = a0 - direction * r, a1 + direction * r
        if min(start, end) < lo - 1e-9 or max(start, end) > hi + 1e-9:
            within = False
        t_tt = move_time_s(start - pos_tt, tt)
        t_tl = move_time_s(evs[0].tilt_deg - pos_tl, tl)
        warm = switch_warmup_s(rig, light, c) if c != light else 0.0
        light = c
        moved = [a for a, t in (("turntable", t_tt), ("tilt", t_tl)) if t > 0]
        settle = _settle(evs[0], rig, moved)
        # Run-up and run-down at acceleration a take ω/a together; the span at ω.
        span = abs(a1 - a0)
        t_sweep = span / w + w / tt.accel_dps2 + (sweep.frames_per_pose - 1) * interval[c]
        b["motion"] += t_tt + t_tl
        b["settle"] += settle
        b["warmup"] += warm
        b["sweep"] += t_sweep
        lower += max(t_tt, t_tl, warm) + t_sweep
        pos_tt, pos_tl = end, evs[0].tilt_deg
    total = sum(b.values())
    return ContinuousEstimate(
        omega_dps=omega, frame_interval_s=interval, blur_deg=blur_deg, blur_px=blur_px, runup_deg=runup,
        within_cable_limit=within, total_s=total, lower_bound_s=min(lower, total), breakdown=b,
    )
