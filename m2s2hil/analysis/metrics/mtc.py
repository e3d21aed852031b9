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
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from m2s2hil.analysis.arrays import as_label_map
from m2s2hil.analysis.bands import PAPER_BANDS
from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.metrics.scores import micro_iou
from m2s2hil.analysis.segmenters.compositing import align_labels, binary_fusion, majority_vote

DEFAULT_K = 8
DEFAULT_MAX_SHIFT = 3
DEFAULT_SEED = 42

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


def _predict(predict: Predictor, x: np.ndarray, shape: tuple[int, int], what: str) -> np.ndarray:
    y = as_label_map(predict(x), f"prediction ({what})")
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
    base = _predict(predict, arr, shape, "base")
    ious = []
    for dx, dy in used:
        warped = _predict(predict, translate(arr, dx, dy), shape, f"shift {dx},{dy}")
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
