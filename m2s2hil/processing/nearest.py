"""Nearest-neighbour demosaicing at full resolution: the baseline.

Each missing value is copied from the closest sample of that band (Euclidean distance; ties go to
the sample above, then to the left). It reproduces constants exactly and everything else only at
the band's own sample positions.
"""

from __future__ import annotations

import numpy as np

from m2s2hil.processing.demosaic import Demosaicer
from m2s2hil.processing.mosaic import MosaicLayout
from m2s2hil.processing.wb import WBTables


def nearest_offsets(layout: MosaicLayout) -> tuple[np.ndarray, np.ndarray]:
    """``(dy, dx)``, each (bands, n, n): offset from a pixel of phase (py, px) to its nearest band sample."""
    n = layout.n
    dy = np.zeros((layout.n_bands, n, n), np.int64)
    dx = np.zeros((layout.n_bands, n, n), np.int64)
    for b, ps in enumerate(layout.positions):
        for py in range(n):
            for px in range(n):
                cands = []
                for r, c in ps:
                    for ky in (-1, 0, 1):
                        for kx in (-1, 0, 1):
                            oy, ox = r + ky * n - py, c + kx * n - px
                            cands.append((oy * oy + ox * ox, oy, ox))
                _, dy[b, py, px], dx[b, py, px] = min(cands)  # ties: most negative dy, then dx
    return dy, dx


class NearestTables(WBTables):
    """WB's tables with the fractions rounded to the nearest sample row (ties up) and, for bands
    with several positions, all the weight on the sub-lattice holding the nearest sample."""

    nearest = True

    def fractions(self, layout: MosaicLayout) -> np.ndarray:
        n = layout.n
        frac = (np.arange(n)[None, :] - self.pr[:, None]) % n
        return (2 * frac > n).astype(np.float32)  # a tie (frac = n/2) keeps the row above

    def weights(self, layout: MosaicLayout) -> np.ndarray:
        n = layout.n
        dy, dx = nearest_offsets(layout)
        pos_index = {p: i for i, p in enumerate(zip(self.pr.tolist(), self.pc.tolist(), strict=True))}
        w = np.zeros((len(self.pr), n, n))
        for b in range(layout.n_bands):
            for py in range(n):
                for px in range(n):
                    w[pos_index[((py + dy[b, py, px]) % n, (px + dx[b, py, px]) % n)], py, px] = 1.0
        return w


class NearestDemosaicer(Demosaicer):
    name = "nearest"

    def __init__(self, layout: MosaicLayout, shape: tuple[int, int]) -> None:
        super().__init__(layout, shape)
        self._tables = NearestTables(layout, self.shape[1])
        self._nblocks = self._blocks(self.shape[0] // layout.n)

    def _run(self, mosaic: np.ndarray) -> None:
        self._tables.run(mosaic, self.out, self._nblocks)
