"""Continuous capture: the steps for ``mode = "continuous"``, one pass per lighting condition and tilt.

Per pass the lamps of the condition go on (usually already: the previous pass switched them
once its last frame was read, so they warm while it brakes) and the tilt moves; with auto
exposure the condition is metered at the pass's first mark. Consecutive passes run in opposite
directions (the plan's snake), so the turntable starts the next pass from where it came to rest,
beyond the last mark, with no move (:func:`m2s2hil.engine.marks.pass_start`); it starts turning
early enough that the first frame a mark can take begins just as the lamps are warm and the tilt
has settled (never before), and the camera's stream starts during the run-up; then it turns at ω
while the camera streams, and the frame nearest each azimuth mark (by timestamp and read-back)
is kept (the matching is :func:`m2s2hil.engine.marks.run_pass`). Blur ω·t_exp is recorded per
frame (``meta["continuous"]``) and per pass (journal event ``continuous_pass``).

The turntable's continuous rotation is the capability the rig recorded when it opened
(``rig.rotation``); a rig without it is refused before anything moves.

ω (:class:`SpeedSettings`, ``EngineOptions.continuous``) is ``speed_dps`` if set, otherwise
the plan's ω per condition
(:func:`m2s2hil.plan.estimate_continuous`), limited so the blur at ``radius_px`` from the
axis stays under ``max_blur_px`` when that is set. A frame is accepted within
``max_angle_error_deg`` of its mark, by default 1.5 frame spacings (at most half an
azimuth step).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Hashable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from m2s2hil.config import RigConfig
from m2s2hil.drivers.errors import FrameIncomplete
from m2s2hil.drivers.interfaces import Frame
from m2s2hil.engine.exposure_search import ExposureResult
from m2s2hil.engine.marks import Match, PassReport, blur_estimate, pass_start, run_pass
from m2s2hil.engine.messages import FrameCaptured, StepGen
from m2s2hil.engine.steps import CaptureKit, SharedSteps
from m2s2hil.errors import UsageError
from m2s2hil.plan import CaptureEvent, ContinuousEstimate, Sweep, estimate_continuous
from m2s2hil.rig.opened import AxisRole


@dataclass(frozen=True)
class SpeedSettings:
    """The engine's continuous-mode options (see the module docstring)."""

    speed_dps: float | None = None
    max_blur_px: float | None = None
    max_angle_error_deg: float | None = None
    radius_px: float = 400.0

    def estimate(self, sweep: Sweep, config: RigConfig) -> ContinuousEstimate:
        """The plan's continuous model at this blur limit (or speed override)."""
        # With a speed override every condition turns at it, whatever its exposure (the
        # estimate used to derive a blur limit from the shortest exposure, so longer ones
        # were modelled slower than they ran: efficiency above 1).
        return estimate_continuous(sweep, config, radius_px=self.radius_px, max_blur_px=self.max_blur_px,
                                   speed_dps=self.speed_dps)

    def omega(self, sweep: Sweep, config: RigConfig, lighting: str, exposure_s: float) -> float:
        if self.speed_dps is not None:
            return self.speed_dps
        omega = self.estimate(sweep, config).omega_dps[lighting]
        if self.max_blur_px is not None:  # auto exposure may have changed t_exp
            omega = min(omega, math.degrees(self.max_blur_px / self.radius_px) / exposure_s)
        return omega

    def match_window(self, sweep: Sweep, config: RigConfig, speed: float, exposure_s: float) -> float:
        """Largest accepted |angle - mark|: 1.5 frame spacings (one dropped frame at a mark is
        tolerated, a longer gap makes the mark missing), unless set explicitly."""
        if self.max_angle_error_deg is not None:
            return self.max_angle_error_deg
        period = max(1.0 / config.camera.model.max_fps, exposure_s)
        return min(sweep.azimuth_step_deg / 2, max(0.1, 1.5 * speed * period))


