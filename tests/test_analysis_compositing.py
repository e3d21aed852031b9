"""SAM-style mask de-duplication, compositing and band fusion, with hand-built masks."""

from __future__ import annotations

import numpy as np
import pytest

from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.segmenters.compositing import (
    align_labels,
    binary_fusion,
    composite_masks,
    deduplicate_masks,
    majority_vote,
    mask_iou_matrix,
    quality_order,
    top_k_masks,
)

SHAPE = (12, 12)


def rect(r0: int, r1: int, c0: int, c1: int, piou: float = 0.9, stab: float = 0.95) -> dict:
    seg = np.zeros(SHAPE, dtype=bool)
    seg[r0:r1, c0:c1] = True
    return {"segmentation": seg, "area": int(seg.sum()), "predicted_iou": piou, "stability_score": stab}


def plus_pixels(mask: dict, pixels: list[tuple[int, int]], piou: float) -> dict:
    seg = mask["segmentation"].copy()
    for r, c in pixels:
        seg[r, c] = True
    return {**mask, "segmentation": seg, "area": int(seg.sum()), "predicted_iou": piou}


A = rect(1, 4, 1, 4, piou=0.95)  # 9 px
B = rect(6, 10, 6, 10, piou=0.93)  # 16 px
C = rect(1, 10, 1, 10, piou=0.91)  # 81 px, contains A and B


def outside_c() -> dict:
    seg = ~C["segmentation"]
    return {"segmentation": seg, "area": int(seg.sum()), "predicted_iou": 0.99, "stability_score": 0.99}


def test_iou_and_dedup_threshold_is_inclusive() -> None:
    a10 = plus_pixels(A, [(0, 0)], piou=0.90)  # IoU with A = 9/10 -> duplicate at 0.9
    a11 = plus_pixels(A, [(0, 0), (0, 1)], piou=0.90)  # IoU 9/11 < 0.9 -> kept
    iou = mask_iou_matrix([A, a10, a11])
    assert iou[0, 1] == pytest.approx(0.9) and iou[0, 2] == pytest.approx(9 / 11)
    kept = deduplicate_masks([a10, A, a11], iou_threshold=0.9)
    assert next(m["predicted_iou"] for m in kept) == 0.95  # the better of the pair survives
    assert len(kept) == 2 and kept[1] is a11


def test_quality_order_and_top_k() -> None:
    low_stab = {**B, "predicted_iou": 0.95, "stability_score": 0.5}
    masks = [C, low_stab, A, B]
    assert quality_order(masks) == [2, 1, 3, 0]  # piou, then stability, then area
    assert top_k_masks(masks, 2) == [A, low_stab]
    assert top_k_masks(masks, 0) == []


def test_small_to_large_compositing_with_background_prior() -> None:
    bg_prior = ~C["segmentation"]
    labels = composite_masks([C, outside_c(), B, A], SHAPE, background=bg_prior, min_pixels=5)
    expected = np.zeros(SHAPE, dtype=np.int32)
    expected[1:10, 1:10] = 3  # C paints what A and B left: 56 of 81 px
    expected[1:4, 1:4] = 1  # smallest first
    expected[6:10, 6:10] = 2
    np.testing.assert_array_equal(labels, expected)


def test_minimal_effective_coverage_skips_mostly_claimed_masks() -> None:
    a_plus = plus_pixels(A, [(0, 0)], piou=0.5)  # 10 px, 9 already claimed by A: coverage 0.1
    labels = composite_masks([A, a_plus], SHAPE, min_coverage=0.2, min_pixels=1)
    assert labels[0, 0] == 0 and labels.max() == 1
    labels = composite_masks([A, a_plus], SHAPE, min_coverage=0.1, min_pixels=1)
    assert labels[0, 0] == 2
    assert composite_masks([A], SHAPE, min_pixels=10).max() == 0  # 9 px < min_pixels


def test_near_tie_prefers_non_background() -> None:
    fg = rect(0, 5, 0, 8)  # 40 px
    bg = rect(2, 8, 2, 8)  # 36 px, overlaps fg on rows 2-4, cols 2-7 (18 px)
    prior = bg["segmentation"]
    # key(bg) = 36·1.15 = 41.4 > 40: the foreground mask paints the overlap first
    labels = composite_masks([bg, fg], SHAPE, background=prior, tie_tolerance=0.15, min_pixels=1)
    assert (labels == 1).sum() == 40
    # without the tolerance the smaller background mask claims the overlap first
    labels = composite_masks([bg, fg], SHAPE, background=prior, tie_tolerance=0.0, min_pixels=1)
    assert (labels == 1).sum() == 40 - 18


def test_majority_vote_aligns_ids_across_bands() -> None:
    m1 = np.array([[0, 1, 1], [2, 2, 0]])
    m2 = np.array([[0, 5, 5], [7, 7, 7]])  # 5 ~ 1, 7 ~ 2
    m3 = np.array([[0, 3, 3], [0, 4, 4]])  # 3 ~ 1, 4 ~ 2
    np.testing.assert_array_equal(align_labels(m1, m2), [[0, 1, 1], [2, 2, 2]])
    np.testing.assert_array_equal(majority_vote([m1, m2, m3]), [[0, 1, 1], [2, 2, 2]])


def test_majority_vote_ties() -> None:
    # 0 vs 1 tie -> non-background; m2's label shares no pixel with m1's 1, so it gets id 2
    np.testing.assert_array_equal(majority_vote([np.array([[0, 1]]), np.array([[1, 0]])]), [[2, 1]])
    # three-way tie (0, 1, 2): a non-background label, the earliest map's
    maps = [np.array([[0]]), np.array([[2]]), np.array([[1]])]
    assert majority_vote(maps, align=False).tolist() == [[2]]
    assert majority_vote([np.array([[1]]), np.array([[2]])], align=False).tolist() == [[1]]


def test_binary_fusion() -> None:
    two = [np.array([[0, 1, 2, 0]]), np.array([[0, 0, 3, 3]])]
    assert binary_fusion(two).tolist() == [[0, 1, 1, 1]]  # 1 of 2 is a tie -> foreground
    three = [np.array([[0, 1, 1]]), np.array([[0, 0, 1]]), np.array([[1, 0, 1]])]
    assert binary_fusion(three).tolist() == [[0, 0, 1]]


def test_bad_masks_and_maps() -> None:
    with pytest.raises(AnalysisInputError, match=r"masks\[0\]"):
        composite_masks([{"area": 3}], SHAPE)
    with pytest.raises(AnalysisInputError, match="differs"):
        composite_masks([{"segmentation": np.ones((3, 3), bool)}], SHAPE)
    with pytest.raises(AnalysisInputError, match=r"label_maps\[1\]"):
        majority_vote([np.zeros((2, 2), int), np.zeros((3, 2), int)])
    with pytest.raises(AnalysisInputError):
        binary_fusion([])
