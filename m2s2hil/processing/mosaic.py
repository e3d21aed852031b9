"""The periodic n×n multispectral filter array (MSFA): layout helpers and cube→mosaic sampling.

Conventions used throughout ``m2s2hil.processing``:

- ``layout[r][c]`` is the band index seen by sensor pixel ``(y, x)`` with ``y % n == r`` and
  ``x % n == c`` (row-major, origin at the top-left pixel of the frame).
- A band may occupy several positions of the cell (the TOUCAN's 10 bands on 16 positions);
  each position's samples form a rectangular sub-lattice ``(r + k·n, c + l·n)``.
- Cubes are band-first: ``(bands, height, width)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from m2s2hil.processing.errors import FrameShapeError, LayoutError


@dataclass(frozen=True)
class MosaicLayout:
    """An n×n MSFA cell of band indices ``0 .. n_bands-1`` (every band at least once)."""

    pattern: tuple[tuple[int, ...], ...]
    n_bands: int

    def __post_init__(self) -> None:
        n = len(self.pattern)
        if n == 0 or any(len(row) != n for row in self.pattern):
            raise LayoutError(f"MSFA layout must be a square n×n array of band indices, got {self.pattern!r}")
        flat = [b for row in self.pattern for b in row]
        bad = sorted({b for b in flat if not (isinstance(b, int | np.integer) and 0 <= b < self.n_bands)})
        if bad:
            raise LayoutError(f"MSFA layout names bands {bad} outside 0..{self.n_bands - 1}")
        missing = sorted(set(range(self.n_bands)) - set(flat))
        if missing:
            raise LayoutError(f"MSFA layout has no position for bands {missing}")

    @classmethod
    def from_pattern(
        cls, pattern: Sequence[Sequence[int]] | np.ndarray, n_bands: int | None = None
    ) -> MosaicLayout:
        rows = tuple(tuple(int(b) for b in row) for row in np.asarray(pattern).tolist())
        if n_bands is None:
            n_bands = 1 + max((b for row in rows for b in row), default=-1)
        return cls(rows, int(n_bands))

    @classmethod
    def from_camera(cls, model) -> MosaicLayout:  # m2s2hil.config.CameraModel (no import cycle)
        return cls.from_pattern(model.layout, model.n_bands)

    @property
    def n(self) -> int:
        return len(self.pattern)

    @cached_property
    def array(self) -> np.ndarray:
        return np.array(self.pattern, dtype=np.int64)

    @cached_property
    def positions(self) -> tuple[tuple[tuple[int, int], ...], ...]:
        """``positions[b]`` = the cell positions ``(r, c)`` of band ``b``, in raster order."""
        out: list[list[tuple[int, int]]] = [[] for _ in range(self.n_bands)]
        for r, row in enumerate(self.pattern):
            for c, b in enumerate(row):
                out[b].append((r, c))
        return tuple(tuple(p) for p in out)

    @cached_property
    def counts(self) -> tuple[int, ...]:
        return tuple(len(p) for p in self.positions)

    def shifted(self, dy: int, dx: int) -> MosaicLayout:
        """The layout seen when the frame origin moves by ``(dy, dx)`` pixels.

        A sensor read with its first row/column dropped (a phase error) looks like
        ``layout.shifted(1, 0)`` / ``shifted(0, 1)``.
        """
        arr = np.roll(self.array, (-dy, -dx), axis=(0, 1))
        return MosaicLayout.from_pattern(arr, self.n_bands)

    def band_map(self, height: int, width: int) -> np.ndarray:
        """Per-pixel band index of an ``height×width`` frame."""
        n = self.n
        return np.tile(self.array, (-(-height // n), -(-width // n)))[:height, :width]

    def check_frame(self, shape: tuple[int, ...], what: str = "frame") -> tuple[int, int]:
        if len(shape) != 2:
            raise FrameShapeError(f"{what} must be a 2-D mosaic, got shape {shape}")
        h, w = shape
        if h < 2 * self.n or w < 2 * self.n or h % self.n or w % self.n:
            raise FrameShapeError(
                f"{what} of {h}×{w} pixels does not tile the {self.n}×{self.n} MSFA "
                f"(needs multiples of {self.n}, at least two cells each way)"
            )
        return h, w

    def describe(self) -> str:
        return " / ".join(" ".join(str(b) for b in row) for row in self.pattern)


def sample_cube(
    cube: np.ndarray,
    layout: MosaicLayout,
    *,
    offset: tuple[int, int] = (0, 0),
    full_scale: int | None = None,
    dtype: type | None = np.uint16,
) -> np.ndarray:
    """Mosaic a ``(bands, H, W)`` cube through the MSFA: pixel ``(y, x)`` keeps band ``layout[y%n][x%n]``.

    ``offset`` shifts the filter array by ``(dy, dx)`` pixels, simulating a frame read with the
    wrong phase. With an integer ``dtype`` values are rounded and clipped to ``[0, full_scale]``
    (an ADC); ``dtype=None`` keeps floats.
    """
    if cube.ndim != 3 or cube.shape[0] != layout.n_bands:
        raise FrameShapeError(f"cube must be ({layout.n_bands}, H, W), got {cube.shape}")
    _, h, w = cube.shape
    bands = layout.shifted(*offset).band_map(h, w) if offset != (0, 0) else layout.band_map(h, w)
    yy, xx = np.indices((h, w))
    mosaic = cube[bands, yy, xx]
    if dtype is None:
        return mosaic.astype(np.float32, copy=False)
    top = full_scale if full_scale is not None else np.iinfo(dtype).max
    return np.clip(np.rint(mosaic), 0, top).astype(dtype)


def cell_mean(cube: np.ndarray, n: int) -> np.ndarray:
    """Average a full-resolution cube over each n×n cell: the reference for super-pixel output."""
    b, h, w = cube.shape
    return cube.reshape(b, h // n, n, w // n, n).mean(axis=(2, 4), dtype=np.float64).astype(np.float32)
