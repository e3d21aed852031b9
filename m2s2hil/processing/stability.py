"""Detecting, from the data, the conditions under which demosaicing fails.

- Saturation: raw pixels at full scale (flagged by ``subtract_dark``); demosaicing spreads a
  clipped value over the method's support, so the cube's mask is the raw mask grown by it.
- Phase error (the mosaic read with its origin off by a pixel, so every band is taken for
  another): positions that hold the same band must agree on average. For every candidate
  offset s the cost is the mean relative disagreement between the sub-lattice means of
  positions the layout says are duplicates; the read is suspect when some s ≠ 0 explains the
  data much better than s = 0. Needs a layout with duplicated bands and a scene whose bands
  differ in mean level (true of any raw frame: filters and quantum efficiency differ).
- Low light: the bright part of the frame (95th percentile) against the dark series' read
  noise (an upper bound on SNR, shot noise comes on top), warned below SNR 5.
High-frequency aliasing cannot be told from true texture in one frame: it is only measured
(docs/processing.md), not warned.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from m2s2hil.config import check_demosaic_method
from m2s2hil.processing.errors import UnknownMethodError
from m2s2hil.processing.mosaic import MosaicLayout

LOW_SNR = 5.0


@dataclass(frozen=True)
class PhaseCheck:
    offset: tuple[int, int]  # best-explaining (dy, dx); (0, 0) when the read looks right
    cost_nominal: float  # relative disagreement of duplicates at offset (0, 0)
    cost_best: float
    conclusive: bool  # False when the layout or the scene cannot tell
    #: cost[sy][sx] of every origin shift tried (the console's phase cost map); empty when none was
    cost: tuple[tuple[float, ...], ...] = ()

    @property
    def suspect(self) -> bool:
        return self.conclusive and self.offset != (0, 0)


def sublattice_stats(mosaic: np.ndarray, n: int, step: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """(n, n) mean of each MSFA position over every ``step``-th row of cells (all columns), and the
    standard error of those means (samples taken as independent). uint16 mosaics are summed in
    int64 (exact); other dtypes square in float32, exact up to 4096."""
    h, w = mosaic.shape
    count = -(-(h // n) // step) * (w // n)
    if mosaic.dtype == np.uint16 and mosaic.flags.c_contiguous:
        from m2s2hil.processing import kernels  # here: importing this module need not load numba

        # exact integer sums in one compiled pass (1.1 → 0.26 ms on the QC rows of a frame)
        s1, s2 = kernels.position_sums_u16(mosaic, n, step)
    else:
        rows = mosaic.reshape(h // n, n, w)[::step]  # whole rows: the sums run on contiguous memory
        s1 = rows.sum(axis=0, dtype=np.float64).reshape(n, w // n, n).sum(axis=1)
        sq = rows.astype(np.float32)
        np.multiply(sq, sq, out=sq)
        s2 = sq.sum(axis=0, dtype=np.float64).reshape(n, w // n, n).sum(axis=1)
    mean = s1 / count
    var = np.maximum(s2 / count - mean**2, 0.0)
    return mean, np.sqrt(var / count)


def sublattice_means(mosaic: np.ndarray, n: int, step: int = 8) -> np.ndarray:
    """(n, n) mean of each MSFA position over every ``step``-th row of cells (all columns)."""
    h, w = mosaic.shape
    rows = mosaic.reshape(h // n, n, w)[::step]
    per_col = rows.sum(axis=0, dtype=np.float64)  # (n, w)
    return per_col.reshape(n, w // n, n).sum(axis=1) / (rows.shape[0] * (w // n))


def duplicate_pairs(layout: MosaicLayout) -> list[tuple[tuple[int, int], tuple[int, int]]]:
    return [(ps[0], p) for ps in layout.positions for p in ps[1:]]


def check_phase(
    mosaic: np.ndarray, layout: MosaicLayout, *, step: int = 8, ratio: float = 4.0, min_cost: float = 0.02
) -> PhaseCheck:
    """Which origin offset makes duplicated positions agree best (see module docstring).

    ``offset`` is reported as the ``(dy, dx)`` for which ``layout.shifted(dy, dx)`` fits the data.
    Suspect when cost(0) ≥ ``min_cost`` (2 % relative disagreement) and cost(0) ≥ ``ratio`` × the
    best cost. Inconclusive (never suspect) when no offset makes duplicates disagree by more than
    ``min_cost`` and 5 standard errors of the means: bands of equal level, or too few samples.
    """
    n = layout.n
    pairs = duplicate_pairs(layout)
    if not pairs:
        return PhaseCheck((0, 0), 0.0, 0.0, conclusive=False)
    mu, se = sublattice_stats(mosaic, n, step)
    level = float(np.mean(mu))
    if level <= 0:
        return PhaseCheck((0, 0), 0.0, 0.0, conclusive=False)
    # cost[s]: hypothesis "frame position q holds the band the layout puts at q − s"
    cost = np.zeros((n, n))
    for sy in range(n):
        for sx in range(n):
            diffs = [
                abs(mu[(a[0] + sy) % n, (a[1] + sx) % n] - mu[(b[0] + sy) % n, (b[1] + sx) % n])
                for a, b in pairs
            ]
            cost[sy, sx] = np.mean(diffs) / level
    noise = 5.0 * float(np.sqrt(2.0) * np.mean(se)) / level
    best = np.unravel_index(np.argmin(cost), cost.shape)
    c0, cb = float(cost[0, 0]), float(cost[best])
    conclusive = float(cost.max()) >= max(min_cost, noise)
    suspect = conclusive and c0 >= max(min_cost, noise) and c0 >= ratio * cb
    offset = (int(-best[0] % n), int(-best[1] % n)) if suspect else (0, 0)
    table = tuple(tuple(float(v) for v in row) for row in cost)
    return PhaseCheck(offset, c0, cb, conclusive=conclusive, cost=table)


def phase_warning(check: PhaseCheck) -> str | None:
    if not check.suspect:
        return None
    dy, dx = check.offset
    return (
        f"MSFA phase looks wrong: duplicated bands disagree by {100 * check.cost_nominal:.1f} % at the "
        f"nominal origin but by {100 * check.cost_best:.1f} % with the layout shifted by ({dy}, {dx}) "
        "pixels; check the "
        "sensor readout offset / ROI and the layout in the calibration file"
    )


class Reach(NamedTuple):
    """How one raw value of an n×n mosaic reaches into a method's cube."""

    full_resolution: bool  # the cube has the sensor's resolution (else one value per n×n cell)
    a: int  # support radius in raw pixels: a·n + b (never below 0)
    b: int
    per_band: bool  # each band is built from its own samples only, so a raw value spoils only its band


