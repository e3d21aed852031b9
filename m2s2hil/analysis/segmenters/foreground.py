"""Which pixels are the object: a threshold on log band energy, and dim regions found by averaging.

``foreground_mask`` thresholds each pixel's band energy e = ‖x‖₂ on its log (shading is
multiplicative: in the linear domain a half in shadow forms its own histogram mode). Rules:

- ``"otsu"``: above the Otsu threshold;
- ``"backdrop"``: above the lower of that and the backdrop's median + ``BACKDROP_MADS`` robust SDs
  (with a bright object Otsu's cut can fall above a dark material and hand it to the background);
- ``"noise"``: the same bound on the energy instead of its log (a dark backdrop is noise, whose
  log spreads widely).

A per-pixel rule cannot find a region whose pixels are each within the backdrop's noise: a dark
material at low exposure (Hubble B2's dark part at 5 % of full scale: 2 301 of its 2 514 pixels
fell to the backdrop), or a face in a spotlight's shadow. Averaged over a window, though, such a
region stands out, since the mean of n pixels has 1/√n of the noise. ``dim_regions`` adds them
(issue 23, sixth pass; docs/evaluation.md):

1. the energy of the pixels not yet in the foreground is averaged over a (2r + 1)² window, the
   foreground left out of every mean (normalised box filter): a backdrop pixel beside a bright
   object does not inherit its light;
2. a pixel whose window mean lies above the backdrop's (median + ``BACKDROP_MADS`` robust SDs of
   the window means of every pixel not in the foreground, most of them backdrop) is a candidate;
3. candidates go through a morphological opening (``opening`` iterations of the 3 × 3 cross), so a
   ring one or two pixels wide along the rim — partly lit blends, which the window makes look
   brighter than they are — drops out, while a region with an interior stays;
4. connected regions of at least ``DIM_MIN_PIXELS`` join the foreground.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from scipy import ndimage
from skimage.filters import threshold_otsu

ForegroundRule = Literal["noise", "backdrop", "otsu"]
BACKDROP_MADS = 6.0
DIM_MIN_PIXELS = 20  # a region smaller than this is no part worth adding (and may be a noise blob)


def foreground_mask(cube: np.ndarray, rule: ForegroundRule = "otsu") -> tuple[np.ndarray, float]:
    """Foreground on the log band energy of a ``(bands, H, W)`` cube.

    ``"otsu"``: above the Otsu threshold. ``"backdrop"``: above the lower of the Otsu threshold and
    the backdrop's level + ``BACKDROP_MADS`` robust SDs (median and 1.4826·MAD of the pixels below
    the Otsu threshold): with a bright object Otsu's cut can fall above a dark material (dark grey
    filament) and hand it to the background; the backdrop's own spread bounds what noise can reach.
    Returns the mask and the threshold expressed as band energy (NaN for a constant cube).
    """
    energy = band_energy(cube)
    top = float(energy.max())
    if top == float(energy.min()):
        return np.zeros(energy.shape, dtype=bool), float("nan")
    eps = 1e-3 * top
    log_e = np.log(energy + eps)
    t = float(threshold_otsu(log_e))
    if rule == "backdrop":
        t = min(t, backdrop_bound(log_e[log_e <= t]))
    elif rule == "noise":
        # the same bound on the energy itself: the backdrop's spread is its noise (a dark backdrop
        # is mostly noise, whose log spreads far more than its value), so a face in the
        # spotlight's shadow a few noise SDs above it is found (in log it fell below 6 MADs)
        t = min(t, float(np.log(backdrop_bound(energy[log_e <= t]) + eps)))
    return log_e > t, float(np.exp(t) - eps)


def band_energy(cube: np.ndarray) -> np.ndarray:
    """(H, W) ‖x‖₂ over the bands."""
    return np.sqrt(np.einsum("bhw,bhw->hw", cube, cube))


def backdrop_bound(below: np.ndarray) -> float:
    """The backdrop's median plus ``BACKDROP_MADS`` robust SDs (1.4826 × MAD) of ``below``."""
    med = float(np.median(below))
    return med + BACKDROP_MADS * 1.4826 * float(np.median(np.abs(below - med)))


def dim_regions(cube: np.ndarray, fg: np.ndarray, *, radius: int = 2, opening: int = 2) -> np.ndarray:
    """(H, W) bool: pixels outside ``fg`` in regions too dim for a per-pixel threshold whose
    window-averaged energy stands above the backdrop's (module docstring); ``radius`` 0: none."""
    import cv2

    if radius < 1 or fg.all() or not fg.any():
        return np.zeros_like(fg)
    k = 2 * radius + 1
    out = (~fg).astype(np.float32)
    energy = band_energy(cube).astype(np.float32)
    # sums over the window of the pixels outside the foreground only (a normalised box filter)
    total = cv2.boxFilter(energy * out, -1, (k, k), normalize=False, borderType=cv2.BORDER_REFLECT)
    count = cv2.boxFilter(out, -1, (k, k), normalize=False, borderType=cv2.BORDER_REFLECT)
    # a window mostly of foreground averages few pixels and is as noisy as they are: not judged
    judged = ~fg & (count >= 0.5 * k * k)
    if int(judged.sum()) < k * k:
        return np.zeros_like(fg)
    mean = total / np.maximum(count, 1.0)
    candidates = judged & (mean > backdrop_bound(mean[judged]))
    candidates = ndimage.binary_opening(candidates, iterations=opening) if opening > 0 else candidates
    regions, n = ndimage.label(candidates)
    if n == 0:
        return candidates
    big = np.bincount(regions.ravel()) >= DIM_MIN_PIXELS
    big[0] = False
    return big[regions]
