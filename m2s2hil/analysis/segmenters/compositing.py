"""SAM-style instance masks → one semantic label map, and label-map fusion across bands.

Pure functions over plain data, so the paper's pipeline (2.4.1, 2.4.2) can be tested
without the SAM model. A *mask record* is the dict SAM's automatic mask generator
returns: ``{"segmentation": bool (H, W), "area": int, "predicted_iou": float,
"stability_score": float, ...}``; only ``segmentation`` is required (area is always
recounted from it; missing scores count as 0).

Conventions:

- *Quality order*: by ``predicted_iou``, then ``stability_score``, then area, all
  descending; ties keep the input order. De-duplication and top-k use this order.
- *De-duplication*: greedy, in quality order: a mask is dropped if its IoU with an
  already kept mask is ≥ ``iou_threshold`` (0.9 in the paper).
- *Compositing* (paper: "paints unlabeled pixels mask-by-mask (small-to-large),
  requiring minimal effective coverage and preferring non-background labels on near
  ties"): masks are visited by area, smallest first. A mask's *effective coverage* is
  the fraction of its pixels not yet claimed; it is painted (its unclaimed pixels only)
  when that fraction is ≥ ``min_coverage`` and at least ``min_pixels`` pixels are
  unclaimed, otherwise skipped. Each painted non-background mask gets the next id
  (1, 2, ...); a *background mask* (≥ ``background_overlap`` of its pixels inside the
  optional ``background`` prior, e.g. an Otsu-dark region) claims its pixels as 0.
  Near ties: a background mask is sorted as if it were ``tie_tolerance`` (5 %) larger,
  so a non-background mask of nearly the same size is painted first. Pixels no mask
  claims are background (0).
- *Majority vote* across bands: per-band ids are arbitrary, so each map is first
  aligned to the first map (Hungarian maximum overlap, 0 ↔ 0, see ``matching``); then
  each pixel takes its most frequent label; ties go to a non-background label, and
  among tied non-background labels to the one of the earliest map.
- *Binary fusion*: foreground where at least half the maps say non-background
  (ties favour foreground); the result is 0/1.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from scipy import sparse

from m2s2hil.analysis.arrays import as_label_map
from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.matching import match_clusters

MaskRecord = Mapping[str, Any]


def _segmentation(mask: MaskRecord, i: int, shape: tuple[int, int] | None = None) -> np.ndarray:
    try:
        seg = np.asarray(mask["segmentation"])
    except (KeyError, TypeError) as exc:
        raise AnalysisInputError(f"masks[{i}]", "mask record has no 'segmentation' array") from exc
    if seg.ndim != 2:
        raise AnalysisInputError(f"masks[{i}]", f"segmentation must be 2-D, got shape {seg.shape}")
    if shape is not None and seg.shape != shape:
        raise AnalysisInputError(f"masks[{i}]", f"segmentation shape {seg.shape} differs from {shape}")
    return seg.astype(bool, copy=False)


def quality_order(masks: Sequence[MaskRecord]) -> list[int]:
    """Indices of ``masks`` best first: predicted_iou, stability_score, area (descending)."""
    def key(i: int) -> tuple[float, float, int]:
        m = masks[i]
        area = int(_segmentation(m, i).sum())
        return (-float(m.get("predicted_iou", 0.0)), -float(m.get("stability_score", 0.0)), -area)

    return sorted(range(len(masks)), key=key)


def mask_iou_matrix(masks: Sequence[MaskRecord]) -> np.ndarray:
    """Pairwise IoU of the masks' pixel sets (sparse products: masks are mostly empty)."""
    if not masks:
        return np.zeros((0, 0))
    shape = _segmentation(masks[0], 0).shape
    rows = [sparse.csr_matrix(_segmentation(m, i, shape).reshape(1, -1)) for i, m in enumerate(masks)]
    stack = sparse.vstack(rows, format="csr").astype(np.int64)
    inter = (stack @ stack.T).toarray().astype(float)
    area = np.diag(inter).copy()
    union = area[:, None] + area[None, :] - inter
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = np.where(union > 0, inter / union, 0.0)
    return iou


def deduplicate_masks(masks: Sequence[MaskRecord], iou_threshold: float = 0.9) -> list[MaskRecord]:
    """Greedy de-duplication in quality order; returns the kept masks, best first."""
    if not 0.0 < iou_threshold <= 1.0:
        raise AnalysisInputError("iou_threshold", f"must lie in (0, 1], got {iou_threshold!r}")
    order = quality_order(masks)
    iou = mask_iou_matrix(masks)
    kept: list[int] = []
    for i in order:
        if all(iou[i, j] < iou_threshold for j in kept):
            kept.append(i)
    return [masks[i] for i in kept]


