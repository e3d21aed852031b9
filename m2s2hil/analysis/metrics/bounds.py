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

``held_out_dice`` asks the other question, whether the information is in the frame at all: a
classifier trained on *other* views of the same build and scene (leave one view out) labels the
held-out view. Its features (``FEATURES``) are the segmenter's (``segmenter``), every band's log
and the unit spectrum (``pixel``), or those with their 3 × 3 and 7 × 7 box means (``context``:
what a pixel's neighbours say); its model a Gaussian per class (``qda``) or gradient-boosted trees
(``boosting``, scikit-learn's ``HistGradientBoostingClassifier``). Told the materials' looks from
the other views, it sees what an unsupervised method must find for itself: where it holds and the
segmenter does not, the loss is the segmenter's, not the pixels'.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from m2s2hil.analysis.arrays import as_cube
from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.metrics.scores import score_clusters
from m2s2hil.analysis.segmenters.pose import pose_features


@dataclass(frozen=True)
class PixelBounds:
    centroid: float  # macro Dice, nearest true class mean
    qda: float  # macro Dice, quadratic discriminant analysis on the truth


def pixel_features(cube: np.ndarray, brightness_weight: float = 0.1) -> np.ndarray:
    """(features, H, W): unit spectra and ``brightness_weight`` · log energy (the segmenter's defaults;
    ``spectral-pose`` teaches its trees on the same)."""
    if brightness_weight <= 0:
        return cube / np.maximum(np.linalg.norm(cube, axis=0), 1e-12)
    return pose_features(cube, brightness_weight)


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


Features = Literal["segmenter", "pixel", "context"]
Model = Literal["qda", "boosting"]
FEATURES: tuple[str, ...] = ("segmenter", "pixel", "context")
LOG_FLOOR_DN = 0.05  # below a x16 bracket's step (1/16 DN), so lifted shadows keep their values


def frame_features(cube: np.ndarray, kind: Features = "context") -> np.ndarray:
    """(features, H, W) of ``held_out_dice`` (module docstring)."""
    arr = np.asarray(cube, dtype=np.float64)
    if kind == "segmenter":
        return pixel_features(arr)
    if kind not in FEATURES:
        raise AnalysisInputError("features", f"{kind!r}; known: {', '.join(FEATURES)}")
    logs = np.log(np.maximum(arr, LOG_FLOOR_DN))
    unit = arr / np.maximum(np.linalg.norm(arr, axis=0), 1e-12)
    if kind == "pixel":
        return np.concatenate([logs, unit])
    from scipy.ndimage import uniform_filter

    near = [uniform_filter(logs, size=(1, n, n), mode="reflect") for n in (3, 7)]
    return np.concatenate([logs, unit, *near])


def _fit(x: np.ndarray, y: np.ndarray, model: Model, seed: int) -> Any:
    ids, counts = np.unique(y, return_counts=True)
    if ids.size < 2:  # one class (or no object) in the other views: that is the answer
        return int(ids[0]) if ids.size else 0
    if model == "boosting":
        from sklearn.ensemble import HistGradientBoostingClassifier

        # (the leaf penalty: unpenalised, a class of a few dozen pixels made the softmax diverge;
        # segmenters.pose measured it; the thirteenth pass's figures were taken without it)
        return HistGradientBoostingClassifier(max_iter=100, early_stopping=False, l2_regularization=1.0,
                                              random_state=seed).fit(x, y)
    from sklearn.discriminant_analysis import QuadraticDiscriminantAnalysis

    keep = np.isin(y, ids[counts >= x.shape[1] + 2])  # as pixel_bounds: too few pixels, no covariance
    if np.unique(y[keep]).size < 2:
        return int(ids[counts.argmax()])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return QuadraticDiscriminantAnalysis(reg_param=1e-3).fit(x[keep], y[keep])


def held_out_dice(cubes: Sequence[np.ndarray], gts: Sequence[np.ndarray], *, features: Features = "context",
                  model: Model = "boosting", sample: int = 20_000, seed: int = 0) -> list[float]:
    """Macro Dice of each view labelled by a classifier trained on the other views (module
    docstring); ``sample``: at most that many training pixels per fold, drawn uniformly."""
    if len(cubes) != len(gts) or len(cubes) < 2:
        raise AnalysisInputError("views", f"{len(cubes)} cubes and {len(gts)} label maps; held out needs "
                                 "two or more of each")
    if model not in ("qda", "boosting"):
        raise AnalysisInputError("model", f"{model!r}; known: qda, boosting")
    xs, ys, truths = [], [], []
    for i, (cube, gt) in enumerate(zip(cubes, gts, strict=True)):
        truth = np.asarray(gt)
        if truth.shape != np.shape(cube)[1:]:
            raise AnalysisInputError(f"views[{i}]", f"label map {truth.shape}, cube {np.shape(cube)}")
        obj = truth > 0
        xs.append(frame_features(cube, features)[:, obj].T)
        ys.append(truth[obj].astype(np.int64))
        truths.append(truth)
    rng = np.random.default_rng(seed)
    out = []
    for i in range(len(xs)):
        x = np.concatenate([v for j, v in enumerate(xs) if j != i])
        y = np.concatenate([v for j, v in enumerate(ys) if j != i])
        if x.shape[0] > sample:
            pick = rng.choice(x.shape[0], sample, replace=False)
            x, y = x[pick], y[pick]
        fitted = _fit(x, y, model, seed)
        if isinstance(fitted, int) or len(xs[i]) == 0:
            labels = np.full(len(xs[i]), fitted if isinstance(fitted, int) else 0)
        else:
            labels = fitted.predict(xs[i])
        full = np.zeros(truths[i].shape, dtype=np.int64)
        full[truths[i] > 0] = labels
        out.append(float(score_clusters(truths[i], full)[0].macro_dice))
    return out
