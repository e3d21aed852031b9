"""Oracle matching of predicted cluster ids to ground-truth class ids.

Segmenters return cluster ids (which material is "cluster 3" is unknown), so before
scoring against ground truth each cluster is given a class by a one-to-one Hungarian
assignment that maximises the number of agreeing pixels
(``scipy.optimize.linear_sum_assignment`` on the gt × cluster contingency matrix from
``sklearn.metrics.cluster.contingency_matrix``).

This is an *oracle*: it looks at the ground truth, so scores after matching are an
upper bound on what the same segmenter would score with a real cluster-to-material
rule. Conventions:

- ``keep_background=True`` (default): predicted 0 is the segmenter's own background
  decision and maps to ground-truth 0; only non-zero clusters enter the assignment.
- A cluster left unmatched (more clusters than classes, or its only possible pairing
  shares no pixel with the class) gets a fresh id above every
  ground-truth label (``max_gt + 1``, ``max_gt + 2`` ... in cluster order). Its pixels are
  then errors: false negatives of the classes they cover, and — under the ``"union"``
  label set of ``segmentation_scores`` — an extra class with precision 0 and Dice 0.
- A ground-truth class left without a cluster simply gets no true positives.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from m2s2hil.analysis.arrays import as_label_map, same_shape


@dataclass(frozen=True)
class ClusterMatch:
    """Result of ``match_clusters``: the map from cluster id to label and the relabelled prediction."""

    mapping: dict[int, int]
    unmatched: tuple[int, ...]
    relabelled: np.ndarray
    overlap: int  # pixels on which the matched prediction agrees with the ground truth


def match_clusters(
    gt: object,
    pred: object,
    *,
    keep_background: bool = True,
    ignore_index: int | None = None,
) -> ClusterMatch:
    """Assign each predicted cluster to at most one ground-truth class (Hungarian, max overlap).

    Pixels whose ground truth equals ``ignore_index`` do not vote in the assignment.
    """
    g = as_label_map(gt, "gt")
    p = as_label_map(pred, "pred")
    same_shape(g, p, ("gt", "pred"))
    gv, pv = g.ravel(), p.ravel()
    if ignore_index is not None:
        keep = gv != ignore_index
        gv, pv = gv[keep], pv[keep]
    classes = np.unique(gv)
    clusters = np.unique(p)  # every cluster needs a label, also those only on ignored pixels
    mapping: dict[int, int] = {}
    if keep_background and 0 in clusters:
        mapping[0] = 0
    cand_clusters = [c for c in clusters if int(c) not in mapping]
    cand_classes = [c for c in classes if not (keep_background and c == 0)]
    if cand_clusters and cand_classes and gv.size:
        from sklearn.metrics.cluster import contingency_matrix  # loaded on first use

        table = contingency_matrix(gv, pv)  # rows: np.unique(gv), cols: np.unique(pv)
        rows = np.searchsorted(classes, cand_classes)
        seen = np.unique(pv)
        sub = np.zeros((len(cand_classes), len(cand_clusters)), dtype=np.int64)
        for j, c in enumerate(cand_clusters):
            k = np.searchsorted(seen, c)
            if k < seen.size and seen[k] == c:
                sub[:, j] = table[rows, k]
        r, c = linear_sum_assignment(sub, maximize=True)
        for ri, ci in zip(r, c, strict=True):
            if sub[ri, ci] == 0:
                continue  # a pairing without a single shared pixel is no match
            mapping[int(cand_clusters[ci])] = int(cand_classes[ri])
    fresh = int(max(int(g.max()), ignore_index if ignore_index is not None else 0)) + 1
    unmatched = []
    for c in clusters:
        if int(c) not in mapping:
            mapping[int(c)] = fresh
            unmatched.append(int(c))
            fresh += 1
    lut_keys = np.array(sorted(mapping), dtype=np.int64)
    lut_vals = np.array([mapping[k] for k in lut_keys], dtype=np.int64)
    relabelled = lut_vals[np.searchsorted(lut_keys, p)]
    agree_mask = relabelled == g
    if ignore_index is not None:
        agree_mask &= g != ignore_index
    return ClusterMatch(mapping, tuple(unmatched), relabelled, int(agree_mask.sum()))
