"""What the simulated TOUCAN renders into a frame: the pluggable frame source.

A source returns a uint16 (height, width) mosaic with values below ``2**bit_depth``;
``gain`` is the linear factor of the ``Gain`` feature. A source whose ``capture`` also takes
a ``start_s`` keyword is told when the frame's exposure began (clock time: the trigger, or
the free-running frame clock), so it can render the exposure interval, motion included. The
camera renders a frame when the host starts reading it, after the exposure.
"""

from __future__ import annotations

import inspect
from typing import Any, Protocol

import numpy as np


class FrameSource(Protocol):
    def capture(self, exposure_s: float, gain: float) -> np.ndarray: ...


class GradientSource:
    """Deterministic default content: a diagonal ramp scaled by exposure × gain.

    Full scale is reached at exposure × gain = ``full_at_s``; the result is cached per
    setting so free-running at 65 fps costs no rendering.
    """

    def __init__(self, width: int, height: int, bit_depth: int = 10, full_at_s: float = 0.05) -> None:
        self.width, self.height, self.bit_depth, self.full_at_s = width, height, bit_depth, full_at_s
        self._cache: dict[tuple[float, float], np.ndarray] = {}

    def capture(self, exposure_s: float, gain: float) -> np.ndarray:
        key = (exposure_s, gain)
        img = self._cache.get(key)
        if img is None:
            top = (1 << self.bit_depth) - 1
            level = min(1.0, exposure_s * gain / self.full_at_s)
            ramp = np.add.outer(np.arange(self.height), np.arange(self.width)).astype(np.float32)
            ramp *= top * level / max(1, self.width + self.height - 2)
            img = ramp.astype(np.uint16)
            img.setflags(write=False)
            self._cache = {key: img}
        return img


def render(source: FrameSource, exposure_s: float, gain: float, start_s: float,
           shape: tuple[int, int]) -> np.ndarray:
    """The frame ``source`` gives for an exposure that began at ``start_s``; a frame of another
    ``shape`` than the sensor's (height, width) is a ValueError."""
    if _takes_start(source):
        timed: Any = source  # its capture() takes start_s too (checked above)
        img = timed.capture(exposure_s, gain, start_s=start_s)
    else:
        img = source.capture(exposure_s, gain)
    if img.shape != shape:
        raise ValueError(f"frame source gave {img.shape}, camera is {shape[0]}x{shape[1]}")
    return img


def _takes_start(source: Any) -> bool:
    """Whether ``source.capture`` accepts the ``start_s`` keyword."""
    try:
        params = inspect.signature(source.capture).parameters
    except (TypeError, ValueError):
        return False
    return "start_s" in params or any(p.kind is p.VAR_KEYWORD for p in params.values())
