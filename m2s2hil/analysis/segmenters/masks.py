"""Giving a segmenter the processor's clipping mask, when it takes one.

A segmenter may offer ``segment(cube, *, saturated=None)``: ``saturated`` is a bool mask of where
a band clipped, ``(H, W)`` (a pixel with any band clipped: ``ProcessedFrame.saturated_mask``) or
``(bands, H, W)`` (which bands: ``processing.stability.band_saturation``, what the evaluation gives,
``evaluation.loading.clipping_mask``). The cube alone cannot say where a band clipped in only one of
a duplicated band's mosaic positions: the averaged value is low but not at the clipping plateau
(docs/evaluation.md, tenth and eleventh passes). The mask is optional: a segmenter without the
keyword is called with the cube alone. SAM and the RGB baselines take none (an RGB value mixes the
bands with weights of both signs, so a clipped band bounds it neither way: ``segmenters.rgb``), nor
need a lab's own segmenter.
"""

from __future__ import annotations

import inspect
from typing import Any

import numpy as np


def takes_saturated(segment: Any) -> bool:
    """True when the callable ``segment`` accepts a ``saturated`` keyword."""
    try:
        params = inspect.signature(segment).parameters
    except (TypeError, ValueError):  # a builtin or C callable: assume the plain protocol
        return False
    return "saturated" in params or any(p.kind is p.VAR_KEYWORD for p in params.values())


def segment_masked(segmenter: Any, cube: np.ndarray, saturated: np.ndarray | None) -> np.ndarray:
    """``segmenter.segment(cube, saturated=saturated)`` when it takes the mask and one is given,
    else ``segmenter.segment(cube)``."""
    if saturated is not None and takes_saturated(segmenter.segment):
        return segmenter.segment(cube, saturated=saturated)
    return segmenter.segment(cube)