def top_k_masks(masks: Sequence[MaskRecord], k: int) -> list[MaskRecord]:
    """The ``k`` best masks in quality order."""
    if k < 0:
        raise AnalysisInputError("k", f"must be ≥ 0, got {k}")
    return [masks[i] for i in quality_order(masks)[:k]]


def composite_masks(
    masks: Sequence[MaskRecord],
    shape: tuple[int, int],
    *,
    background: np.ndarray | None = None,
    background_overlap: float = 0.5,
    min_coverage: float = 0.2,
    min_pixels: int = 10,
    tie_tolerance: float = 0.05,
) -> np.ndarray:
    """Paint masks small-to-large into an int32 ``(H, W)`` semantic map (see module docstring)."""
    shape = (int(shape[0]), int(shape[1]))
    if not 0.0 <= min_coverage <= 1.0:
        raise AnalysisInputError("min_coverage", f"must lie in [0, 1], got {min_coverage!r}")
    bg_prior = None
    if background is not None:
        bg_prior = np.asarray(background, dtype=bool)
        if bg_prior.shape != shape:
            raise AnalysisInputError("background", f"shape {bg_prior.shape} differs from {shape}")
    segs = [_segmentation(m, i, shape) for i, m in enumerate(masks)]
    areas = np.array([int(s.sum()) for s in segs], dtype=np.int64)
    is_bg = np.zeros(len(segs), dtype=bool)
    if bg_prior is not None:
        for i, s in enumerate(segs):
            is_bg[i] = areas[i] > 0 and (s & bg_prior).sum() >= background_overlap * areas[i]
    sort_key = areas * np.where(is_bg, 1.0 + tie_tolerance, 1.0)
    order = np.argsort(sort_key, kind="stable")
    labels = np.zeros(shape, dtype=np.int32)
    claimed = np.zeros(shape, dtype=bool)
    next_id = 1
    for i in order:
        if areas[i] == 0:
            continue
        free = segs[i] & ~claimed
        n_free = int(free.sum())
        if n_free < min_pixels or n_free < min_coverage * areas[i]:
            continue
        claimed |= free
        if not is_bg[i]:
            labels[free] = next_id
            next_id += 1
    return labels


def _stack(label_maps: Sequence[object]) -> list[np.ndarray]:
    if len(label_maps) == 0:
        raise AnalysisInputError("label_maps", "need at least one label map")
    maps = [as_label_map(m, f"label_maps[{i}]") for i, m in enumerate(label_maps)]
    for i, m in enumerate(maps[1:], start=1):
        if m.shape != maps[0].shape:
            raise AnalysisInputError(f"label_maps[{i}]", f"shape {m.shape} differs from {maps[0].shape}")
    return maps


def align_labels(reference: object, other: object) -> np.ndarray:
    """Relabel ``other`` so its segments carry the ids of the ``reference`` segments they overlap most."""
    return match_clusters(reference, other, keep_background=True).relabelled


def majority_vote(label_maps: Sequence[object], *, align: bool = True) -> np.ndarray:
    """Pixel-wise majority vote (ties: non-background, then the earliest map's label)."""
    maps = _stack(label_maps)
    if align:
        maps = [maps[0]] + [align_labels(maps[0], m) for m in maps[1:]]
    stack = np.stack(maps)
    universe = np.unique(stack)
    idx = np.searchsorted(universe, stack)  # (n, H, W) positions in universe
    counts = np.stack([(idx == j).sum(axis=0) for j in range(universe.size)])  # (L, H, W)
    best = counts.max(axis=0)
    nonbg = universe != 0
    any_fg_tie = ((counts == best) & nonbg[:, None, None]).any(axis=0)
    out = np.zeros(stack.shape[1:], dtype=np.int64)
    # Visit maps last to first so the earliest map's valid label is written last.
    for i in range(stack.shape[0] - 1, -1, -1):
        votes = np.take_along_axis(counts, idx[i][None], axis=0)[0]
        valid = (votes == best) & (nonbg[idx[i]] | ~any_fg_tie)
        out[valid] = stack[i][valid]
    return out


def binary_fusion(label_maps: Sequence[object]) -> np.ndarray:
    """Foreground (1) where at least half the maps are non-background, else 0 (uint8)."""
    maps = _stack(label_maps)
    votes = np.sum([m != 0 for m in maps], axis=0)
    return (2 * votes >= len(maps)).astype(np.uint8)
