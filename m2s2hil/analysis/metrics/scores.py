"""Segmentation metrics of the paper (2.4.2): per-class and macro precision, recall, Dice; micro-IoU.

Definitions, for a class c over the evaluated pixels:

- ``P_c = TP/(TP+FP)``, ``R_c = TP/(TP+FN)``, ``Dice_c = 2TP/(2TP+FP+FN)`` (= F1_c);
- macro = unweighted mean over the classes of the *label set*; macro Dice is the mean
  of the per-class Dice values, **not** the harmonic mean of macro P and macro R;
- ``micro-IoU = ΣTP / Σ(TP+FP+FN)`` over the classes of the label set.

Label set (``labels``):

- ``"gt"`` (default): the classes present in the ground truth. Pixels predicted as a
  class absent from the ground truth still count, as false negatives of the true class;
  they only cost recall (and Dice), never another class's precision.
- ``"union"``: ground-truth classes plus every predicted class; a spurious predicted
  class then enters the mean with P = 0 and Dice = 0 (its recall is 0/0).
- an explicit sequence of class ids (e.g. every class of a build, present or not).

``exclude_labels`` removes classes from the label set (their pixels stay, so they still
produce FP/FN for the other classes); ``ignore_index`` removes the *pixels* whose
ground truth is that value (void) before anything is counted.

0/0 rule (``zero_division``): a ratio with a zero denominator takes this value;
0.0 by default (scikit-learn's convention). ``float("nan")`` leaves that class out of
that metric's macro mean instead. Under ``"gt"``, only precision can be 0/0 (a true
class that is never predicted); its Dice is then 0, never 0/0. A macro mean over an
empty label set is NaN.

Segmenter output (cluster ids) is scored with ``score_clusters``: oracle Hungarian
matching to the ground truth (``matching.match_clusters``) first.

The per-class ratios come from ``sklearn.metrics.precision_recall_fscore_support``; the
counts behind micro-IoU from ``sklearn.metrics.confusion_matrix`` over all labels seen.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from m2s2hil.analysis.arrays import as_label_map, same_shape
from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.matching import ClusterMatch, match_clusters

LabelSet = Literal["gt", "union"] | Sequence[int]


@dataclass(frozen=True)
class SegmentationScores:
    """Scores of one prediction against one ground truth; arrays are aligned with ``labels``."""

    labels: tuple[int, ...]
    precision: np.ndarray
    recall: np.ndarray
    dice: np.ndarray
    tp: np.ndarray
    fp: np.ndarray
    fn: np.ndarray
    macro_precision: float
    macro_recall: float
    macro_dice: float
    micro_iou: float
    n_pixels: int
    zero_division: float = field(default=0.0)

    @property
    def support(self) -> np.ndarray:
        """Ground-truth pixel count per class (TP + FN)."""
        return self.tp + self.fn

    def per_class(self) -> list[dict[str, float | int]]:
        """One row per class of the label set: label, tp, fp, fn, precision, recall, dice."""
        return [
            {
                "label": lab,
                "tp": int(self.tp[i]),
                "fp": int(self.fp[i]),
                "fn": int(self.fn[i]),
                "precision": float(self.precision[i]),
                "recall": float(self.recall[i]),
                "dice": float(self.dice[i]),
            }
            for i, lab in enumerate(self.labels)
        ]

    def as_dict(self) -> dict[str, Any]:
        """JSON-friendly summary (NaN stays a float NaN; callers serialise as they need)."""
        return {
            "labels": list(self.labels),
            "macro_precision": self.macro_precision,
            "macro_recall": self.macro_recall,
            "macro_dice": self.macro_dice,
            "micro_iou": self.micro_iou,
            "n_pixels": self.n_pixels,
            "zero_division": self.zero_division,
            "per_class": self.per_class(),
        }


def _check_zero_division(value: float) -> float:
    v = float(value)
    if not (math.isnan(v) or v in (0.0, 1.0)):
        raise AnalysisInputError("zero_division", f"must be 0.0, 1.0 or nan, got {value!r}")
    return v


def _pixels(gt: object, pred: object, ignore_index: int | None) -> tuple[np.ndarray, np.ndarray]:
    g = as_label_map(gt, "gt")
    p = as_label_map(pred, "pred")
    same_shape(g, p, ("gt", "pred"))
    g, p = g.ravel(), p.ravel()
    if ignore_index is not None:
        keep = g != ignore_index
        g, p = g[keep], p[keep]
    return g, p


def resolve_labels(
    gt: np.ndarray,
    pred: np.ndarray,
    labels: LabelSet = "gt",
    exclude_labels: Sequence[int] = (),
    ignore_index: int | None = None,
) -> tuple[int, ...]:
    """The sorted class ids a macro mean runs over (see module docstring)."""
    if isinstance(labels, str):
        if labels == "gt":
            found = np.unique(gt)
        elif labels == "union":
            found = np.union1d(np.unique(gt), np.unique(pred))
        else:
            raise AnalysisInputError("labels", f"expected 'gt', 'union' or a list of ids, got {labels!r}")
        chosen = [int(v) for v in found]
    else:
        try:
            chosen = sorted({int(v) for v in labels})
        except (TypeError, ValueError) as exc:
            raise AnalysisInputError("labels", f"not a list of integer class ids: {labels!r}") from exc
    drop = {int(v) for v in exclude_labels}
    if ignore_index is not None:
        drop.add(int(ignore_index))
    return tuple(v for v in chosen if v not in drop)


def _nanmean(values: np.ndarray) -> float:
    if values.size == 0 or np.isnan(values).all():
        return float("nan")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return float(np.nanmean(values))


def _counts(g: np.ndarray, p: np.ndarray, labs: tuple[int, ...]) -> tuple[np.ndarray, ...]:
    # Confusion over every label seen, so pixels of labels outside the label set still
    # count as FP/FN of the classes inside it.
    universe = np.union1d(np.union1d(np.unique(g), np.unique(p)), np.asarray(labs, dtype=np.int64))
    with warnings.catch_warnings():
        # sklearn warns about a single label even when ``labels`` is given, as it is here.
        warnings.filterwarnings("ignore", message="A single label", category=UserWarning)
        from sklearn.metrics import confusion_matrix  # loaded on first use (2 s of CPU a process)

        cm = confusion_matrix(g, p, labels=universe)  # rows: gt, columns: pred
    idx = np.searchsorted(universe, np.asarray(labs, dtype=np.int64))
    tp = np.diag(cm)[idx].astype(np.int64)
    fp = cm.sum(axis=0)[idx].astype(np.int64) - tp
    fn = cm.sum(axis=1)[idx].astype(np.int64) - tp
    return tp, fp, fn


def segmentation_scores(
    gt: object,
    pred: object,
    labels: LabelSet = "gt",
    *,
    zero_division: float = 0.0,
    exclude_labels: Sequence[int] = (),
    ignore_index: int | None = None,
) -> SegmentationScores:
    """Per-class and macro precision/recall/Dice and micro-IoU of ``pred`` against ``gt``.

    ``gt`` and ``pred`` are integer ``(H, W)`` label maps in the same label space (match
    cluster ids to classes first with ``m2s2hil.analysis.matching.match_clusters``).
    """
    zd = _check_zero_division(zero_division)
    g, p = _pixels(gt, pred, ignore_index)
    labs = resolve_labels(g, p, labels, exclude_labels, ignore_index)
    if not labs or g.size == 0:
        # Nothing to count: every per-class ratio is 0/0.
        n = len(labs)
        ratio = np.full(n, zd)
        zeros = np.zeros(n, dtype=np.int64)
        mean = _nanmean(ratio)
        return SegmentationScores(labs, ratio, ratio, ratio, zeros, zeros, zeros, mean, mean, mean,
                                  zd, int(g.size), zd)
    from sklearn.metrics import precision_recall_fscore_support

    prec, rec, dice, _ = precision_recall_fscore_support(
        g, p, labels=list(labs), average=None, zero_division=zd
    )
    tp, fp, fn = _counts(g, p, labs)
    denom = int(tp.sum() + fp.sum() + fn.sum())
    miou = float(tp.sum()) / denom if denom else zd
    return SegmentationScores(
        labels=labs,
        precision=np.asarray(prec, dtype=float),
        recall=np.asarray(rec, dtype=float),
        dice=np.asarray(dice, dtype=float),
        tp=tp,
        fp=fp,
        fn=fn,
        macro_precision=_nanmean(np.asarray(prec, dtype=float)),
        macro_recall=_nanmean(np.asarray(rec, dtype=float)),
        macro_dice=_nanmean(np.asarray(dice, dtype=float)),
        micro_iou=miou,
        n_pixels=int(g.size),
        zero_division=zd,
    )


def score_clusters(
    gt: object,
    clusters: object,
    labels: LabelSet = "gt",
    *,
    keep_background: bool = True,
    zero_division: float = 0.0,
    exclude_labels: Sequence[int] = (),
    ignore_index: int | None = None,
) -> tuple[SegmentationScores, ClusterMatch]:
    """Score a segmenter's cluster map: oracle Hungarian matching to ``gt``, then ``segmentation_scores``."""
    match = match_clusters(gt, clusters, keep_background=keep_background, ignore_index=ignore_index)
    scores = segmentation_scores(gt, match.relabelled, labels, zero_division=zero_division,
                                 exclude_labels=exclude_labels, ignore_index=ignore_index)
    return scores, match