#: Every method's reach: one table that the demosaicers read too, so the evaluation can rebuild a
#: stored cube's clipping mask from its raw frame without building one (or importing numba).
_REACH: dict[str, Reach] = {
    "superpixel": Reach(False, 0, 0, True),  # a clipped raw pixel spoils exactly its own cell
    "nearest": Reach(True, 1, -1, True),
    "wb": Reach(True, 1, -1, True),
    # R − PPI at a sample s reads R within n + 1 of s and PPI0 at s ± n, itself R within n − 1 of
    # those (2n − 1 in all); WB of the differences reaches samples n − 1 away: 3n − 2. Its guide
    # (PPI) mixes every band, so a clipped raw value spoils them all.
    "ppid": Reach(True, 3, -2, False),
}


def _reach(method: str) -> Reach:
    return _REACH[check_demosaic_method(method, UnknownMethodError)]


def support_radius(method: str, n: int) -> int:
    """How far (raw pixels) one raw value of an n×n mosaic reaches in ``method``'s cube."""
    r = _reach(method)
    return max(0, r.a * n + r.b)


def full_resolution(method: str) -> bool:
    """True when ``method``'s cube has the sensor's resolution, False for one value per cell."""
    return _reach(method).full_resolution


def cube_saturation(raw_mask: np.ndarray, method: str, n: int, out: np.ndarray | None = None) -> np.ndarray:
    """The cube's clipping mask from the raw one: grown by the method's support at full resolution,
    one flag per n×n cell for super-pixel (``FrameProcessor``'s ``saturated_mask``)."""
    if full_resolution(method):
        return grow_mask(raw_mask, support_radius(method, n), out=out)
    return cell_mask(raw_mask, n, out=out)


