"""PPID: demosaicing through the pseudo-panchromatic image (Mihoubi, Losson, Mathon, Macaire 2017).

0. Band balancing (the paper's eqs. 21–22): each band is scaled so all bands share one mean
   level, and the scaling is undone at the end. Without it a dim band (431 nm under halogen
   light is ~15× darker than 877 nm) differs from the PPI by a full copy of the texture, which
   interpolates badly. The gains come from the frame itself (per-position means of every 8th
   cell row, as in ``stability.sublattice_means``).
1. PPI0 = balanced mosaic * M, a low-pass filter giving every MSFA position the same weight.
   M here is the normalised separable tent of half-width n (the bilinear kernel), so PPI0 is
   the mean over positions of their bilinear interpolations: phase-correct, and linear on
   linear ramps. (The paper's 5×5 M for 4×4 also weights positions equally but gives the PPI a
   periodic error on per-band ramps; see docs/processing.md.)
2. Edge-sensitive refinement: PPI(p) = R(p) + Σ_q γ_q (PPI0(q) − R(q)) / Σ_q γ_q over the 8 pixels
   q of p's band at distance n, γ_q = 1 / (1 + 1-2-1 mean |R(p+δ) − R(q+δ)|) (kernels.py).
3. Per band, the difference R − PPI at the band's samples is interpolated by WB and added back:
   Î_b = (PPI + WB_b(R − PPI)) / g_b.

All four steps run in one pass (``kernels.ppid_kernel``): each block of rows keeps the balanced
mosaic, PPI0, the edge weights and the PPI in small ring buffers, so memory sees the mosaic read
once and the cube written once (no frame-sized intermediates).
"""

from __future__ import annotations

import numpy as np

from m2s2hil.processing import kernels
from m2s2hil.processing.demosaic import Demosaicer
from m2s2hil.processing.mosaic import MosaicLayout
from m2s2hil.processing.stability import sublattice_means
from m2s2hil.processing.wb import WBTables

MAX_GAIN = 64.0


def gains_from_levels(band_mu: np.ndarray) -> np.ndarray:
    level = float(np.mean(band_mu))
    ok = band_mu > max(1e-6, level / MAX_GAIN)
    gains = np.where(ok, level / np.where(ok, band_mu, 1.0), 1.0)
    return np.clip(gains, 1.0 / MAX_GAIN, MAX_GAIN).astype(np.float32)


def ppi_filter(n: int) -> np.ndarray:
    """1-D half of the separable PPI0 filter: tent of half-width n, summing to 1."""
    tent = n - np.abs(np.arange(-(n - 1), n, dtype=np.float64))
    return (tent / tent.sum()).astype(np.float32)


class PPIDDemosaicer(Demosaicer):
    name = "ppid"

    def __init__(self, layout: MosaicLayout, shape: tuple[int, int], *, balance: bool = True) -> None:
        super().__init__(layout, shape)
        h, w = self.shape
        self.balance = balance
        self._tables = WBTables(layout, w)
        self._kernel = ppi_filter(layout.n)
        self.gains = np.ones(layout.n_bands, np.float32)
        # per-pixel gains of the n row phases, tiled once (no ``x % n`` per pixel in the kernel)
        self._tile = layout.array[:, np.arange(w) % layout.n]
        self._nblocks = self._blocks(h // layout.n)

    def band_gains(self, mosaic: np.ndarray) -> np.ndarray:
        """Per-band gains that bring every band's mean to the common mean (1 where a band is empty)."""
        mu = sublattice_means(mosaic, self.layout.n)
        return gains_from_levels(
            np.array([np.mean([mu[r, c] for r, c in ps]) for ps in self.layout.positions])
        )

    def fix_gains(self, band_levels: np.ndarray | None) -> None:
        """Balance with fixed gains from per-band levels (e.g. the white reference's band means)
        instead of each frame's own means; ``None`` goes back to per-frame gains."""
        if band_levels is None:
            self.balance = True
            return
        self.gains[:] = gains_from_levels(np.asarray(band_levels, dtype=np.float64))
        self.balance = False

    def _run(self, mosaic: np.ndarray) -> None:
        if self.balance:
            self.gains[:] = self.band_gains(mosaic)
        t = self._tables
        kernels.ppid_kernel(
            mosaic,
            self.gains[self._tile],
            self._kernel,
            t.pr,
            t.pc,
            t.start,
            t.count,
            t.fyt,
            t.wrows,
            (1.0 / self.gains).astype(np.float32),
            self.out,
            self._nblocks,
        )
