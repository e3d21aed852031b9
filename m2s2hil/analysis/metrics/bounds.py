"""Supervised per-pixel references: how well a classifier *told the truth* does on the features the
spectral segmenter clusters, per frame.

A robustness cell can fail because the segmenter (unsupervised: it must find the materials) falls
short, or because the pixels themselves no longer tell the materials apart (shadow, highlights,
noise). These references separate the two. Both see the segmenter's default features (unit
spectrum plus ``brightness_weight`` · log energy) of the object's pixels (``gt > 0``) and the
ground truth, and are scored like the segmenter (``score_clusters``, macro Dice):

- ``centroid``: every pixel to the nearest true class mean (means from the frame's own truth);
- ``qda``: ``sklearn``'s quadratic discriminant analysis fitted on the frame's pixels and their
  truth (a Gaussian per class with its own covariance: the segmenter's mixture, with the right
  components); a class of fewer pixels than features + 2 has no covariance to estimate and is
  left out of the fit, its pixels counted as errors.

Both are scored on the pixels they were fitted on (resubstitution), so they are optimistic: an
upper reference for any per-pixel method on these features, not a held-out accuracy. Neither uses
space (neighbours, regions), so a spatial method can still beat them.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from m2s2hil.analysis.arrays import as_cube
from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.metrics.scores import score_clusters


@dataclass(frozen=True)
class PixelBounds:
    centroid: float  # macro Dice, nearest true class mean
    qda: float  # macro Dice, quadratic discriminant analysis on the truth


def pixel_features(cube: np.ndarray, brightness_weight: float = 0.1) -> np.ndarray:
    """(features, H, W): unit spectra and ``brightness_weight`` · log energy (the segmenter's defaults)."""
    energy = np.linalg.norm(cube, axis=0)
    unit = cube / np.maximum(energy, 1e-12)
    if brightness_weight <= 0:
        return unit
    return np.concatenate([unit, brightness_weight * np.log(np.maximum(energy, 1e-12))[np.newaxis]])


def pixel_bounds(cube: object, gt: object, *, brightness_weight: float = 0.1) -> PixelBounds:
    """Macro Dice of the two supervised references on ``cube`` (bands, H, W) against ``gt`` (H, W)."""
    from sklearn.discriminant_analysis import QuadraticDiscriminantAnalysis

    arr = as_cube(cube).astype(np.float64)
    truth = np.asarray(gt)
    if truth.shape != arr.shape[1:]:
        raise AnalysisInputError("gt", f"shape {truth.shape}, expected {arr.shape[1:]} (the cube's)")
    obj = truth > 0
    ids = np.unique(truth[obj])
    if ids.size < 2:  # one material (or none): assigning the object is all there is to do
        return PixelBounds(1.0, 1.0)
    x = pixel_features(arr, brightness_weight)[:, obj].T
    y = truth[obj]
    means = np.stack([x[y == i].mean(axis=0) for i in ids])
    nearest = ids[((x[:, None, :] - means[None]) ** 2).sum(axis=-1).argmin(axis=1)]
    # a small ridge for unit spectra's near-singular covariance; a class of fewer pixels than
    # features + 2 has no covariance to estimate and is left out (its pixels then count as errors)
    counts = {int(i): int(np.sum(y == i)) for i in ids}
    fitted = np.isin(y, [i for i, c in counts.items() if c >= x.shape[1] + 2])
    predicted = np.zeros_like(y)
    if len({int(v) for v in y[fitted]}) >= 2:
        qda = QuadraticDiscriminantAnalysis(reg_param=1e-3)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # sklearn's "variables are collinear"
            predicted = qda.fit(x[fitted], y[fitted]).predict(x)
    else:  # at most one class large enough: the object is that class
        predicted[:] = int(np.bincount(y).argmax())
    out = []
    for labels in (nearest, predicted):
        full = np.zeros(truth.shape, dtype=np.int64)
        full[obj] = labels
        out.append(float(score_clusters(truth, full)[0].macro_dice))
    return PixelBounds(*out)