def micro_iou(
    reference: object,
    other: object,
    labels: LabelSet = "union",
    *,
    exclude_labels: Sequence[int] = (),
    ignore_index: int | None = None,
    empty_value: float = 1.0,
) -> float:
    """``ΣTP / Σ(TP+FP+FN)`` of ``other`` against ``reference`` over a label set.

    Default label set is the union of both maps' labels, which makes the score symmetric:
    with every label counted it equals ``agree / (agree + 2·disagree)`` pixels. A label in
    ``exclude_labels`` is omitted from the sums (a pixel where one map says it and the other
    says c still costs class c one FP or FN). When nothing is left to compare (0/0) the two
    maps agree trivially and ``empty_value`` (1.0) is returned.
    """
    g, p = _pixels(reference, other, ignore_index)
    labs = resolve_labels(g, p, labels, exclude_labels, ignore_index)
    if not labs or g.size == 0:
        return float(empty_value)
    tp, fp, fn = _counts(g, p, labs)
    denom = int(tp.sum() + fp.sum() + fn.sum())
    return float(tp.sum()) / denom if denom else float(empty_value)


def harmonic_mean(a: float, b: float) -> float:
    """``2ab/(a+b)`` (0 when both are 0): what macro Dice is *not*; kept for comparison tables."""
    return 0.0 if a + b == 0 else 2.0 * a * b / (a + b)
