"""A spectrum read off a raw mosaic: the mean dark-subtracted DN of each band over a region, and
its reflectance against a white reference.

The region is given in sensor pixels and widened to whole mosaic cells (a 4×4 TOUCAN cell holds
every band once or twice, so a single cell is the smallest region that has a spectrum). Each
band's value is the mean of its own pixels inside the region, read straight from the mosaic:
no demosaicing, so nothing of the neighbouring bands leaks in (the super-pixel cube averages the
same samples per cell).

Reflectance is ``ρ_white · (DN / (t·g)) / (W / (t_w·g_w))`` with ``W`` the white reference's
dark-subtracted signal over the same region (so vignetting and the lamps' spectrum cancel)
and ``t``, ``g`` the exposures and gains: it assumes a sensor linear in exposure and gain and
the same lighting for the frame and the panel (the caller says whether the lightings match).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from m2s2hil.errors import UsageError
from m2s2hil.processing.mosaic import MosaicLayout


class RegionOutOfRange(UsageError):
    """A spectrum region outside the sensor (an HTTP 422 naming the parameter)."""


@dataclass(frozen=True)
class Region:
    """A region snapped to whole mosaic cells, in sensor pixels."""

    x: int
    y: int
    w: int
    h: int

    def as_dict(self) -> dict[str, int]:
        return {"x": self.x, "y": self.y, "w": self.w, "h": self.h}


def snap_region(x: int, y: int, w: int, h: int, sensor: tuple[int, int], period: int,
                where: str = "query") -> Region:
    """(x, y, w, h) in sensor pixels checked against ``sensor`` (width, height) and widened to
    whole ``period``-pixel cells."""
    width, height = sensor
    for name, v, hi in (("x", x, width), ("y", y, height)):
        if not 0 <= v < hi:
            raise RegionOutOfRange(f"{where}.{name}: {v} is outside the sensor (0..{hi - 1})")
    for name, v, start, hi in (("w", w, x, width), ("h", h, y, height)):
        if v < 1 or start + v > hi:
            raise RegionOutOfRange(f"{where}.{name}: {v} pixels from {start} leave the sensor "
                                   f"({hi} pixels; at least 1)")
    x0, y0 = x // period * period, y // period * period
    x1 = -(-(x + w) // period) * period
    y1 = -(-(y + h) // period) * period
    return Region(x0, y0, x1 - x0, y1 - y0)


def band_means(mosaic: np.ndarray, layout: MosaicLayout, region: Region) -> np.ndarray:
    """Mean of each band's pixels inside ``region`` (whole cells), float64 (bands,)."""
    n = layout.n
    sub = np.asarray(mosaic[region.y: region.y + region.h, region.x: region.x + region.w], np.float64)
    cells = sub.reshape(region.h // n, n, region.w // n, n).mean(axis=(0, 2))  # (n, n) per position
    return np.array([np.mean([cells[r, c] for r, c in pos]) for pos in layout.positions])


def dark_subtracted(raw: np.ndarray, dark: np.ndarray | None, layout: MosaicLayout,
                    region: Region) -> np.ndarray:
    """The region's band means of ``raw − dark`` (clipped at 0 per pixel, as the processing
    chain does) or of ``raw`` alone when there is no dark."""
    if dark is None:
        return band_means(raw, layout, region)
    sl = np.s_[region.y: region.y + region.h, region.x: region.x + region.w]
    diff = np.clip(raw[sl].astype(np.float64) - dark[sl].astype(np.float64), 0.0, None)
    return band_means(diff, layout, Region(0, 0, region.w, region.h))


def reflectance(dn: np.ndarray, exposure_s: float, gain: float, white: np.ndarray, white_exposure_s: float,
                white_gain: float, white_reflectance: np.ndarray) -> np.ndarray:
    """Reflectance per band (see the module docstring); NaN where the white signal is zero."""
    rate = dn / (exposure_s * gain)
    white_rate = white / (white_exposure_s * white_gain)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(white_rate > 0, white_reflectance * rate / white_rate, np.nan)
    return np.asarray(out, np.float64)


def superpixel_cube(mosaic: np.ndarray, layout: MosaicLayout) -> np.ndarray:
    """(bands, H/n, W/n) float32: each band's mean over its positions in every cell (the
    super-pixel cube, in numpy: for pictures, where a numba kernel's compile costs more than it saves)."""
    n = layout.n
    h, w = mosaic.shape
    cells = np.asarray(mosaic, np.float32).reshape(h // n, n, w // n, n).transpose(1, 3, 0, 2)
    bands = [np.mean([cells[r, c] for r, c in pos], axis=0) for pos in layout.positions]
    return np.stack(bands).astype(np.float32)
