"""Metrics and cluster matching on tiny label maps whose scores are computed by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.matching import match_clusters
from m2s2hil.analysis.metrics.scores import harmonic_mean, micro_iou, score_clusters, segmentation_scores

NAN = float("nan")

# Pixels (gt, pred): (0,0) (0,1) (1,1) (1,1) (2,2) (2,0)
GT3 = np.array([[0, 0, 1], [1, 2, 2]])
PRED3 = np.array([[0, 1, 1], [1, 2, 0]])


def test_per_class_and_macro_by_hand() -> None:
    s = segmentation_scores(GT3, PRED3)
    assert s.labels == (0, 1, 2)
    # class 0: TP1 FP1 FN1; class 1: TP2 FP1 FN0; class 2: TP1 FP0 FN1
    assert s.tp.tolist() == [1, 2, 1]
    assert s.fp.tolist() == [1, 1, 0]
    assert s.fn.tolist() == [1, 0, 1]
    np.testing.assert_allclose(s.precision, [1 / 2, 2 / 3, 1])
    np.testing.assert_allclose(s.recall, [1 / 2, 1, 1 / 2])
    np.testing.assert_allclose(s.dice, [2 / 4, 4 / 5, 2 / 3])
    assert s.macro_precision == pytest.approx((1 / 2 + 2 / 3 + 1) / 3)
    assert s.macro_recall == pytest.approx(2 / 3)
    assert s.macro_dice == pytest.approx((1 / 2 + 4 / 5 + 2 / 3) / 3)
    assert s.micro_iou == pytest.approx(4 / 8)
    assert s.support.tolist() == [2, 2, 2]


def test_macro_dice_is_not_harmonic_mean_of_macro_p_and_r() -> None:
    s = segmentation_scores(GT3, PRED3)
    hm = harmonic_mean(s.macro_precision, s.macro_recall)
    assert hm == pytest.approx(2 * (13 / 18) * (2 / 3) / (13 / 18 + 2 / 3))  # 0.6933...
    assert s.macro_dice == pytest.approx(59 / 90)  # 0.6556...
    assert abs(hm - s.macro_dice) > 0.03


# Pixels (gt, pred): (1,1) (1,3) (2,1) (2,1); class 2 is never predicted, 3 is not in the gt.
GT_ABS = np.array([[1, 1], [2, 2]])
PRED_ABS = np.array([[1, 3], [1, 1]])


def test_gt_label_set_and_zero_division_rules() -> None:
    s0 = segmentation_scores(GT_ABS, PRED_ABS)  # labels="gt", 0/0 -> 0
    assert s0.labels == (1, 2)
    np.testing.assert_allclose(s0.precision, [1 / 3, 0.0])  # P_2 = 0/0 -> 0
    np.testing.assert_allclose(s0.recall, [1 / 2, 0.0])
    np.testing.assert_allclose(s0.dice, [2 / 5, 0.0])  # Dice_2 = 0/2, not 0/0
    assert s0.macro_precision == pytest.approx(1 / 6)
    assert s0.macro_recall == pytest.approx(1 / 4)
    assert s0.macro_dice == pytest.approx(1 / 5)
    assert s0.micro_iou == pytest.approx(1 / 6)  # TP 1, FP 2+0, FN 1+2

    s_nan = segmentation_scores(GT_ABS, PRED_ABS, zero_division=NAN)
    assert math.isnan(s_nan.precision[1])
    assert s_nan.macro_precision == pytest.approx(1 / 3)  # class 2 left out of the P mean
    assert s_nan.macro_recall == pytest.approx(1 / 4)

    s1 = segmentation_scores(GT_ABS, PRED_ABS, zero_division=1.0)
    assert s1.macro_precision == pytest.approx((1 / 3 + 1) / 2)


def test_union_label_set_counts_spurious_class() -> None:
    s = segmentation_scores(GT_ABS, PRED_ABS, labels="union")
    assert s.labels == (1, 2, 3)
    np.testing.assert_allclose(s.precision, [1 / 3, 0, 0])
    np.testing.assert_allclose(s.recall, [1 / 2, 0, 0])  # R_3 = 0/0 -> 0
    np.testing.assert_allclose(s.dice, [2 / 5, 0, 0])
    assert s.macro_dice == pytest.approx(2 / 15)
    assert s.micro_iou == pytest.approx(1 / 7)  # TP 1, FP 2+0+1, FN 1+2+0

    s_nan = segmentation_scores(GT_ABS, PRED_ABS, labels="union", zero_division=NAN)
    assert s_nan.macro_precision == pytest.approx(1 / 6)  # mean(1/3, 0); P_2 is NaN
    assert s_nan.macro_recall == pytest.approx(1 / 4)  # mean(1/2, 0); R_3 is NaN


def test_explicit_labels_with_class_absent_everywhere() -> None:
    s = segmentation_scores(GT_ABS, PRED_ABS, labels=[1, 2, 3, 4])
    assert s.dice[3] == 0.0  # class 4: 0/0 -> zero_division
    assert s.macro_dice == pytest.approx(0.4 / 4)
    s_nan = segmentation_scores(GT_ABS, PRED_ABS, labels=[1, 2, 3, 4], zero_division=NAN)
    assert s_nan.macro_dice == pytest.approx(0.4 / 3)


def test_ignore_index_drops_void_pixels_and_exclude_keeps_them() -> None:
    gt = np.array([[1, 255], [2, 2]])
    pred = np.array([[1, 1], [2, 1]])
    s = segmentation_scores(gt, pred, ignore_index=255)
    assert s.labels == (1, 2) and s.n_pixels == 3
    np.testing.assert_allclose(s.precision, [1 / 2, 1])
    np.testing.assert_allclose(s.recall, [1, 1 / 2])
    # exclude class 0: its pixels stay and cost class 1 a false positive
    e = segmentation_scores(np.array([[0, 1]]), np.array([[1, 1]]), exclude_labels=[0])
    assert e.labels == (1,)
    assert e.precision[0] == pytest.approx(1 / 2) and e.recall[0] == 1.0


def test_counts_agree_with_ratios_on_random_maps() -> None:
    rng = np.random.default_rng(3)
    gt = rng.integers(0, 5, size=(40, 50))
    pred = rng.integers(0, 7, size=(40, 50))
    for labels in ("gt", "union", [0, 2, 9]):
        s = segmentation_scores(gt, pred, labels=labels)
        tp, fp, fn = s.tp.astype(float), s.fp.astype(float), s.fn.astype(float)
        with np.errstate(invalid="ignore", divide="ignore"):
            dice = np.where(2 * tp + fp + fn > 0, 2 * tp / (2 * tp + fp + fn), 0.0)
            prec = np.where(tp + fp > 0, tp / (tp + fp), 0.0)
        np.testing.assert_allclose(s.dice, dice)
        np.testing.assert_allclose(s.precision, prec)
        assert s.micro_iou == pytest.approx(tp.sum() / (tp.sum() + fp.sum() + fn.sum()))


def test_micro_iou_all_labels_is_agree_over_agree_plus_twice_disagree() -> None:
    a = np.array([[0, 0, 1, 1], [2, 2, 2, 0]])
    b = np.array([[0, 1, 1, 1], [2, 0, 2, 0]])
    assert micro_iou(a, b) == pytest.approx(6 / (6 + 2 * 2))
    assert micro_iou(a, b) == micro_iou(b, a)
    # without label 0: TP_1 = 2, TP_2 = 2, FP_1 = 1 (pair 0,1), FN_2 = 1 (pair 2,0)
    assert micro_iou(a, b, exclude_labels=[0]) == pytest.approx(4 / 6)
    assert micro_iou(np.zeros((2, 2), int), np.zeros((2, 2), int), exclude_labels=[0]) == 1.0


def test_bad_inputs_raise_typed_errors() -> None:
    with pytest.raises(AnalysisInputError, match="pred"):
        segmentation_scores(np.zeros((2, 2), int), np.zeros((2, 3), int))
    with pytest.raises(AnalysisInputError, match="integer"):
        segmentation_scores(np.zeros((2, 2)), np.zeros((2, 2), int))
    with pytest.raises(AnalysisInputError, match="zero_division"):
        segmentation_scores(GT3, PRED3, zero_division=0.5)
    with pytest.raises(AnalysisInputError, match="labels"):
        segmentation_scores(GT3, PRED3, labels="all")
    with pytest.raises(AnalysisInputError, match="negative"):
        segmentation_scores(-GT3, PRED3)


GT_M = np.array([[0, 0, 0, 0], [1, 1, 2, 2], [1, 1, 2, 2], [3, 3, 3, 3]])
PRED_M = np.array([[0, 0, 0, 0], [5, 5, 7, 7], [5, 5, 7, 9], [2, 2, 2, 2]])


def test_hungarian_matching_with_an_extra_cluster() -> None:
    m = match_clusters(GT_M, PRED_M)
    assert m.mapping == {0: 0, 5: 1, 7: 2, 2: 3, 9: 4}  # 9 unmatched -> fresh id max(gt)+1
    assert m.unmatched == (9,)
    assert m.relabelled.tolist() == [[0, 0, 0, 0], [1, 1, 2, 2], [1, 1, 2, 4], [3, 3, 3, 3]]
    assert m.overlap == 15
    s = segmentation_scores(GT_M, m.relabelled)
    assert s.recall.tolist() == [1.0, 1.0, 0.75, 1.0]
    assert s.precision.tolist() == [1.0, 1.0, 1.0, 1.0]  # the stray cluster costs recall only
    u = segmentation_scores(GT_M, m.relabelled, labels="union")
    assert u.labels[-1] == 4 and u.precision[-1] == 0.0


def test_matching_background_option_and_zero_overlap_pairs() -> None:
    gt = np.array([[0, 0, 1, 1]])
    pred = np.array([[3, 3, 0, 0]])
    assert match_clusters(gt, pred, keep_background=False).mapping == {3: 0, 0: 1}
    kept = match_clusters(gt, pred)  # 0 -> 0 fixed; cluster 3 shares no pixel with class 1
    assert kept.mapping == {0: 0, 3: 2}
    assert kept.unmatched == (3,)


def test_score_clusters_matches_then_scores() -> None:
    scores, match = score_clusters(GT_M, PRED_M, labels="union")
    assert match.unmatched == (9,)
    assert scores.labels == (0, 1, 2, 3, 4)
    assert scores.recall[2] == 0.75 and scores.precision[4] == 0.0
