"""Capture plans: a :class:`Sweep` (what to capture and how), the :class:`CaptureEvent` list it
expands to in the cheapest order, and how long that takes.

``model`` holds the vocabulary (exposure and dark policies, events and their ids), ``estimate``
the duration model and its stop-and-go lower bound, ``floor`` the physical floor of any mode,
``order`` the search over loop nestings, ``sweep`` the sweep itself; they import one way
(model ← estimate ← floor ← order ← sweep). The names below are the package's API.
"""

from m2s2hil.plan.estimate import (
    ContinuousEstimate,
    PlanEstimate,
    estimate,
    estimate_continuous,
    move_time_s,
    switch_warmup_s,
)
from m2s2hil.plan.floor import PhysicalFloor, physical_floor
from m2s2hil.plan.model import (
    AXES,
    DEFAULT_EXPOSURE_S,
    MAX_BRACKET,
    AutoExposureSettings,
    CaptureEvent,
    DarkPolicy,
    FixedExposure,
    PlanError,
    bracket_base_id,
    dark_event,
    dark_event_id,
    frame_event_id,
)
from m2s2hil.plan.order import commanded_azimuths
from m2s2hil.plan.sweep import Sweep, parse_sweep

__all__ = [
    "AXES",
    "DEFAULT_EXPOSURE_S",
    "MAX_BRACKET",
    "AutoExposureSettings",
    "CaptureEvent",
    "ContinuousEstimate",
    "DarkPolicy",
    "FixedExposure",
    "PhysicalFloor",
    "PlanError",
    "PlanEstimate",
    "Sweep",
    "bracket_base_id",
    "commanded_azimuths",
    "dark_event",
    "dark_event_id",
    "estimate",
    "estimate_continuous",
    "frame_event_id",
    "move_time_s",
    "parse_sweep",
    "physical_floor",
    "switch_warmup_s",
]