class ContinuousSteps(SharedSteps):
    """:class:`~m2s2hil.engine.steps.CaptureSteps` for ``mode = "continuous"``: a unit is what
    is still to do of one pass. Keeps the pass reports and the per-frame blur for the summary."""

    def __init__(self, kit: CaptureKit, settings: SpeedSettings) -> None:
        super().__init__(kit)
        self.settings = settings
        self.blur_deg: list[float] = []  # per stored frame
        self.passes: list[dict[str, Any]] = []  # per pass: its report
        self._stream_start_s: float | None = None  # least start-up of the camera's stream seen
        self._rest_deg: float | None = None  # the turntable's read-back where the last pass stopped
        self._next_lighting: dict[int, str] | None = None  # pass index -> the next pass's lighting

    def setup(self) -> None:
        if self.rig.rotation is None:
            raise UsageError(f"the turntable ({self.rig.turntable.name}) cannot rotate continuously: "
                             "capture this sweep in stop-and-go mode")
        super().setup()

    def unit_key(self, event: CaptureEvent) -> Hashable | None:
        return event.pass_index if event.kind == "frame" else None

    def execute(self, unit: Sequence[CaptureEvent], attempt: int) -> StepGen[None]:
        if unit[0].kind == "dark":
            yield from self.capture_dark(unit[0])
            return
        yield from self.lit_unit()
        while not (yield from self._capture_pass(unit, attempt)):
            pass  # the lens cap went on and off for a dark meanwhile: lamps and tilt again

    def recover(self) -> None:
        super().recover()
        self._rest_deg = None  # a fault may have moved it: the next pass moves and verifies

    def forget(self) -> None:
        super().forget()
        self._rest_deg = None

    def lower_bound_s(self) -> float:
        return self.settings.estimate(self.kit.sweep, self.rig.config).lower_bound_s

    def summary(self) -> dict[str, Any]:
        out = super().summary()
        if self.blur_deg:
            out["blur_deg"] = {"mean": float(np.mean(self.blur_deg)), "max": float(np.max(self.blur_deg))}
            out["passes"] = self.passes
        return out

    def _capture_pass(self, todo: Sequence[CaptureEvent], attempt: int) -> StepGen[bool]:
        """One pass over the marks of ``todo`` (events of one pass); FrameIncomplete if marks
        were missed. False (before the stream) when a dark under the operator's cap
        interrupted it."""
        kit, settings = self.kit, self.settings
        rotation = self.rig.rotation
        assert rotation is not None  # checked in setup()
        clock = self.rig.clock
        config = self.rig.config
        sweep = kit.sweep
        first = todo[0]
        assert first.tilt_deg is not None and first.lighting is not None
        cycles = kit.darks.lens_cycles
        yield from kit.set_condition(first)  # the lamps' warm-up runs from here, under the moves
        moved: list[AxisRole] = ["tilt"] if self.ops.move("tilt", first.tilt_deg) else []
        settle_until = clock.monotonic() + self.ops.settle_s(moved, first.settle_s)
        exposure, auto = self._exposure_for_pass(first)
        speed = settings.omega(sweep, config, first.lighting, exposure)
        marks: dict[float, list[CaptureEvent]] = {}
        for ev in todo:
            assert ev.azimuth_deg is not None
            marks.setdefault(ev.azimuth_deg, []).append(ev)
        window = settings.match_window(sweep, config, speed, exposure)
        start, rest = self._pass_start(list(marks), speed, window)
        # Overlap: the turntable heads for its start (when it must move at all) while the tilt
        # settles, the lamps warm and the darks are looked up (run_pass then only verifies it).
        # Not alongside the tilt move: on GRBL both axes share one planner, whose blocks run
        # one after the other and whose status says Run until the last one ends [src:planner.c],
        # so the tilt's arrival could not be watched while the turntable moved.
        tol = config.axes["turntable"].tolerance_deg
        if rest is None or abs(rest - start) > tol / 2:
            rest = None
            self.ops.start_move("turntable", start)
        dark = yield from kit.darks.for_setting(exposure, first.gain)
        if kit.darks.lens_cycles != cycles:
            return False
        kit.camera.configure(exposure, first.gain)
        blur = blur_estimate(speed, exposure, settings.radius_px)
        self._rest_deg = None  # until this pass reports where it stopped

        def on_match(match: Match) -> Iterator[FrameCaptured]:
            evs = sorted(match.key, key=lambda e: e.frame)
            for ev, frame, extra in zip(evs, match.frames, match.extras, strict=False):
                meta = kit.frames.meta(ev, frame, exposure, dark, extra["clock_s"], extra["wall"], attempt)
                meta["pose"] = {"turntable_deg": extra["angle_deg"], "tilt_deg": self.ops.pose()["tilt"],
                                "turntable_source": "interpolated read-back at mid-exposure"}
                meta["continuous"] = {
                    "mark_deg": match.mark_deg, "angle_deg": extra["angle_deg"],
                    "error_deg": extra["angle_deg"] - match.mark_deg, "speed_dps": extra["speed_dps"],
                    # the interpolated read-back's own uncertainty (marks.AngleTrack.uncertainty_at)
                    "pose_uncertainty_deg": extra.get("angle_uncertainty_deg"),
                    "commanded_speed_dps": speed, **blur.to_dict(),
                }
                if auto is not None:
                    meta["auto_exposure"] = auto.to_dict()
                self.blur_deg.append(blur.deg)
                yield FrameCaptured(ev, frame.data, meta, dark, extra.get("truth"))

        def on_frame(frame: Frame) -> dict[str, Any]:
            return {"clock_s": clock.monotonic(), "wall": clock.wall(), "truth": kit.frames.truth()}

        report: PassReport = yield from run_pass(
            self.rig, self.ops, rotation, marks=[(a, evs) for a, evs in marks.items()], speed_dps=speed,
            exposure_s=exposure, k=sweep.frames_per_pose,
            window_deg=window,
            on_match=on_match, on_frame=on_frame,
            frame_timeout_s=exposure + kit.camera.snap_timeout_s,
            start_deg=start, rest_deg=rest,
            ready_at=max(settle_until, self.ops.lamps_ready_at()),
            stream_start_s=self._stream_start_s, on_done=self._switch_ahead(first),
        )
        self._rest_deg = report.rest_deg
        if report.stream_start_s is not None:
            got = report.stream_start_s
            self._stream_start_s = got if self._stream_start_s is None else min(self._stream_start_s, got)
        info = {"pass_index": first.pass_index, "lighting": first.lighting, "elevation": first.elevation,
                "exposure_s": exposure, **report.to_dict(), **blur.to_dict()}
        self.passes.append(info)
        kit.store.record_event("continuous_pass", info)
        if report.stopped_early:
            return True  # pause/abort: the runner's boundary handles it; what is left stays pending
        missing = [ev for _, evs in report.missing for ev in evs]
        if missing:
            raise FrameIncomplete(
                f"no frame matched to {len(report.missing)} azimuth mark(s) "
                f"({', '.join(f'{a:g}' for a, _ in report.missing[:5])} deg); "
                f"{report.dropped} frame(s) dropped in the pass",
                device=self.rig.camera.name, command="continuous pass",
            )
        return True

    def _pass_start(self, marks: list[float], speed: float, window_deg: float) -> tuple[float, float | None]:
        """Where :func:`~m2s2hil.engine.marks.run_pass` starts turning towards ``marks``, and
        where the turntable rests now if known: where the last pass stopped, the verified pose,
        or (at the first pass) its read-back while it stands still. It starts from there when
        that is on this pass's near side (the snake's turn), without a move."""
        ax = self.rig.config.axes["turntable"]
        rest = self._rest_deg if self._rest_deg is not None else self.ops.pose()["turntable"]
        if rest is None and not self.rig.turntable.is_moving():
            rest = float(self.rig.turntable.position())
        direction = -1 if len(marks) > 1 and marks[0] > marks[-1] else 1
        first = min(marks) if direction > 0 else max(marks)
        return pass_start(first, direction, speed, ax.accel_dps2, window_deg, rest,
                          (ax.min_deg, ax.max_deg)), rest

    def _switch_ahead(self, ev: CaptureEvent) -> Callable[[], object] | None:
        """What switches the plan's next pass's lamps once this pass has its last frame (so
        they warm while the turntable brakes and turns back); None when it keeps these lamps.
        Lamps switched for a pass that does not come next (a retry, a resume) cost only time:
        each pass sets its own lamps and waits for those still warming."""
        if self._next_lighting is None:
            order = sorted({(e.pass_index, e.lighting) for e in self.kit.sweep.expand(self.rig.config)
                            if e.kind == "frame" and e.lighting is not None})
            self._next_lighting = {p: nxt for (p, _l), (_p, nxt) in itertools.pairwise(order)}
        nxt = self._next_lighting.get(ev.pass_index)
        if nxt is None or nxt == ev.lighting:
            return None
        channels = frozenset(self.rig.config.lamp_channels(nxt))
        return lambda: self.ops.set_lamps(channels)

    def _exposure_for_pass(self, ev: CaptureEvent) -> tuple[float, ExposureResult | None]:
        exposure = self.kit.exposure
        if not exposure.needs_metering(ev):
            return exposure.exposure(ev)
        assert ev.azimuth_deg is not None
        self.ops.move("turntable", ev.azimuth_deg)  # meter at the pass's first mark
        self._rest_deg = None  # it stands at the verified pose now
        self.ops.wait_ready(self.rig.clock.monotonic())
        return exposure.exposure(ev)
