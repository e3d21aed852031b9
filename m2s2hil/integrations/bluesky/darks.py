"""The engine's master darks driven from a bluesky plan: the lens cap, and the steps run to their end.

The darks are :class:`m2s2hil.engine.darks.SessionDarks`' own (same capture, master-dark build,
``store.write_dark``, temperature retakes): its methods are engine steps, generators of
:mod:`m2s2hil.engine.messages` that the engine's runner consumes. :func:`run_step` stands in for
the runner outside it. The one message it cannot answer is a
:class:`~m2s2hil.engine.messages.LensRequest` on a real rig (``rig.lens_needs_operator``): the
runner parks for the operator there, and a bluesky plan has no operator console to park on, so
the plan stops with :class:`LensCapNeeded` instead (a clear error, not a pause: resuming a
RunEngine replays from its last checkpoint, which would re-run half a dark). A simulated rig caps
its own lens (``rig.cap_lens``) and never asks.
"""

from __future__ import annotations

from typing import TypeVar

from m2s2hil.engine.messages import LensRequest, StepGen
from m2s2hil.errors import UsageError
from m2s2hil.rig.opened import Rig

T = TypeVar("T")


class LensCapNeeded(UsageError):
    """A master dark on a real rig: only the operator can put the lens cap on (see the module docstring)."""


def lens_cap_message(what: str) -> str:
    return (f"{what}: the master darks need the lens cap on, and on a real rig only the operator "
            "can put it on; m2s2_sweep does not park for the operator. Take the darks with "
            "`m2s2hil capture` (it pauses for the cap) into this session first, or run a sweep "
            "with dark.frames = 0 (its frames then carry no dark)")


def run_step(step: StepGen[T], rig: Rig) -> T:
    """Run an engine step to its end and return its value; the messages it yields are the
    runner's bookkeeping (a dark stored, a condition reached), except a lens request on a real
    rig, which raises :class:`LensCapNeeded`."""
    try:
        msg = next(step)
        while True:
            if isinstance(msg, LensRequest) and rig.lens_needs_operator:
                step.close()
                raise LensCapNeeded(lens_cap_message(f"lens cap {'on' if msg.capped else 'off'}"))
            msg = step.send(None)
    except StopIteration as done:
        return done.value
