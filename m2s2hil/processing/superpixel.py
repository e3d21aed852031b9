"""Super-pixel hypercube extraction: one value per band per n×n cell (10×512×512 for the TOUCAN).

A band that occupies several positions of the cell gets the mean of those positions. The result
has 1/n of the sensor's resolution and a per-band spatial offset: band b's value sits at the
centroid of its positions, not at the cell centre (see docs/processing.md).
"""

from __future__ import annotations

import numpy as np

from m2s2hil.processing import kernels
from m2s2hil.processing.demosaic import Demosaicer
from m2s2hil.processing.mosaic import MosaicLayout


def position_tables(layout: MosaicLayout) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cell positions grouped by band: ``(pr, pc, band_start, band_count)``."""
    order = [p for ps in layout.positions for p in ps]
    pr = np.array([p[0] for p in order], dtype=np.int64)
    pc = np.array([p[1] for p in order], dtype=np.int64)
    count = np.array(layout.counts, dtype=np.int64)
    start = np.concatenate(([0], np.cumsum(count)[:-1])).astype(np.int64)
    return pr, pc, start, count


class SuperPixelDemosaicer(Demosaicer):
    name = "superpixel"
    full_resolution = False

    def __init__(self, layout: MosaicLayout, shape: tuple[int, int]) -> None:
        super().__init__(layout, shape)
        self._tables = position_tables(layout)

    @property
    def support_radius(self) -> int:
        return 0  # a saturated raw pixel spoils exactly its own cell

    def _run(self, mosaic: np.ndarray) -> None:
        # serial on purpose: 0.9 ms of work gains 0.4 ms from a second thread on an idle machine,
        # but on a shared one a parallel region can wait several ms for a descheduled worker
        kernels.superpixel_rows(mosaic, *self._tables, self.out, 0, self.out_shape[1])

    def centroids(self) -> np.ndarray:
        """(bands, 2) mean (row, col) position of each band inside the cell."""
        return np.array([np.mean(ps, axis=0) for ps in self.layout.positions], dtype=np.float64)
