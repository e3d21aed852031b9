"""Stop-and-go capture: one event at a time, the stage standing still for each snap.

A *frame* event: the lamps of its condition on (only when they change), tilt then turntable
moved and verified against the read-back within the axis tolerance, settle and lamp warm-up
waited (the warm-up overlaps the move), the exposure (:mod:`m2s2hil.engine.exposure`:
automatic once per lighting condition when the sweep asks for it), one snap; the frame is
yielded to the runner (its pipeline). A *dark* event: master darks (:mod:`m2s2hil.engine.darks`);
a dark taken under the operator's cap in the middle of a frame (lamps and pose given up
while parked) makes the frame start over.

Overlapped (``overlap``, the default: ``EngineOptions.overlap``): once a frame's exposure has
ended, the stage heads for the plan's next pose while the frame is read out
(:meth:`~m2s2hil.engine.exposure.CameraControl.snap_then`); the next event's move then only
waits for it and verifies the read-back. The move is a guess (the next event run may be a
requeued one): a wrong guess costs a move, never a frame, since every frame still moves to
its own pose and verifies it. The pose recorded is the one read back before the exposure.
The lamps switch after the readout (a frame is rendered, and a real sensor read, with the
lamps of its own condition), so a lighting change's warm-up runs alongside the rest of the move.
"""

from __future__ import annotations

import itertools
from collections.abc import Hashable, Sequence

from m2s2hil.engine.messages import FrameCaptured, StepGen
from m2s2hil.engine.steps import CaptureKit, SharedSteps
from m2s2hil.plan import CaptureEvent, estimate


class StopAndGoSteps(SharedSteps):
    """:class:`~m2s2hil.engine.steps.CaptureSteps` for ``mode = "stop-and-go"``."""

    def __init__(self, kit: CaptureKit, *, overlap: bool = True) -> None:
        super().__init__(kit)
        self.overlap = overlap
        self._next: dict[int, CaptureEvent] | None = None  # plan index -> the frame after it

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
        cfg = self.rig.config
        return estimate(self.kit.sweep.expand(cfg), cfg, overlap=self.overlap).lower_bound_s

    def _planned_next(self, ev: CaptureEvent) -> CaptureEvent | None:
        if self._next is None:
            events = self.kit.sweep.expand(self.rig.config)
            self._next = {a.index: b for a, b in itertools.pairwise(events) if b.kind == "frame"}
        return self._next.get(ev.index)

    def _head_for_next(self, ev: CaptureEvent) -> None:
        """After ``ev``'s exposure: start the move to the plan's next pose (tilt first, as
        :meth:`RigOps.move_pose` moves)."""
        nxt = self._planned_next(ev)
        if nxt is None or nxt.azimuth_deg is None or nxt.tilt_deg is None:
            return
        self.ops.start_move("tilt", nxt.tilt_deg)
        self.ops.start_move("turntable", nxt.azimuth_deg)

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
        pose = self.ops.pose()  # verified before the exposure; the stage may leave during the readout
        if self.overlap:
            frame = kit.camera.snap_then(exposure, lambda: self._head_for_next(ev))
        else:
            frame = kit.camera.snap(exposure)
        truth = kit.frames.truth()
        dark = yield from kit.darks.check_temperature(dark, exposure, ev.gain, frame.temperature_c)
        if kit.darks.lens_cycles != cycles:
            return False
        meta = kit.frames.meta(ev, frame, exposure, dark, t_clock, t_wall, attempt)
        meta["pose"] = {"turntable_deg": pose["turntable"], "tilt_deg": pose["tilt"]}
        if auto is not None:
            meta["auto_exposure"] = auto.to_dict()
        yield FrameCaptured(ev, frame.data, meta, dark, truth)
        return True
