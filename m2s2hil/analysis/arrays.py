"""Validation of the two array kinds the analysis library takes.

Conventions (used everywhere in ``m2s2hil.analysis``):

- a *cube* is a float array ``(bands, H, W)`` (channels first, like the processing
  pipeline's hypercubes); a single band ``(H, W)`` is accepted where noted;
- a *label map* is an integer array ``(H, W)``; label 0 is background.
"""

from __future__ import annotations

import numpy as np

from m2s2hil.analysis.errors import AnalysisInputError


def as_cube(cube: object, argument: str = "cube") -> np.ndarray:
    """Return ``cube`` as a finite float32 ``(bands, H, W)`` array or raise AnalysisInputError."""
    arr = np.asarray(cube)
    if arr.ndim == 2:
        arr = arr[np.newaxis]
    if arr.ndim != 3:
        raise AnalysisInputError(argument, f"expected a (bands, H, W) cube, got shape {arr.shape}")
    if arr.dtype.kind not in "uif":
        raise AnalysisInputError(argument, f"expected numeric data, got dtype {arr.dtype}")
    if min(arr.shape) == 0:
        raise AnalysisInputError(argument, f"empty cube of shape {arr.shape}")
    out = arr.astype(np.float32, copy=False)
    if not np.isfinite(out).all():
        raise AnalysisInputError(argument, "contains NaN or infinite values")
    return out


def as_label_map(labels: object, argument: str = "labels") -> np.ndarray:
    """Return ``labels`` as a non-negative int64 ``(H, W)`` array or raise AnalysisInputError."""
    arr = np.asarray(labels)
    if arr.ndim != 2:
        raise AnalysisInputError(argument, f"expected an (H, W) label map, got shape {arr.shape}")
    if arr.dtype.kind == "b":
        arr = arr.astype(np.int64)
    if arr.dtype.kind not in "ui":
        raise AnalysisInputError(argument, f"expected integer labels, got dtype {arr.dtype}")
    if arr.size == 0:
        raise AnalysisInputError(argument, "empty label map")
    out = arr.astype(np.int64, copy=False)
    if out.min() < 0:
        raise AnalysisInputError(argument, f"negative label {int(out.min())}")
    return out


def same_shape(a: np.ndarray, b: np.ndarray, names: tuple[str, str]) -> None:
    """Raise AnalysisInputError unless two label maps have the same shape."""
    if a.shape != b.shape:
        raise AnalysisInputError(names[1], f"shape {b.shape} differs from {names[0]} shape {a.shape}")
