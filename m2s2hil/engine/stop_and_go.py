"""Stop-and-go capture: one event at a time, the stage standing still for each snap.

A *frame* event: the lamps of its condition on (only when they change), tilt then turntable
moved and verified against the read-back within the axis tolerance, settle and lamp warm-up
waited (the warm-up overlaps the move), the exposure (:mod:`m2s2hil.engine.exposure`:
automatic once per lighting condition when the sweep asks for it), one snap; the frame is
yielded to the runner (its pipeline). A *dark* event: master darks (:mod:`m2s2hil.engine.darks`);
a dark taken under the operator's cap in the middle of a frame (lamps and pose given up
while parked) makes the frame start over.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence

from m2s2hil.engine.messages import FrameCaptured, StepGen
from m2s2hil.engine.steps import SharedSteps
from m2s2hil.plan import CaptureEvent, estimate


class StopAndGoSteps(SharedSteps):
    """:class:`~m2s2hil.engine.steps.CaptureSteps` for ``mode = "stop-and-go"``."""

    def unit_key(self, event: CaptureEvent) -> Hashable | None:
        return None  # every event on its own

    def execute(self, unit: Sequence[CaptureEvent], attempt: int) -> StepGen[None]:
        ev = unit[0]
        if ev.kind == "dark":
            yield from self.capture_dark(ev)
            return
        yield from self.lit_unit()
        while not (yield from self._capture_frame(ev, attempt)):
            pass  # the lens cap went on and off for a dark meanwhile: lamps and pose again

    def lower_bound_s(self) -> float:
        return estimate(self.kit.sweep.expand(self.rig.config), self.rig.config).lower_bound_s

    def _capture_frame(self, ev: CaptureEvent, attempt: int) -> StepGen[bool]:
        """One frame; False (nothing yielded for it) when a dark under the operator's cap
        interrupted it."""
        kit = self.kit
        clock = self.rig.clock
        assert ev.azimuth_deg is not None and ev.tilt_deg is not None
        cycles = kit.darks.lens_cycles
        yield from kit.set_condition(ev)
        moved = self.ops.move_pose(ev.azimuth_deg, ev.tilt_deg)
        self.ops.wait_ready(clock.monotonic() + self.ops.settle_s(moved, ev.settle_s))
        exposure, auto = kit.exposure.exposure(ev)
        dark = yield from kit.darks.for_setting(exposure, ev.gain)
        if kit.darks.lens_cycles != cycles:
            return False
        kit.camera.configure(exposure, ev.gain)
        t_clock, t_wall = clock.monotonic(), clock.wall()
        frame = kit.camera.snap(exposure)
        truth = kit.frames.truth()
        dark = yield from kit.darks.check_temperature(dark, exposure, ev.gain, frame.temperature_c)
        if kit.darks.lens_cycles != cycles:
            return False
        meta = kit.frames.meta(ev, frame, exposure, dark, t_clock, t_wall, attempt)
        if auto is not None:
            meta["auto_exposure"] = auto.to_dict()
        yield FrameCaptured(ev, frame.data, meta, dark, truth)
        return True
