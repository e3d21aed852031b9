"""What the capture steps yield to the runner (the shape of bluesky's plan messages).

A :class:`~m2s2hil.engine.steps.CaptureSteps` ``execute(unit, attempt)`` is a generator of
these; the runner consumes them one by one and is the only one to act on them: it submits a
:class:`FrameCaptured` to its pipeline, counts a :class:`DarkStored`, shows a
:class:`ConditionReached` in its status, answers a :class:`LensRequest` by parking for the
operator (a real rig's lens cap), and sends back, for every message, whether a pause or an
abort is pending; a long step (a continuous pass) asks at each :class:`Checkpoint` and stops
early when told so. Faults are raised, not yielded: the runner applies the fault policy.
"""

from __future__ import annotations

from collections.abc import Generator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from m2s2hil.plan import CaptureEvent

if TYPE_CHECKING:
    from m2s2hil.engine.darks import Dark


@dataclass(frozen=True)
class FrameCaptured:
    """A frame for the pipeline: its event, raw data, metadata, dark and simulator truth."""

    event: CaptureEvent
    data: np.ndarray
    meta: dict[str, Any]
    dark: Dark | None
    truth: Any = None


@dataclass(frozen=True)
class DarkStored:
    """A dark was captured and stored (a planned one counts as done)."""

    event: CaptureEvent


@dataclass(frozen=True)
class ConditionReached:
    """The event's lighting condition and elevation are now in front of the camera."""

    event: CaptureEvent


@dataclass(frozen=True)
class LensRequest:
    """The lens cap must be on (``capped``) or off from here on; on a real rig the runner parks
    until the operator confirms it (a no-op when it is so already)."""

    capped: bool


@dataclass(frozen=True)
class Checkpoint:
    """A point where a long step may stop early; the runner's reply is True to stop."""


StepMessage = FrameCaptured | DarkStored | ConditionReached | LensRequest | Checkpoint
T = TypeVar("T")
#: A step: yields messages, receives "stop now?" (None on the first resumption), returns ``T``.
StepGen = Generator[StepMessage, bool | None, T]

__all__ = ["Checkpoint", "ConditionReached", "DarkStored", "FrameCaptured", "LensRequest", "StepGen",
           "StepMessage"]
