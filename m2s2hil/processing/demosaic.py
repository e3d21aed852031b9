"""One interface for every demosaicing method: ``get_demosaicer(name, layout, shape).process(mosaic)``.

A demosaicer is built once per (method, layout, frame shape) and owns its output cube, which
``process`` overwrites on every call (no allocation per frame): copy the result if you keep it
past the next frame.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import ClassVar

import numpy as np
from numba import get_num_threads, parallel_chunksize

from m2s2hil.config import DEMOSAIC_METHODS, check_demosaic_method
from m2s2hil.processing.errors import FrameShapeError, LayoutError, UnknownMethodError
from m2s2hil.processing.mosaic import MosaicLayout
from m2s2hil.processing.stability import full_resolution, support_radius
from m2s2hil.processing.streaming import aligned_empty

#: The method names, known below processing (the rig file checks them without importing numba);
#: :func:`_registry` has a class for each (tests/test_config.py).
METHODS: tuple[str, ...] = DEMOSAIC_METHODS

INPUT_DTYPES = (np.dtype(np.uint16), np.dtype(np.float32))


class Demosaicer(ABC):
    """Turns an (H, W) mosaic (uint16, or float32 for averaged references) into a float32 cube."""

    name: ClassVar[str]

    def __init__(self, layout: MosaicLayout, shape: tuple[int, int]) -> None:
        if layout.n < 2:
            raise LayoutError(
                f"{self.name}: a 1×1 layout is a monochrome sensor, nothing to demosaic (an MSFA needs n ≥ 2)"
            )
        self.layout = layout
        self.shape = layout.check_frame(tuple(shape))
        # on a cache line: the full-resolution kernels stream their rows into it (streaming.py)
        self.out = aligned_empty(self.out_shape)

    @property
    def out_shape(self) -> tuple[int, int, int]:
        h, w = self.shape
        if self.full_resolution:
            return (self.layout.n_bands, h, w)
        n = self.layout.n
        return (self.layout.n_bands, h // n, w // n)

    @property
    def full_resolution(self) -> bool:
        """True when the cube has the sensor's resolution, False for one value per n×n cell
        (``stability.full_resolution``)."""
        return full_resolution(self.name)

    @property
    def support_radius(self) -> int:
        """How far (in raw pixels) one raw value can reach in the output: used to grow saturation
        masks (``stability.support_radius``, one table for every method)."""
        return support_radius(self.name, self.layout.n)

    def _blocks(self, rows: int) -> int:
        return max(1, min(rows, 8 * get_num_threads()))

    def process(self, mosaic: np.ndarray) -> np.ndarray:
        if mosaic.shape != self.shape:
            raise FrameShapeError(
                f"{self.name}: mosaic is {mosaic.shape}, this demosaicer was built for {self.shape}"
            )
        if mosaic.dtype not in INPUT_DTYPES:
            raise FrameShapeError(f"{self.name}: mosaic must be uint16 or float32, got {mosaic.dtype}")
        if not mosaic.flags.c_contiguous:
            mosaic = np.ascontiguousarray(mosaic)
        # dynamic scheduling of the kernels' blocks: on a shared machine a descheduled thread's
        # blocks are taken over by the other instead of stalling the frame (median WB 17 → 9 ms)
        with parallel_chunksize(1):
            self._run(mosaic)
        return self.out

    @abstractmethod
    def _run(self, mosaic: np.ndarray) -> None: ...

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name} n={self.layout.n} {self.shape[0]}×{self.shape[1]}>"


def as_layout(layout) -> MosaicLayout:
    """Accept a ``MosaicLayout``, a ``CameraModel`` or an n×n array of band indices."""
    if isinstance(layout, MosaicLayout):
        return layout
    if hasattr(layout, "layout") and hasattr(layout, "n_bands"):
        return MosaicLayout.from_camera(layout)
    return MosaicLayout.from_pattern(layout)


def _registry() -> dict[str, type[Demosaicer]]:
    from m2s2hil.processing.nearest import NearestDemosaicer
    from m2s2hil.processing.ppid import PPIDDemosaicer
    from m2s2hil.processing.superpixel import SuperPixelDemosaicer
    from m2s2hil.processing.wb import WBDemosaicer

    return {
        "superpixel": SuperPixelDemosaicer,
        "nearest": NearestDemosaicer,
        "wb": WBDemosaicer,
        "ppid": PPIDDemosaicer,
    }


def check_method(name: str) -> str:
    """``name`` if it is a demosaicing method, else :class:`UnknownMethodError`."""
    return check_demosaic_method(name, UnknownMethodError)


def get_demosaicer(name: str, layout, shape: tuple[int, int]) -> Demosaicer:
    """The demosaicer called ``name`` for this layout and frame shape (output preallocated)."""
    check_method(name)
    return _registry()[name](as_layout(layout), (int(shape[0]), int(shape[1])))
