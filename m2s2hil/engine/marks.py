"""Continuous-rotation capture: match streamed frames to azimuth marks.

Beyond the paper's stop-and-go, the turntable can turn at a constant speed while the
camera streams; the frame nearest each 10° mark (by angle) is kept. The angle of a
frame comes from two sources joined on the host clock:

- the turntable's read-back, sampled while it turns (:class:`AngleTrack`: linear
  interpolation between the samples around the frame's time, which is exact at
  constant speed; a least-squares line over recent samples gives the measured speed);
- the frame's device timestamp, mapped onto the host clock by the smallest observed
  ``host_time - timestamp`` (the transfer latency's floor), plus half the exposure:
  the angle is taken at mid-exposure. The floor of ``host - device`` time is the frame's
  end of readout, so mid-exposure is ``mapped - readout - exposure/2`` (device
  timestamps mark the start of exposure, as U3V leaders do).

The price is motion blur of ``ω·t_exp`` degrees during the exposure;
:func:`blur_estimate` expresses it in degrees and in pixels at a given radius from
the rotation axis, and the engine records both with every frame.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from m2s2hil.engine.messages import Checkpoint, StepGen, StepMessage

if TYPE_CHECKING:
    from m2s2hil.drivers.interfaces import ContinuousRotation
    from m2s2hil.rig.opened import Rig
    from m2s2hil.rig.operations import RigOps


class AngleTrack:
    """Read-back samples (host time, degrees) of an axis turning (at constant speed, mostly).

    ``accel_dps2`` bounds the axis's acceleration: between the first two samples (the start of
    a run-up, when no change of slope has been seen yet) the interpolation is off by at most
    what that acceleration bends the path, and the uncertainty says so."""

    def __init__(self, window: int = 32, accel_dps2: float = 0.0) -> None:
        self._samples: collections.deque[tuple[float, float]] = collections.deque(maxlen=window)
        self._half: collections.deque[float] = collections.deque(maxlen=window)
        self.accel_dps2 = accel_dps2

    def add(self, t: float, deg: float, half_width_s: float = 0.0) -> None:
        """A read-back ``deg`` known to have been taken within ``t ± half_width_s`` (the
        query's round trip)."""
        self._samples.append((float(t), float(deg)))
        self._half.append(float(half_width_s))

    def uncertainty_at(self, t: float) -> float:
        """How far :meth:`angle_at` may be off (degrees): the bracketing samples' time
        uncertainty at their slope; between them, how far an acceleration bends the path from
        the chord (``a·(t - t0)·(t1 - t)/2``, with ``a`` the change of slope from the interval
        before, or the axis's bound when there is none); beyond the samples, the change of slope
        between the last two intervals carried over the extrapolated time."""
        s, h = self._samples, self._half
        if len(s) < 2:
            raise ValueError("need at least two read-back samples")
        i = next((i for i in range(1, len(s)) if s[i][0] >= t), len(s) - 1)
        (t0, a0), (t1, a1) = s[i - 1], s[i]
        slope = abs(a1 - a0) / (t1 - t0) if t1 > t0 else 0.0
        out = slope * max(h[i - 1], h[i])
        if t0 < t < t1:
            accel = self.accel_dps2
            if i >= 2 and t0 > s[i - 2][0]:
                before = (a0 - s[i - 2][1]) / (t0 - s[i - 2][0])
                accel = abs((a1 - a0) / (t1 - t0) - before) / ((t1 - s[i - 2][0]) / 2)
            out += accel * (t - t0) * (t1 - t) / 2
        if t > t1 and len(s) >= 3 and t1 > t0 and t0 > s[-3][0]:
            prev = (a0 - s[-3][1]) / (t0 - s[-3][0])
            out += abs((a1 - a0) / (t1 - t0) - prev) * (t - t1)
        return out

    def __len__(self) -> int:
        return len(self._samples)

    def last_time(self) -> float:
        """When the latest sample was taken (-inf before any)."""
        return self._samples[-1][0] if self._samples else -math.inf

    def steady(self, tolerance_dps: float = 0.2) -> bool:
        """The last two intervals had the same slope (within ``tolerance_dps``, a few read-back
        quanta): beyond the samples the path goes straight on, so extrapolating is exact."""
        s = self._samples
        if len(s) < 3 or not s[-3][0] < s[-2][0] < s[-1][0]:
            return False
        before = (s[-2][1] - s[-3][1]) / (s[-2][0] - s[-3][0])
        last = (s[-1][1] - s[-2][1]) / (s[-1][0] - s[-2][0])
        return abs(last - before) <= tolerance_dps

    def fit(self) -> tuple[float, float]:
        """``(a0, ω)`` with ``angle(t) = a0 + ω·t``; needs two samples at different times."""
        if len(self._samples) < 2:
            raise ValueError("need at least two read-back samples")
        ts = np.array([s[0] for s in self._samples])
        ds = np.array([s[1] for s in self._samples])
        t0 = ts.mean()
        dt = ts - t0
        den = float(np.dot(dt, dt))
        if den <= 0:
            raise ValueError("read-back samples all at the same time")
        w = float(np.dot(dt, ds - ds.mean()) / den)
        return float(ds.mean() - w * t0), w

    def angle_at(self, t: float) -> float:
        """Linear interpolation between the samples around ``t`` (extrapolated from the last
        two beyond them): exact at constant speed, and still right during the run-up."""
        s = self._samples
        if len(s) < 2:
            raise ValueError("need at least two read-back samples")
        if t <= s[0][0]:
            (t0, a0), (t1, a1) = s[0], s[1]
        elif t >= s[-1][0]:
            (t0, a0), (t1, a1) = s[-2], s[-1]
        else:
            i = next(i for i in range(1, len(s)) if s[i][0] >= t)
            (t0, a0), (t1, a1) = s[i - 1], s[i]
        if t1 == t0:
            return a1
        return a0 + (a1 - a0) * (t - t0) / (t1 - t0)

    def speed(self) -> float:
        return self.fit()[1]


class TimestampMapper:
    """Device timestamps → host monotonic time, by the floor of the observed latency."""

    def __init__(self) -> None:
        self.offset: float | None = None

    def observe(self, device_ts: float, host_ts: float) -> None:
        off = host_ts - device_ts
        if self.offset is None or off < self.offset:
            self.offset = off

    def host_time(self, device_ts: float) -> float:
        if self.offset is None:
            raise ValueError("no timestamp observed yet")
        return device_ts + self.offset


@dataclass
class Candidate:
    angle: float
    error: float
    frame: Any
    extra: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Match:
    key: Any  # what the caller attached to the mark (the capture events)
    mark_deg: float
    angle_deg: float  # interpolated azimuth at mid-exposure
    frames: tuple[Any, ...]
    extras: tuple[dict, ...]
    wanted: int = 1

    @property
    def complete(self) -> bool:
        return len(self.frames) >= self.wanted

    @property
    def error_deg(self) -> float:
        return self.angle_deg - self.mark_deg


class MarkMatcher:
    """Keep, per mark, the ``k`` frames nearest to it; release a mark once it is passed.

    ``direction`` is +1 when the angle grows with time, -1 otherwise. A frame is a
    candidate for the marks within ``window_deg`` of it, so at most ``k`` frames per
    mark in that window are held: memory stays bounded however long the stream runs.
    """

    def __init__(
        self, marks: list[tuple[float, Any]], direction: int, k: int = 1, window_deg: float = 5.0
    ) -> None:
        if direction not in (1, -1):
            raise ValueError("direction must be +1 or -1")
        self.direction = direction
        self.k = max(1, k)
        self.window = window_deg
        self._pending: list[tuple[float, Any]] = sorted(marks, key=lambda m: direction * m[0])
        self._cands: list[list[Candidate]] = [[] for _ in self._pending]

    @property
    def remaining(self) -> list[tuple[float, Any]]:
        return list(self._pending)

    def done(self) -> bool:
        return not self._pending

    def held(self) -> int:
        return sum(len(c) for c in self._cands)

    def offer(self, angle: float, frame: Any, extra: dict | None = None) -> list[Match]:
        """Consider one frame at ``angle``; return the marks it completes."""
        d = self.direction
        for (mark, _key), cands in zip(self._pending, self._cands, strict=True):
            signed = d * (angle - mark)
            if signed < -self.window:
                break  # this mark and the ones after it are still ahead
            if abs(signed) <= self.window:
                cands.append(Candidate(angle, abs(angle - mark), frame, extra or {}))
                cands.sort(key=lambda c: c.error)
                del cands[self.k :]
        out: list[Match] = []
        # Once past a mark, errors only grow: the mark is complete when it holds k frames
        # and the newest one did not make the cut, or when it has left the window.
        while self._pending:
            mark, _key = self._pending[0]
            cands = self._cands[0]
            signed = d * (angle - mark)
            if signed < 0:
                break
            full = len(cands) >= self.k and all(c.frame is not frame for c in cands)
            if not (full or signed > self.window):
                break
            out.append(self._release())
        return out

    def _release(self) -> Match:
        mark, key = self._pending.pop(0)
        cands = sorted(self._cands.pop(0), key=lambda c: c.angle * self.direction)
        angle = float(np.mean([c.angle for c in cands])) if cands else math.nan
        return Match(key, mark, angle, tuple(c.frame for c in cands), tuple(c.extra for c in cands), self.k)

    def flush(self) -> list[Match]:
        """Release every mark that holds ``k`` frames (the stream has ended)."""
        out = []
        while self._pending and len(self._cands[0]) >= self.k:
            out.append(self._release())
        return out

    def drop_candidates(self) -> None:
        """Forget held frames (a revolution cut short): their marks stay pending."""
        for c in self._cands:
            c.clear()


@dataclass(frozen=True)
class Blur:
    deg: float  # ω·t_exp
    px_at_radius: float  # arc length in sensor pixels at ``radius_px`` from the axis

    def to_dict(self) -> dict[str, float]:
        return {"blur_deg": self.deg, "blur_px": self.px_at_radius}


def blur_estimate(speed_dps: float, exposure_s: float, radius_px: float) -> Blur:
    deg = abs(speed_dps) * exposure_s
    return Blur(deg, math.radians(deg) * radius_px)


def run_up_deg(speed_dps: float, accel_dps2: float, margin_s: float = 0.2) -> float:
    """Angle the turntable needs to reach a steady ``speed_dps`` (plus a margin)."""
    v = abs(speed_dps)
    return v * v / (2 * accel_dps2) + v * margin_s


def reach_s(distance_deg: float, speed_dps: float, accel_dps2: float) -> float:
    """Time from rest to cover ``distance_deg`` accelerating at ``accel_dps2`` up to ``speed_dps``."""
    d, v = max(0.0, distance_deg), abs(speed_dps)
    ramp = v * v / (2 * accel_dps2)
    return math.sqrt(2 * d / accel_dps2) if d <= ramp else v / accel_dps2 + (d - ramp) / v


def pass_start(first_deg: float, direction: int, speed_dps: float, accel_dps2: float, window_deg: float,
               rest_deg: float | None, limits: tuple[float, float]) -> float:
    """Where a pass towards ``direction`` starts turning: where the turntable rests when that is
    on the near side of the first mark (no move: accelerating from there passes any run-up start
    already moving, and a frame taken slower is only sharper), else far enough before the mark
    to be at speed at the first frame that may be kept (the ramp plus the match window)."""
    if rest_deg is not None and direction * (first_deg - rest_deg) >= 0:
        return rest_deg
    back = speed_dps * speed_dps / (2 * accel_dps2) + window_deg
    return min(limits[1], max(limits[0], first_deg - direction * back))


@dataclass
class PassReport:
    """What one continuous pass did."""

    marks: int
    matched: int
    frames_read: int
    dropped: int  # block ids missing from the stream
    missing: list[tuple[float, Any]]  # marks without their frames
    speed_dps: float | None  # measured from the read-back
    max_error_deg: float | None  # largest |angle - mark| of the kept frames
    duration_s: float
    stopped_early: bool = False
    stream_start_s: float | None = None  # how long the camera's stream took to start
    rest_deg: float | None = None  # the turntable's read-back once stopped (None after an error)
    before_ready: int = 0  # frames exposed before the lamps were warm and the tilt settled: not kept

    def to_dict(self) -> dict:
        return {
            "marks": self.marks, "matched": self.matched, "frames_read": self.frames_read,
            "dropped": self.dropped, "missing_marks": [m for m, _ in self.missing],
            "measured_speed_dps": self.speed_dps, "max_error_deg": self.max_error_deg,
            "duration_s": self.duration_s, "stopped_early": self.stopped_early,
            "stream_start_s": self.stream_start_s, "frames_before_ready": self.before_ready,
        }


def run_pass(
    rig: Rig,
    ops: RigOps,
    rotation: ContinuousRotation,
    *,
    marks: list[tuple[float, Any]],
    speed_dps: float,
    exposure_s: float,
    k: int,
    window_deg: float,
    on_match: Callable[[Match], Iterable[StepMessage]],
    on_frame: Callable[[Any], dict] | None = None,
    frame_timeout_s: float = 2.0,
    poll_interval_s: float = 0.05,
    start_deg: float | None = None,
    rest_deg: float | None = None,
    ready_at: float = -math.inf,
    stream_start_s: float | None = None,
    on_done: Callable[[], object] | None = None,
) -> StepGen[PassReport]:
    """One continuous pass over ``marks`` (commanded turntable angles, in any order): a step.

    The turntable starts at ``start_deg`` (default: :func:`pass_start` with no known rest),
    moved there and verified unless ``rest_deg``, its read-back at rest, says it stands there.
    No frame exposed before ``ready_at`` (lamps warm, tilt settled) is kept. With a long enough
    run-up and a known ``stream_start_s`` the rotation starts first, timed so that the first
    frame that may be kept begins no sooner than ``ready_at``, and the camera's stream starts
    during the run-up; otherwise the stream starts first, no sooner than lets its first frame
    begin at ``ready_at``. Frames are matched to marks and ``on_match`` yields what it makes of
    each; before every frame it yields a :class:`~m2s2hil.engine.messages.Checkpoint` and stops
    early when the reply says so. Once every mark has its frames, ``on_done`` runs before the
    turntable brakes (the next pass's lamps switch and warm meanwhile). Rotation and stream are
    always stopped before it returns, raises or is closed.
    """
    clock = rig.clock
    tt, cam = rig.turntable, rig.camera
    model = rig.config.camera.model
    ax = rig.config.axes["turntable"]
    angles = sorted(m[0] for m in marks)
    direction = 1
    if len(marks) > 1 and marks[0][0] > marks[-1][0]:
        direction = -1
    first, last = (angles[0], angles[-1]) if direction > 0 else (angles[-1], angles[0])
    start = start_deg if start_deg is not None else pass_start(
        first, direction, speed_dps, ax.accel_dps2, window_deg, None, (ax.min_deg, ax.max_deg))
    if rest_deg is None or abs(rest_deg - start) > ax.tolerance_deg / 2:
        ops.move("turntable", start)
    readout = 1.0 / model.max_fps
    fps = min(model.max_fps, 1.0 / max(exposure_s, 1e-6))
    matcher = MarkMatcher(marks, direction, k=k, window_deg=window_deg)
    track, mapper = AngleTrack(window=64, accel_dps2=ax.accel_dps2), TimestampMapper()
    speeds = AngleTrack(window=3)  # the last ~0.1 s: the run-up is over by the first mark
    # From rest at `start`, the first frame that may be kept (mid-exposure at the first mark less
    # the window) begins `lead` s after the rotation starts, one whole exposure early to be safe.
    lead = reach_s(direction * (first - start) - window_deg, speed_dps, ax.accel_dps2) - exposure_s
    rotate_first = stream_start_s is not None and lead >= 1.25 * stream_start_s
    t0 = clock.monotonic()
    frames_read = dropped = early = 0
    last_block: int | None = None
    errors: list[float] = []
    stopped = False
    end = last + direction * (window_deg + 1.0)
    travel = abs(end - start)
    last_poll = -math.inf
    started_s: float | None = None
    rest: float | None = None

    def poll() -> None:
        nonlocal last_poll
        a = clock.monotonic()
        pos = float(tt.position())
        b = clock.monotonic()
        track.add((a + b) / 2, pos, (b - a) / 2)
        speeds.add((a + b) / 2, pos)
        last_poll = b

    def sleep_until(t: float) -> None:
        wait = t - clock.monotonic()
        if wait > 0:
            clock.sleep(wait)

    def start_stream() -> None:
        nonlocal started_s
        a = clock.monotonic()
        cam.start_stream(fps)
        started_s = clock.monotonic() - a

    missing: list[tuple[float, Any]] = []
    # While the speed changes (a run-up), frames wait for a read-back after their mid-exposure:
    # the angle is interpolated, not extrapolated along a line the path bends away from.
    waiting: collections.deque[tuple[float, Any, dict]] = collections.deque()
    past_end = False

    def resolve(final: bool = False) -> Iterator[StepMessage]:
        nonlocal past_end
        while waiting and (final or waiting[0][0] <= track.last_time() or track.steady()):
            t_mid, frame, extra = waiting.popleft()
            angle = track.angle_at(t_mid)
            extra["angle_deg"] = angle
            extra["angle_uncertainty_deg"] = track.uncertainty_at(t_mid)
            yield from release(matcher.offer(angle, frame, extra))
            if direction * (angle - end) > 0:
                past_end = True
                waiting.clear()

    def release(ms: list[Match]) -> Iterator[StepMessage]:
        for m in ms:
            if not m.complete:  # passed without (enough) frames near it: a gap in the stream
                missing.append((m.mark_deg, m.key))
                continue
            errors.append(abs(m.error_deg))
            yield from on_match(m)

    try:
        if rotate_first:
            assert stream_start_s is not None
            sleep_until(ready_at - lead)
            rotation.rotate(speed_dps, direction=direction)
            poll()
            start_stream()  # during the run-up: frames flow before the first one that may be kept
        else:
            # Every frame of the stream may be kept: its first exposure begins no sooner than
            # ready_at (80 % of the least start-up seen, so a faster start only makes it later).
            sleep_until(ready_at - (0.8 * stream_start_s if stream_start_s is not None else 0.0))
            start_stream()
            rotation.rotate(speed_dps, direction=direction)
            poll()
        turning = clock.monotonic()
        give_up = turning + travel / max(speed_dps, 1e-6) + 2 * speed_dps / ax.accel_dps2 + 5.0
        while not matcher.done() and not past_end:
            if (yield Checkpoint()):
                stopped = True
                break
            if clock.monotonic() - last_poll >= poll_interval_s:
                poll()
                yield from resolve()
            frame = cam.read_frame(timeout=frame_timeout_s)
            frames_read += 1
            if last_block is not None and frame.block_id > last_block + 1:
                dropped += frame.block_id - last_block - 1
            last_block = frame.block_id
            mapper.observe(frame.timestamp_s, frame.host_time_s)
            if len(track) < 2:
                poll()
            t_mid = mapper.host_time(frame.timestamp_s) - readout - exposure_s / 2
            # The mapped time is never earlier than the real one (the latency's floor): a frame
            # kept here did begin after ready_at. The timing above makes this a guard only.
            if t_mid - exposure_s / 2 < ready_at:
                early += 1
            else:
                extra = dict(on_frame(frame)) if on_frame else {}
                try:
                    extra["speed_dps"] = abs(speeds.speed())
                except ValueError:
                    extra["speed_dps"] = None
                waiting.append((t_mid, frame, extra))
                yield from resolve()
            if clock.monotonic() > give_up:
                break
        if not stopped and waiting:
            poll()  # the frames still waiting for a read-back after them
            yield from resolve(final=True)
        if matcher.done() and not stopped and not missing and on_done is not None:
            on_done()  # the last frame is read: the next pass's lamps may come on while it brakes
    finally:
        stop_errors = []
        for step in (tt.stop, cam.stop_stream):
            try:
                step()
            except Exception as exc:  # both steps are tried; the first error is raised below
                stop_errors.append(exc)
        ops.invalidate(lamps=False)
        if not stop_errors:
            try:  # where the next pass may start from, without a move
                rest = float(tt.position())
            except Exception:  # not known: the next pass moves and verifies
                rest = None
    if stopped:
        matcher.drop_candidates()
    else:
        yield from release(matcher.flush())
    if stop_errors:
        raise stop_errors[0]
    try:
        measured = abs(speeds.speed())
    except ValueError:
        measured = None
    if not stopped:
        missing.extend(matcher.remaining)
    return PassReport(
        marks=len(marks), matched=len(errors), frames_read=frames_read,
        dropped=dropped, missing=missing, speed_dps=measured,
        max_error_deg=max(errors) if errors else None, duration_s=clock.monotonic() - t0,
        stopped_early=stopped, stream_start_s=started_s, rest_deg=rest, before_ready=early,
    )
