"""Cubes made fit to look at: white-balanced false colour and the sRGB transfer curve.

Display only (previews, contact sheets, the live view): nothing here feeds an analysis.

- :func:`srgb_encode`: linear values in [0, 1] to 8-bit with the sRGB transfer function
  (IEC 61966-2-1: 12.92·v below 0.0031308, else 1.055·v^(1/2.4) − 0.055), through a lookup table.
- :func:`false_colour`: the bands nearest 640, 550 and 470 nm as R, G and B, white-balanced
  (grey world by default: the three channels' means made equal over the lit pixels, or a given
  per-band white such as the calibration's white reference), scaled so the 99.5th percentile
  is white, then sRGB-encoded. Without the balance a neutral material looks green: the TOUCAN's
  mid bands collect the most light under a warm lamp.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

RGB_TARGET_NM = (640.0, 550.0, 470.0)
_LUT_SIZE = 4096


def _srgb_lut() -> np.ndarray:
    v = np.linspace(0.0, 1.0, _LUT_SIZE)
    out = np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1 / 2.4) - 0.055)
    return np.clip(np.rint(out * 255.0), 0, 255).astype(np.uint8)


SRGB_LUT = _srgb_lut()


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear values (clipped to [0, 1]) to uint8 with the sRGB transfer curve."""
    scaled = np.asarray(linear, dtype=np.float32) * (_LUT_SIZE - 1) + 0.5
    idx = np.clip(scaled, 0, _LUT_SIZE - 1).astype(np.intp)
    return SRGB_LUT[idx]


def rgb_bands(bands_nm: Sequence[float]) -> tuple[int, int, int]:
    """Indices of the bands nearest 640, 550 and 470 nm."""
    nm = np.asarray(bands_nm, dtype=np.float64)
    r, g, b = (int(np.argmin(np.abs(nm - t))) for t in RGB_TARGET_NM)
    return r, g, b


def false_colour(cube: np.ndarray, bands_nm: Sequence[float], *,
                 white: Sequence[float] | np.ndarray | None = None, percentile: float = 99.5) -> np.ndarray:
    """(bands, H, W) cube → (H, W, 3) uint8 sRGB image (see the module docstring).

    ``white``: the signal of a white reference per band (all bands); None for grey world.
    """
    idx = rgb_bands(bands_nm)
    rgb = np.stack([cube[i] for i in idx], axis=-1).astype(np.float32)
    if white is not None:
        w = np.asarray(white, dtype=np.float64)[list(idx)]
        gains = np.where(w > 0, w.max() / np.where(w > 0, w, 1.0), 1.0)
    else:
        # grey world over the lit part (above the mean brightness: the black backdrop would
        # otherwise weigh the balance with its noise)
        # (every 2nd pixel of every 2nd row: a balance for the eye needs no more, and the preview
        # is made for every stored frame)
        sample = rgb[::2, ::2]
        lum = sample.sum(axis=-1)
        lit = lum > lum.mean() if lum.size else np.zeros(0, bool)
        means = sample[lit].mean(axis=0) if np.any(lit) else sample.reshape(-1, 3).mean(axis=0)
        gains = np.where(means > 0, means.max() / np.where(means > 0, means, 1.0), 1.0)
    rgb *= gains.astype(np.float32)
    top = _percentile_of_sample(rgb, percentile)
    if top > 0:
        rgb /= top
    return srgb_encode(rgb)


def _percentile_of_sample(arr: np.ndarray, q: float) -> float:
    """The q-th percentile of every 4th pixel of every 4th row (np.partition, no full sort): a
    display scale needs no more, and a full percentile of a 512² × 3 image costs a live frame."""
    sample = arr[::4, ::4].ravel() if arr.ndim >= 2 else arr.ravel()
    if sample.size == 0:
        return 0.0
    k = round(q / 100.0 * (sample.size - 1))
    return float(np.partition(sample, k)[k])
