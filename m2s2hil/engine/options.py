"""The engine's tuning options, in one place (defaults are what ``capture`` and the daemon use)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from m2s2hil.engine.continuous_steps import SpeedSettings

#: Builds a frame processor: ``factory(method, camera_model, dark=..., calibration=...)``.
ProcessorFactory = Callable[..., Any]


@dataclass(frozen=True)
class EngineOptions:
    """How a run is carried out (not what it captures: that is the sweep).

    ``process_depth``/``store_depth``: queue bounds of the pipeline; ``store_workers``:
    parallel writers; ``retry_skipped``: a resumed run retries earlier gaps; ``check_disk``:
    free space checked before anything moves; ``save_truth``: the simulator's label map stored
    with each frame (simulated rigs only); ``snap_timeout_s``: added to the exposure as the
    snap timeout (default: the rig's camera timeout); ``processor_factory``: the frame
    processor (default :class:`m2s2hil.processing.chain.FrameProcessor`); ``continuous``:
    the turntable speed and mark matching of continuous mode; ``overlap``: stop-and-go starts
    the move to the next pose as soon as an exposure ends (the readout runs during the move).
    """

    process_depth: int = 4
    store_depth: int = 4
    store_workers: int = 2
    retry_skipped: bool = True
    check_disk: bool = True
    save_truth: bool = True
    snap_timeout_s: float | None = None
    processor_factory: ProcessorFactory | None = None
    continuous: SpeedSettings = field(default_factory=SpeedSettings)
    overlap: bool = True

    @classmethod
    def of(cls, *, speed_dps: float | None = None, max_blur_px: float | None = None,
           max_angle_error_deg: float | None = None, radius_px: float = 400.0, **kw: Any) -> EngineOptions:
        """The options from flat keywords (the continuous ones folded into ``continuous``)."""
        return cls(continuous=SpeedSettings(speed_dps, max_blur_px, max_angle_error_deg, radius_px), **kw)
