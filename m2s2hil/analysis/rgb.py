"""Wavelength → RGB approximation of the paper's synthetic split, and the RGB baseline.

The paper renders each TOUCAN band's centre wavelength as an RGB colour with the
classic Bruton mapping and γ = 0.8 (science notes). Piecewise-linear ramps, λ in nm:

    380–440: R = (440−λ)/60, G = 0,            B = 1
    440–490: R = 0,          G = (λ−440)/50,   B = 1
    490–510: R = 0,          G = 1,            B = (510−λ)/20
    510–580: R = (λ−510)/70, G = 1,            B = 0
    580–645: R = 1,          G = (645−λ)/65,   B = 0
    645–780: R = 1,          G = 0,            B = 0

Intensity factor: 0.3 + 0.7·(λ−380)/40 below 420 nm, 0.3 + 0.7·(780−λ)/80 above
700 nm, 1 in between. Each channel = (factor·c)^γ (0 stays 0).

Near infrared (the 820 and 877 nm bands, outside 380–780 nm, where Bruton returns
black): ``nir="clamp"`` (default) gives them the colour of 780 nm, i.e. a dark red
R = 0.3^γ ≈ 0.382, G = B = 0 — an RGB sensor sees NIR, if at all, through its red
channel, and clamping keeps the NIR bands' signal in the rendering instead of deleting
it. ``nir="black"`` is Bruton's original (zero; those bands vanish from the RGB image).
The same rule applies symmetrically below 380 nm (colour of 380 nm); the TOUCAN has no
such band.

``render_rgb`` turns a cube into a 3-channel image: each channel is the weighted mean
of the bands, weighted by that band's colour in the channel
(``rgb_c = Σ_b w_bc·x_b / Σ_b w_bc``), so the RGB image keeps the cube's intensity
scale. ``RgbBaseline`` segments that image with any segmenter, making RGB vs
multispectral a comparison of inputs with the same segmenter family.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np

from m2s2hil.analysis.arrays import as_cube
from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.segment import Segmenter
from m2s2hil.config import CameraModel

NirRule = Literal["clamp", "black"]
DEFAULT_GAMMA = 0.8
TOUCAN_BANDS_NM: tuple[float, ...] = tuple(CameraModel().bands_nm)


def _ramps(lam: float) -> tuple[float, float, float]:
    if lam < 440:
        return (440 - lam) / 60, 0.0, 1.0
    if lam < 490:
        return 0.0, (lam - 440) / 50, 1.0
    if lam < 510:
        return 0.0, 1.0, (510 - lam) / 20
    if lam < 580:
        return (lam - 510) / 70, 1.0, 0.0
    if lam < 645:
        return 1.0, (645 - lam) / 65, 0.0
    return 1.0, 0.0, 0.0


def _factor(lam: float) -> float:
    if lam < 420:
        return 0.3 + 0.7 * (lam - 380) / 40
    if lam > 700:
        return 0.3 + 0.7 * (780 - lam) / 80
    return 1.0


def wavelength_to_rgb(wavelength_nm: float, gamma: float = DEFAULT_GAMMA,
                      nir: NirRule = "clamp") -> tuple[float, float, float]:
    """(R, G, B) in [0, 1] of one wavelength (see module docstring for the rule outside 380–780 nm)."""
    lam = float(wavelength_nm)
    if not np.isfinite(lam) or lam <= 0:
        raise AnalysisInputError("wavelength_nm", f"must be a positive number of nm, got {wavelength_nm!r}")
    if gamma <= 0:
        raise AnalysisInputError("gamma", f"must be > 0, got {gamma!r}")
    if nir not in ("clamp", "black"):
        raise AnalysisInputError("nir", f"expected 'clamp' or 'black', got {nir!r}")
    if lam < 380 or lam > 780:
        if nir == "black":
            return 0.0, 0.0, 0.0
        lam = min(max(lam, 380.0), 780.0)
    f = _factor(lam)
    return tuple(float((f * c) ** gamma) if c > 0 else 0.0 for c in _ramps(lam))  # type: ignore[return-value]


def band_colours(bands_nm: Sequence[float] = TOUCAN_BANDS_NM, gamma: float = DEFAULT_GAMMA,
                 nir: NirRule = "clamp") -> np.ndarray:
    """``(bands, 3)`` array of each band's RGB colour."""
    return np.array([wavelength_to_rgb(b, gamma, nir) for b in bands_nm], dtype=np.float64)


def render_rgb(cube: object, bands_nm: Sequence[float] = TOUCAN_BANDS_NM, gamma: float = DEFAULT_GAMMA,
               nir: NirRule = "clamp") -> np.ndarray:
    """float32 ``(3, H, W)`` RGB rendering of a ``(bands, H, W)`` cube (weighted band means)."""
    arr = as_cube(cube)
    if arr.shape[0] != len(bands_nm):
        raise AnalysisInputError("cube", f"has {arr.shape[0]} bands but {len(bands_nm)} wavelengths given")
    w = band_colours(bands_nm, gamma, nir)  # (bands, 3)
    total = w.sum(axis=0)
    norm = np.divide(w, total, out=np.zeros_like(w), where=total > 0).astype(np.float32)
    bands, h, wd = arr.shape
    rgb = norm.T @ arr.reshape(bands, -1)  # (3, H·W)
    return rgb.reshape(3, h, wd)


class RgbBaseline:
    """Render the cube to RGB with ``render_rgb`` and segment that with ``segmenter``."""

    def __init__(self, segmenter: Segmenter, bands_nm: Sequence[float] = TOUCAN_BANDS_NM,
                 gamma: float = DEFAULT_GAMMA, nir: NirRule = "clamp") -> None:
        if not callable(getattr(segmenter, "segment", None)):
            raise AnalysisInputError("segmenter", f"{segmenter!r} has no segment(cube) method")
        self.segmenter = segmenter
        self.bands_nm = tuple(float(b) for b in bands_nm)
        self.gamma = float(gamma)
        self.nir: NirRule = nir
        band_colours(self.bands_nm, self.gamma, self.nir)  # validate now, not at the first image
        self.name = f"rgb-{getattr(segmenter, 'name', type(segmenter).__name__)}"

    def segment(self, cube: np.ndarray) -> np.ndarray:
        return self.segmenter.segment(render_rgb(cube, self.bands_nm, self.gamma, self.nir))
