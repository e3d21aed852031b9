"""Stop-and-go capture: one event at a time, the stage standing still for each snap.

A *frame* event: the lamps of its condition on (only when they change), tilt then turntable
moved and verified against the read-back within the axis tolerance, settle and lamp warm-up
waited (the warm-up overlaps the move), the exposure (:mod:`m2s2hil.engine.exposure`:
automatic once per lighting condition when the sweep asks for it), one snap; the frame goes
to the runner's pipeline. A *dark* event: master darks (:mod:`m2s2hil.engine.darks`).
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence

from m2s2hil.engine.steps import SharedSteps
from m2s2hil.plan import CaptureEvent, estimate


class StopAndGoSteps(SharedSteps):
    """:class:`~m2s2hil.engine.steps.CaptureSteps` for ``mode = "stop-and-go"``."""

    def unit_key(self, event: CaptureEvent) -> Hashable | None:
        return None  # every event on its own

    def execute(self, unit: Sequence[CaptureEvent], attempt: int) -> None:
        ev = unit[0]
        if ev.kind == "dark":
            self.capture_dark(ev)
        else:
            self._capture_frame(ev, attempt)

    def lower_bound_s(self) -> float:
        return estimate(self.kit.sweep.expand(self.rig.config), self.rig.config).lower_bound_s

    def _capture_frame(self, ev: CaptureEvent, attempt: int) -> None:
        kit = self.kit
        clock = self.rig.clock
        assert ev.azimuth_deg is not None and ev.tilt_deg is not None
        kit.set_condition(ev)
        moved = self.ops.move_pose(ev.azimuth_deg, ev.tilt_deg)
        self.ops.wait_ready(clock.monotonic() + self.ops.settle_s(moved, ev.settle_s))
        exposure, auto = kit.exposure.exposure(ev)
        dark = kit.darks.for_setting(exposure, ev.gain)
        kit.camera.configure(exposure, ev.gain)
        t_clock, t_wall = clock.monotonic(), clock.wall()
        frame = kit.camera.snap(exposure)
        truth = kit.frames.truth()
        dark = kit.darks.check_temperature(dark, exposure, ev.gain, frame.temperature_c)
        meta = kit.frames.meta(ev, frame, exposure, dark, t_clock, t_wall, attempt)
        if auto is not None:
            meta["auto_exposure"] = auto.to_dict()
        kit.hooks.submit(ev, frame.data, meta, dark, truth)