def band_saturation(raw_mask: np.ndarray, method: str, layout: MosaicLayout) -> np.ndarray:
    """(bands, H', W') bool: where each band of ``method``'s cube holds a clipped raw value. Its
    ``any`` over bands is ``cube_saturation``. A segmenter needs the bands, not just the pixel: a cell
    where one of a band's two positions clipped records a value bent low but not at the clipping
    plateau, which the cube alone cannot tell from a material's shape (docs/evaluation.md)."""
    mask = np.asarray(raw_mask, dtype=bool)
    reach = _reach(method)
    n = layout.n
    if not mask.any():  # most frames: nothing clipped, nothing to spread
        shape = mask.shape if reach.full_resolution else (mask.shape[0] // n, mask.shape[1] // n)
        return np.zeros((layout.n_bands, *shape), bool)
    if not reach.per_band:
        one = cube_saturation(mask, method, layout.n)
        return np.broadcast_to(one, (layout.n_bands, *one.shape)).copy()
    if not reach.full_resolution:
        h, w = mask.shape
        cells = mask.reshape(h // n, n, w // n, n)
        out = np.zeros((layout.n_bands, h // n, w // n), bool)
        for b, spots in enumerate(layout.positions):
            for r, c in spots:
                out[b] |= cells[:, r, :, c]
        return out
    radius = support_radius(method, n)
    out = np.empty((layout.n_bands, *mask.shape), bool)
    mine = np.empty(mask.shape, bool)
    for b, spots in enumerate(layout.positions):  # the band's own samples: strided copies, not a map
        mine.fill(False)
        for r, c in spots:
            mine[r::n, c::n] = mask[r::n, c::n]
        grow_mask(mine, radius, out=out[b])
    return out


def grow_mask(raw_mask: np.ndarray, radius: int, out: np.ndarray | None = None) -> np.ndarray:
    """Raw saturation mask grown by ``radius`` pixels (a (2r+1)² square), as bool."""
    if out is None:
        out = np.empty_like(raw_mask)
    if radius <= 0:
        np.copyto(out, raw_mask)
        return out
    k = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    grown = cv2.dilate(raw_mask.view(np.uint8), k)
    np.not_equal(grown, 0, out=out)
    return out


def cell_mask(raw_mask: np.ndarray, n: int, out: np.ndarray | None = None) -> np.ndarray:
    """True for every n×n cell that holds at least one flagged raw pixel."""
    h, w = raw_mask.shape
    return np.any(raw_mask.reshape(h // n, n, w // n, n), axis=(1, 3), out=out)


def saturation_warning(raw_mask: np.ndarray, full_scale: int, radius: int) -> str | None:
    return saturation_count_warning(int(np.count_nonzero(raw_mask)), raw_mask.size, full_scale, radius)


def saturation_count_warning(count: int, size: int, full_scale: int, radius: int) -> str | None:
    """The saturation warning from a count of clipped raw pixels out of ``size``."""
    if not count:
        return None
    frac = 100.0 * count / size
    return (
        f"{count} raw pixels ({frac:.2f} %) at full scale {full_scale}: their true values are unknown and "
        f"every band within {radius} px of them is unreliable (see saturated_mask); shorten the exposure"
    )


def low_light_warning(
    mosaic: np.ndarray, read_noise_dn: float | None, n: int, step: int = 8, row_step: int | None = None
) -> str | None:
    """Warn when even the bright part of the frame (95th percentile) is below 5× the read noise.

    A percentile rather than the median: M2S2 frames are mostly dark background around the
    mockup, so the median says nothing about the object. Needs the dark series' read noise.
    Samples every ``step``-th cell in both directions; ``row_step`` (default ``step``) overrides
    it for cell rows, e.g. 1 for a mosaic that already holds only every 8th cell row.
    """
    if not read_noise_dn or read_noise_dn <= 0:
        return None
    h, w = mosaic.shape
    rs = step if row_step is None else row_step
    sample = mosaic.reshape(h // n, n, w // n, n)[::rs, :, ::step, :]
    k = int(0.95 * (sample.size - 1))
    if mosaic.dtype == np.uint16:  # the k-th smallest from a histogram, read in place: exact
        from m2s2hil.processing import kernels

        # the usual frame is bright enough: at most k samples below the bound (a hair above it, so
        # float rounding of signal / read noise cannot disagree) means the k-th smallest reaches it
        bound = LOW_SNR * read_noise_dn * (1.0 + 1e-9)
        if kernels.count_below_cells_u16(mosaic, n, rs, step, bound) <= k:
            return None
        signal = float(kernels.kth_smallest_cells_u16(mosaic, n, rs, step, k))
    else:
        signal = float(np.partition(sample.ravel(), k)[k])
    snr = signal / read_noise_dn
    if snr >= LOW_SNR:
        return None
    return (
        f"very low light: the bright part of the frame (95th percentile, {signal:.1f} DN) is only "
        f"{snr:.1f}× the read noise ({read_noise_dn:.2f} DN), SNR below {LOW_SNR:g}; "
        "demosaiced bands are noise-dominated and spectral angles unreliable; lengthen the exposure"
    )
