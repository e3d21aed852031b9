"""Continuous-mode capture for the engine: one pass per lighting condition and tilt.

Per pass the lamps of the condition go on and the tilt moves; with auto exposure the
condition is metered at the pass's first mark; then the turntable turns at ω while the
camera streams, and the frame nearest each azimuth mark (by timestamp and read-back) is
kept (the matching is :func:`m2s2hil.engine.marks.run_pass`). Blur ω·t_exp is recorded per
frame (``meta["continuous"]``) and per pass (journal event ``continuous_pass``).

ω is the engine's ``speed_dps`` if set, otherwise the plan's ω per condition
(:func:`m2s2hil.plan.estimate_continuous`), limited so the blur at ``radius_px`` from the
axis stays under ``max_blur_px`` when that is set. A frame is accepted within
``max_angle_error_deg`` of its mark, by default 1.5 frame spacings (at most half an
azimuth step).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from m2s2hil.config import RigConfig
from m2s2hil.drivers.errors import FrameIncomplete
from m2s2hil.engine.darks import Dark, SessionDarks
from m2s2hil.engine.exposure import AutoExposure, CameraControl
from m2s2hil.engine.exposure_search import ExposureResult
from m2s2hil.engine.frames import FrameStages
from m2s2hil.engine.marks import PassReport, blur_estimate, run_pass
from m2s2hil.plan import CaptureEvent, ContinuousEstimate, Sweep, estimate_continuous
from m2s2hil.rig.opened import Rig
from m2s2hil.rig.operations import RigOps
from m2s2hil.store.session import SessionStore

Submit = Callable[[CaptureEvent, np.ndarray, dict, Dark | None, Any], None]


@dataclass(frozen=True)
class SpeedSettings:
    """The engine's continuous-mode options (see the module docstring)."""

    speed_dps: float | None
    max_blur_px: float | None
    max_angle_error_deg: float | None
    radius_px: float

    def estimate(self, sweep: Sweep, config: RigConfig) -> ContinuousEstimate:
        """The plan's continuous model at this blur limit (or speed override)."""
        blur = self.max_blur_px
        if self.speed_dps is not None:
            # ω = speed for the shortest exposure (exactly, when all conditions share it)
            t = min(sweep.exposure_for(c) for c in sweep.lighting)
            blur = self.radius_px * math.radians(self.speed_dps * t)
        return estimate_continuous(sweep, config, radius_px=self.radius_px, max_blur_px=blur)

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


class PassCapture:
    """Captures continuous passes and keeps their reports and the per-frame blur for the run summary.

    The engine supplies ``set_condition(event)`` (lamps of the event's condition on),
    ``submit(event, data, meta, dark, truth)`` (into the pipeline) and ``should_stop()``
    (a pause or abort was asked for: the pass stops early, its remaining marks stay pending).
    """

    def __init__(self, rig: Rig, store: SessionStore, sweep: Sweep, ops: RigOps, *, camera: CameraControl,
                 exposure: AutoExposure, darks: SessionDarks, frames: FrameStages,
                 set_condition: Callable[[CaptureEvent], None], submit: Submit,
                 should_stop: Callable[[], bool]) -> None:
        self.rig = rig
        self.store = store
        self.sweep = sweep
        self.ops = ops
        self.camera = camera
        self.exposure = exposure
        self.darks = darks
        self.frames = frames
        self.set_condition = set_condition
        self.submit = submit
        self.should_stop = should_stop
        self.blur_deg: list[float] = []  # per stored frame
        self.passes: list[dict] = []  # per pass: its report

    def capture(self, todo: list[CaptureEvent], settings: SpeedSettings, attempt: int) -> None:
        """One pass over the marks of ``todo`` (events of one pass); FrameIncomplete if marks were missed."""
        clock = self.rig.clock
        config = self.rig.config
        first = todo[0]
        assert first.tilt_deg is not None and first.lighting is not None
        self.set_condition(first)
        moved = ["tilt"] if self.ops.move("tilt", first.tilt_deg) else []
        exposure, auto = self._exposure_for_pass(first)
        dark = self.darks.for_setting(exposure, first.gain)
        speed = settings.omega(self.sweep, config, first.lighting, exposure)
        self.camera.configure(exposure, first.gain)
        blur = blur_estimate(speed, exposure, settings.radius_px)
        marks: dict[float, list[CaptureEvent]] = {}
        for ev in todo:
            assert ev.azimuth_deg is not None
            marks.setdefault(ev.azimuth_deg, []).append(ev)

        def on_match(match: Any, frame_info: list[dict]) -> None:
            evs = sorted(match.key, key=lambda e: e.frame)
            for ev, frame, extra in zip(evs, match.frames, match.extras, strict=False):
                meta = self.frames.meta(ev, frame, exposure, dark, extra["clock_s"], extra["wall"], attempt)
                meta["pose"] = {"turntable_deg": extra["angle_deg"], "tilt_deg": self.ops.pose()["tilt"],
                                "turntable_source": "interpolated read-back at mid-exposure"}
                meta["continuous"] = {
                    "mark_deg": match.mark_deg, "angle_deg": extra["angle_deg"],
                    "error_deg": extra["angle_deg"] - match.mark_deg, "speed_dps": extra["speed_dps"],
                    "commanded_speed_dps": speed, **blur.to_dict(),
                }
                if auto is not None:
                    meta["auto_exposure"] = auto.to_dict()
                self.blur_deg.append(blur.deg)
                self.submit(ev, frame.data, meta, dark, extra.get("truth"))

        def on_frame(frame: Any) -> dict:
            return {"clock_s": clock.monotonic(), "wall": clock.wall(), "truth": self.frames.truth()}

        self.ops.wait_ready(clock.monotonic() + self.ops.settle_s(moved, first.settle_s))
        report: PassReport = run_pass(
            self.rig, self.ops, marks=[(a, evs) for a, evs in marks.items()], speed_dps=speed,
            exposure_s=exposure, k=self.sweep.frames_per_pose,
            window_deg=settings.match_window(self.sweep, config, speed, exposure),
            on_match=on_match, should_stop=self.should_stop, on_frame=on_frame,
            frame_timeout_s=exposure + self.camera.snap_timeout_s,
        )
        info = {"pass_index": first.pass_index, "lighting": first.lighting, "elevation": first.elevation,
                "exposure_s": exposure, **report.to_dict(), **blur.to_dict()}
        self.passes.append(info)
        self.store.record_event("continuous_pass", info)
        if report.stopped_early:
            return  # pause/abort: the engine's boundary handles it; what is left stays pending
        missing = [ev for _, evs in report.missing for ev in evs]
        if missing:
            raise FrameIncomplete(
                f"no frame matched to {len(report.missing)} azimuth mark(s) "
                f"({', '.join(f'{a:g}' for a, _ in report.missing[:5])} deg); "
                f"{report.dropped} frame(s) dropped in the pass",
                device=getattr(self.rig.camera, "name", "camera"), command="continuous pass",
            )

    def _exposure_for_pass(self, ev: CaptureEvent) -> tuple[float, ExposureResult | None]:
        if not self.exposure.needs_metering(ev):
            return self.exposure.exposure(ev)
        assert ev.azimuth_deg is not None
        self.ops.move("turntable", ev.azimuth_deg)  # meter at the pass's first mark
        self.ops.wait_ready(self.rig.clock.monotonic())
        return self.exposure.exposure(ev)
