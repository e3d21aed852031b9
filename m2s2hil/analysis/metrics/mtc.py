"""mTC: ground-truth-free temporal/augmentation consistency (paper 2.4.2).

For an input x (a cube ``(bands, H, W)`` or one band ``(H, W)``) and a predictor f
returning an ``(H, W)`` label map:

    ŷ = f(x);   for k = 1..K:  ỹ_k = τ_k⁻¹(f(τ_k(x)));   mTC = (1/K) Σ_k IoU(ŷ, ỹ_k)

- τ_k is an integer translation by (Δx_k, Δy_k), applied identically to every band as
  a cyclic shift (``np.roll`` on the last two axes: Δx along W, Δy along H); τ_k⁻¹ is
  the exact roll back. Positive Δx moves content right, positive Δy moves it down.
- Shifts are drawn once from ``np.random.default_rng(seed)`` with a single call
  ``rng.integers(-max_shift, max_shift + 1, size=(K, 2))``: row k is (Δx_k, Δy_k), so the
  draw order is Δx_1, Δy_1, Δx_2, Δy_2, ... Paper settings: K = 8, max_shift = 3,
  seed = 42, which gives (Δx, Δy) = (-3, 2), (1, 0), (0, 3), (-3, 1), (-2, -3), (0, 3),
  (2, 2), (2, 2) with numpy's PCG64 generator.
- IoU is ``scores.micro_iou`` over the union of both maps' labels; with
  ``ignore_label`` = g, label g is left out of the sums (see that function). With every
  label counted, IoU = agree / (agree + 2·disagree) pixels.
- Segmenters that return cluster ids may number the same segments differently after
  a perturbation; ``align=True`` relabels each ỹ_k onto ŷ first (Hungarian maximum
  overlap, 0 ↔ 0, ``compositing.align_labels``). Off by default: the paper compares
  binary maps, where ids cannot permute.
- The paper's HIL predictor segments each of bands {5, 9, 10} (1-based) and fuses them
  in binary form (foreground vs background): ``band_fused_predictor``.
- ``saturated`` (the cube's clipping mask, ``segmenters.masks``) is shifted with the cube and
  given to each prediction as ``predict(x, saturated=mask)``: the clipping belongs to the pixel,
  so it moves with it.

**What a shift perturbs (issue 23).** A cyclic shift of an object that does not touch the
border keeps the raster order of its pixels, so a segmenter that draws its fit sample by
index with a fixed seed fits *the same pixels* after every shift, and one whose foreground
pool is below its sample size fits all of them in a new order: mTC = 1.000 then measures
order invariance, not stability. ``ResampledFit`` wraps a sampling segmenter (one with
``sample_size`` and ``seed``, e.g. ``SpectralSegmenter``) so that each prediction fits a
different sample: at most ``fraction`` (default 1/4) of the foreground's pixels, drawn with
the segmenter's seed + k for the k-th perturbation (k = 0 for ŷ). mTC then asks whether
another draw of the object's pixels gives the same map. Where the segmenter's own fit pool
(e.g. its homogeneous pixels) is smaller than that cap, it fits the whole pool and only the
mixture's initialisation (its seed) changes. Any predictor may offer ``perturbed(k)`` to get
the same treatment; plain callables are called unchanged. A pixel-wise predictor (a
threshold per pixel, the one-band path of the binary setting) has nothing to resample and
still scores exactly 1.0.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from m2s2hil.analysis.arrays import as_label_map
from m2s2hil.analysis.bands import PAPER_BANDS
from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.metrics.scores import micro_iou
from m2s2hil.analysis.segmenters.compositing import align_labels, binary_fusion, majority_vote

DEFAULT_K = 8
DEFAULT_MAX_SHIFT = 3
DEFAULT_SEED = 42
DEFAULT_FIT_FRACTION = 0.25  # ResampledFit: the fit sample's share of the foreground
MIN_FIT_SAMPLE = 200  # ... but never fewer pixels than this (a 12-component mixture needs data)

Shift = tuple[int, int]  # (dx, dy)
Predictor = Callable[[np.ndarray], np.ndarray]


def draw_shifts(
    k: int = DEFAULT_K, max_shift: int = DEFAULT_MAX_SHIFT, seed: int = DEFAULT_SEED
) -> tuple[Shift, ...]:
    """The K translations (Δx, Δy), uniform in {−max_shift, …, max_shift}², in the documented order."""
    if k < 1:
        raise AnalysisInputError("k", f"need at least one perturbation, got {k}")
    if max_shift < 0:
        raise AnalysisInputError("max_shift", f"must be ≥ 0, got {max_shift}")
    rng = np.random.default_rng(seed)
    draws = rng.integers(-max_shift, max_shift + 1, size=(k, 2))
    return tuple((int(dx), int(dy)) for dx, dy in draws)


def translate(x: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """τ: cyclic shift of the last two axes (all bands alike) by dy rows and dx columns."""
    return np.roll(x, shift=(dy, dx), axis=(-2, -1))


def untranslate(y: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """τ⁻¹: the exact roll back of ``translate(·, dx, dy)``."""
    return np.roll(y, shift=(-dy, -dx), axis=(-2, -1))


@dataclass(frozen=True)
class MTCResult:
    """mTC score, the IoU per perturbation, the shifts used and the base prediction ŷ."""

    score: float
    ious: tuple[float, ...]
    shifts: tuple[Shift, ...]
    base: np.ndarray

    def as_dict(self) -> dict[str, object]:
        return {"mtc": self.score, "ious": list(self.ious), "shifts": [list(s) for s in self.shifts]}


def _predict(predict: Callable[..., np.ndarray], x: np.ndarray, shape: tuple[int, int], what: str,
             saturated: np.ndarray | None = None) -> np.ndarray:
    out = predict(x) if saturated is None else predict(x, saturated=saturated)
    y = as_label_map(out, f"prediction ({what})")
    if y.shape != shape:
        raise AnalysisInputError(f"prediction ({what})", f"shape {y.shape}, expected {shape}")
    return y


def mtc(
    predict: Predictor,
    x: np.ndarray,
    *,
    k: int = DEFAULT_K,
    max_shift: int = DEFAULT_MAX_SHIFT,
    seed: int = DEFAULT_SEED,
    shifts: Sequence[Shift] | None = None,
    ignore_label: int | None = None,
    align: bool = False,
    saturated: np.ndarray | None = None,
) -> MTCResult:
    """mTC of ``predict`` on ``x``; pass ``shifts`` to override the seeded draw."""
    arr = np.asarray(x)
    if arr.ndim not in (2, 3):
        raise AnalysisInputError("x", f"expected (H, W) or (bands, H, W), got shape {arr.shape}")
    shape = (int(arr.shape[-2]), int(arr.shape[-1]))
    if shifts is None:
        used = draw_shifts(k, max_shift, seed)
    else:
        used = tuple((int(dx), int(dy)) for dx, dy in shifts)
    if not used:
        raise AnalysisInputError("shifts", "need at least one shift")
    exclude = () if ignore_label is None else (ignore_label,)
    mask = None
    if saturated is not None:
        mask = np.asarray(saturated, dtype=bool)  # (H, W), or per band (bands, H, W)
        if mask.ndim not in (2, 3) or mask.shape[-2:] != shape:
            problem = f"mask shape {mask.shape}, expected (…, {shape[0]}, {shape[1]})"
            raise AnalysisInputError("saturated", problem)
    perturbed = getattr(predict, "perturbed", None)  # ResampledFit: a new fit sample per perturbation
    base = _predict(perturbed(0) if perturbed else predict, arr, shape, "base", mask)
    ious = []
    for k, (dx, dy) in enumerate(used, start=1):
        f = perturbed(k) if perturbed else predict
        moved = None if mask is None else translate(mask, dx, dy)
        warped = _predict(f, translate(arr, dx, dy), shape, f"shift {dx},{dy}", moved)
        back = untranslate(warped, dx, dy)
        if align:
            back = align_labels(base, back)
        ious.append(micro_iou(base, back, exclude_labels=exclude))
    return MTCResult(float(np.mean(ious)), tuple(ious), used, base)


def band_fused_predictor(
    segment_band: Predictor,
    bands: Sequence[int] = PAPER_BANDS,
    *,
    binary: bool = True,
) -> Predictor:
    """f(cube) = fusion of ``segment_band(cube[b-1:b])`` over the 1-based ``bands``.

    ``binary=True`` is the paper's mTC setting (foreground vs background, majority vote,
    ties to foreground); ``binary=False`` fuses the aligned label maps by majority vote.
    """
    chosen = tuple(int(b) for b in bands)
    if not chosen or min(chosen) < 1:
        raise AnalysisInputError("bands", f"expected 1-based band numbers, got {bands!r}")

    def predict(cube: np.ndarray) -> np.ndarray:
        arr = np.asarray(cube)
        if arr.ndim != 3 or max(chosen) > arr.shape[0]:
            raise AnalysisInputError("cube", f"shape {arr.shape} has no band {max(chosen)} (1-based)")
        maps = [segment_band(arr[b - 1 : b]) for b in chosen]
        return binary_fusion(maps) if binary else majority_vote(maps)

    return predict


class ResampledFit:
    """A sampling segmenter whose fit sample changes with the perturbation (module docstring).

    ``perturbed(k)`` is the segmenter with ``seed + k`` and a sample of at most
    ``max(min_sample, fraction × foreground pixels)`` (never more than its own
    ``sample_size``); calling the object itself is ``perturbed(0)``. The foreground is counted
    with ``spectral.foreground_mask`` under the segmenter's own ``foreground`` rule.
    """

    def __init__(self, segmenter: Any, fraction: float = DEFAULT_FIT_FRACTION,
                 min_sample: int = MIN_FIT_SAMPLE) -> None:
        for attr in ("segment", "sample_size", "seed"):
            if not hasattr(segmenter, attr):
                raise AnalysisInputError(
                    "segmenter", f"{type(segmenter).__name__} has no {attr!r}: ResampledFit needs a "
                    "segmenter that draws a seeded fit sample (sample_size, seed), e.g. SpectralSegmenter")
        if not 0.0 < fraction <= 1.0:
            raise AnalysisInputError("fraction", f"must lie in (0, 1], got {fraction!r}")
        if min_sample < 2:
            raise AnalysisInputError("min_sample", f"must be ≥ 2, got {min_sample!r}")
        self.segmenter = segmenter
        self.fraction = float(fraction)
        self.min_sample = int(min_sample)
        self.name = f"{getattr(segmenter, 'name', type(segmenter).__name__)} (resampled fit)"

    def sample_size(self, cube: np.ndarray) -> int:
        """The fit sample's size for ``cube``."""
        from m2s2hil.analysis.segmenters.spectral import foreground_mask  # scikit-learn: only when used

        arr = np.asarray(cube, dtype=np.float64)
        if arr.ndim == 2:
            arr = arr[np.newaxis]
        fg, _ = foreground_mask(arr, getattr(self.segmenter, "foreground", "otsu"))
        cap = max(self.min_sample, math.ceil(self.fraction * int(fg.sum())))
        return int(min(int(self.segmenter.sample_size), cap))

    def perturbed(self, k: int) -> Predictor:
        def predict(cube: np.ndarray, **kw: Any) -> np.ndarray:  # kw: ``saturated``, as ``mtc`` gives it
            seg = copy.copy(self.segmenter)
            seg.seed = int(self.segmenter.seed) + int(k)
            seg.sample_size = self.sample_size(cube)
            return seg.segment(cube, **kw)

        return predict

    def __call__(self, cube: np.ndarray, **kw: Any) -> np.ndarray:
        return self.perturbed(0)(cube, **kw)

    segment = __call__
