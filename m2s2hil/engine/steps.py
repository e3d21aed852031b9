"""The capture steps the runner drives: a typed protocol and what both implementations share.

The runner (:class:`~m2s2hil.engine.runner.Engine`) owns states, safe boundaries, pause and
abort, the fault policy, the pipeline and events; it knows nothing of how a capture is done.
That is a :class:`CaptureSteps` implementation's job, in the shape of pymmcore-plus's
``PMDAEngine`` (setup, execute an event, teardown):

- :class:`~m2s2hil.engine.stop_and_go.StopAndGoSteps`: move, settle, snap, one event at a time;
- :class:`~m2s2hil.engine.continuous_steps.ContinuousSteps`: one turntable pass per unit.

Both capture the planned darks the same way (:class:`SharedSteps`). ``execute`` is a
generator of :mod:`m2s2hil.engine.messages` (frames, darks stored, conditions reached, lens
requests, checkpoints): the steps never call into the runner. A step raises on a fault (the
runner applies the policy).
"""

from __future__ import annotations

import contextlib
from collections.abc import Hashable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from m2s2hil.engine.darks import SessionDarks
from m2s2hil.engine.exposure import CameraControl, ExposureMeter
from m2s2hil.engine.frames import FrameStages
from m2s2hil.engine.messages import ConditionReached, LensRequest, StepGen
from m2s2hil.plan import CaptureEvent, Sweep
from m2s2hil.rig.opened import Rig
from m2s2hil.rig.operations import RigOps
from m2s2hil.store.session import SessionStore


@dataclass
class CaptureKit:
    """The helpers a capture is made of, shared by the steps and (frames) the runner's pipeline."""

    rig: Rig
    store: SessionStore
    sweep: Sweep
    ops: RigOps
    camera: CameraControl
    exposure: ExposureMeter
    darks: SessionDarks
    frames: FrameStages

    def set_condition(self, ev: CaptureEvent) -> StepGen[None]:
        """The lamps of the event's lighting condition on (switched only when they change)."""
        assert ev.lighting is not None
        yield ConditionReached(ev)
        self.ops.set_lamps(frozenset(self.rig.config.lamp_channels(ev.lighting)))


class CaptureSteps(Protocol):
    """How captures are done; the runner calls these from its own thread only."""

    def setup(self) -> None:
        """Before the first event of a run: restore what an earlier run of the session learnt,
        mount the scene."""

    def unit_key(self, event: CaptureEvent) -> Hashable | None:
        """Events with the same non-None key are captured together as one unit."""

    def execute(self, unit: Sequence[CaptureEvent], attempt: int) -> StepGen[None]:
        """Capture ``unit`` (pending events, in plan order), yielding what it captures and
        needs; ``attempt`` is 1 + failed tries. Raises on a fault; a unit stopped at a
        :class:`~m2s2hil.engine.messages.Checkpoint` leaves its rest pending."""

    def recover(self) -> None:
        """After a fault: stop any acquisition and command every camera setting again."""

    def forget(self) -> None:
        """After a pause: command every camera setting again."""

    def teardown(self) -> None:
        """After the run, whatever ended it (the rig is already safe). Never raises."""

    def lower_bound_s(self) -> float:
        """The plan's lower bound on the duration of the whole sweep in this mode."""

    def summary(self) -> dict[str, Any]:
        """What the run summary records about the steps (e.g. blur, passes, auto exposure)."""


class SharedSteps:
    """What stop-and-go and continuous capture do alike: darks, set-up and teardown."""

    def __init__(self, kit: CaptureKit) -> None:
        self.kit = kit
        self.rig = kit.rig
        self.ops = kit.ops

    def setup(self) -> None:
        self.kit.exposure.restore()
        self.rig.mount(self.kit.sweep.satellite, self.kit.sweep.build)

    def capture_dark(self, ev: CaptureEvent) -> StepGen[None]:
        yield from self.kit.darks.capture(ev)

    def lit_unit(self) -> StepGen[None]:
        """Before a lit unit: the lens cap off (on a real rig, as the operator confirms)."""
        yield LensRequest(False)

    def recover(self) -> None:
        self.kit.camera.forget()
        with contextlib.suppress(Exception):
            self.rig.camera.stop_stream()

    def forget(self) -> None:
        self.kit.camera.forget()

    def teardown(self) -> None:
        with contextlib.suppress(Exception):
            self.rig.camera.stop_stream()

    def summary(self) -> dict[str, Any]:
        results = self.kit.exposure.results
        return {"auto_exposure": {c: r.exposure_s for c, r in results.items()}} if results else {}
