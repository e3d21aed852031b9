"""Super-pixel hypercube extraction: one value per band per n×n cell (10×512×512 for the TOUCAN).

A band that occupies several positions of the cell gets the mean of those positions. The result
has 1/n of the sensor's resolution and a per-band spatial offset: band b's value sits at the
centroid of its positions, not at the cell centre (see docs/processing.md).
"""

from __future__ import annotations

import numpy as np
from numba import parallel_chunksize

from m2s2hil.processing import kernels
from m2s2hil.processing.demosaic import Demosaicer
from m2s2hil.processing.errors import FrameShapeError
from m2s2hil.processing.mosaic import MosaicLayout

_NO_DARK = np.zeros((0, 0), np.uint16)
_NO_DARK.flags.writeable = False  # the kernel gets a read-only dark always: one specialisation
_NO_QC = np.zeros((0, 1, 1), np.uint16)


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

    def __init__(self, layout: MosaicLayout, shape: tuple[int, int]) -> None:
        super().__init__(layout, shape)
        self._tables = position_tables(layout)

    def _run(self, mosaic: np.ndarray) -> None:
        # serial on purpose: the work is memory-bound (a second thread gains little even on an idle
        # machine), and on a shared one a parallel region can wait several ms for a descheduled
        # worker or for an OpenMP pool spinning against the pipeline's own threads
        kernels.superpixel_rows(mosaic, *self._tables, self.out, 0, self.out_shape[1])

    def process_raw(
        self,
        raw: np.ndarray,
        dark: np.ndarray | None,
        full_scale: int,
        cell_sat: np.ndarray,
        qc_rows: np.ndarray | None = None,
        qc_step: int = 8,
    ) -> tuple[np.ndarray, int]:
        """``(cube, saturated raw pixels)`` for a raw uint16 frame: dark subtraction (clipped at 0),
        saturation flags per cell into ``cell_sat`` and super-pixel in one pass (the same cube as
        ``process(subtract_dark(raw, dark))``). Every ``qc_step``-th cell row of the corrected mosaic
        goes into ``qc_rows`` (ceil(H/n / qc_step), n, W) when given."""
        h, w = self.shape
        n = self.layout.n
        if raw.shape != self.shape or raw.dtype != np.uint16 or not raw.flags.c_contiguous:
            raise FrameShapeError(
                f"{self.name}: raw must be C-contiguous uint16 {self.shape}, got {raw.dtype} {raw.shape}"
            )
        d = _NO_DARK if dark is None else np.ascontiguousarray(dark)
        if d.flags.writeable:  # a read-only view: numba compiles the kernel once, not per flag
            d = d.view()
            d.flags.writeable = False
        if dark is not None and (d.shape != self.shape or d.dtype != np.uint16):
            raise FrameShapeError(
                f"{self.name}: dark {d.dtype} {d.shape} does not fit raw frame uint16 {self.shape}"
            )
        if cell_sat.shape != self.out_shape[1:] or cell_sat.dtype != np.bool_:
            raise FrameShapeError(
                f"{self.name}: cell_sat must be bool {self.out_shape[1:]}, "
                f"got {cell_sat.dtype} {cell_sat.shape}"
            )
        qc = _NO_QC if qc_rows is None else qc_rows
        want = (-(-(h // n) // qc_step), n, w)
        if qc_rows is not None and (qc.shape != want or qc.dtype != np.uint16):
            raise FrameShapeError(f"{self.name}: qc_rows must be uint16 {want}, got {qc.dtype} {qc.shape}")
        # blocks of cell rows handed out one at a time, as the demosaicers' kernels: a worker that
        # loses its core has its blocks taken over instead of stalling the frame
        with parallel_chunksize(1):
            n_sat = kernels.dark_superpixel_rows(
                raw, d, full_scale, *self._tables, self.out, cell_sat, qc, qc_step, self._blocks(h // n)
            )
        return self.out, int(n_sat)

    def centroids(self) -> np.ndarray:
        """(bands, 2) mean (row, col) position of each band inside the cell."""
        return np.array([np.mean(ps, axis=0) for ps in self.layout.positions], dtype=np.float64)
