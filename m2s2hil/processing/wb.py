"""Weighted bilinear (WB) demosaicing at full resolution (Brauers & Aach 2006).

Each band's sparse plane is interpolated with the bilinear (tent) kernel of half-width n, aligned
on the band's own sample positions, so every band keeps its true phase. For a band with one
position per cell this is exactly the normalised 7×7 tent convolution of the literature. A band
with k positions has k rectangular sub-lattices; its estimate is a convex blend of their bilinear
estimates with weights ∝ 1/e_i, where e_i = fy(1−fy) + fx(1−fx) is the bilinear error factor of
sub-lattice i at that phase (0 on its own samples, so measured values pass through unchanged).
Any convex blend of exact linear interpolants is exact for linear ramps.
"""

from __future__ import annotations

import numpy as np

from m2s2hil.processing import kernels
from m2s2hil.processing.demosaic import Demosaicer
from m2s2hil.processing.mosaic import MosaicLayout
from m2s2hil.processing.superpixel import position_tables

_EMPTY = np.zeros((0, 0), np.float32)
_NO_SCALE = np.zeros(0, np.float32)


def blend_weights(layout: MosaicLayout) -> np.ndarray:
    """(positions, n, n) weight of each position's sub-lattice at each phase (sums to 1 per band)."""
    n = layout.n
    pr, pc, start, count = position_tables(layout)
    wts = np.zeros((len(pr), n, n), np.float64)
    for s, cnt in zip(start, count, strict=True):
        for py in range(n):
            for px in range(n):
                fy = ((py - pr[s : s + cnt]) % n) / n
                fx = ((px - pc[s : s + cnt]) % n) / n
                err = fy * (1 - fy) + fx * (1 - fx)
                if np.any(err == 0):
                    wts[s : s + cnt, py, px] = err == 0
                else:
                    inv = 1.0 / err
                    wts[s : s + cnt, py, px] = inv / inv.sum()
    return wts


class WBTables:
    """Everything the WB kernel needs for one layout and frame width.

    The same kernel does nearest-neighbour demosaicing when given 0/1 vertical fractions and
    one-hot blend weights (``nearest.NearestTables``).
    """

    nearest = False

    def __init__(self, layout: MosaicLayout, width: int) -> None:
        n = layout.n
        self.pr, self.pc, self.start, self.count = position_tables(layout)
        self.fyt = self.fractions(layout)
        self.wrows = np.tile(self.weights(layout), (1, 1, width // n)).astype(np.float32)

    def fractions(self, layout: MosaicLayout) -> np.ndarray:
        """(positions, n): vertical fraction of each position's sub-lattice at each row phase."""
        n = layout.n
        return (((np.arange(n)[None, :] - self.pr[:, None]) % n) / n).astype(np.float32)

    def weights(self, layout: MosaicLayout) -> np.ndarray:
        return blend_weights(layout)

    def run(
        self,
        src: np.ndarray,
        out: np.ndarray,
        nblocks: int,
        add: np.ndarray = _EMPTY,
        scale: np.ndarray = _NO_SCALE,
    ) -> None:
        """WB of ``src`` into ``out``; with ``add``, ``out[b] = scale[b] * (WB_b(src) + add)``."""
        kernels.wb_kernel(
            src,
            self.pr,
            self.pc,
            self.start,
            self.count,
            self.fyt,
            self.wrows,
            add,
            scale,
            self.nearest,
            out,
            nblocks,
        )


class WBDemosaicer(Demosaicer):
    name = "wb"

    def __init__(self, layout: MosaicLayout, shape: tuple[int, int]) -> None:
        super().__init__(layout, shape)
        self._tables = WBTables(layout, self.shape[1])
        self._nblocks = self._blocks(self.shape[0] // layout.n)

    def _run(self, mosaic: np.ndarray) -> None:
        self._tables.run(mosaic, self.out, self._nblocks)
