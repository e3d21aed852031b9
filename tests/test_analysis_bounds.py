"""The supervised per-pixel references of ``analysis.metrics.bounds`` (issue 23: where the
segmenter fails, whether the pixels still told the materials apart)."""

from __future__ import annotations

import numpy as np
import pytest

from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.metrics.bounds import pixel_bounds, pixel_features
from m2s2hil.analysis.segmenters.spectral import SpectralSegmenter


def two_materials(noise: float, *, same: bool = False, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """48² scene: backdrop, then the left and right halves of a square, two spectra (or one)."""
    rng = np.random.default_rng(seed)
    gt = np.zeros((48, 48), np.int64)
    gt[8:40, 8:24] = 1
    gt[8:40, 24:40] = 2
    a = np.linspace(1.0, 2.0, 10)
    b = a if same else a[::-1]
    cube = np.zeros((10, 48, 48))
    cube[:, gt == 1] = 100.0 * a[:, None]
    cube[:, gt == 2] = 100.0 * b[:, None]
    return cube + rng.normal(0.0, noise, cube.shape), gt


def test_clean_materials_are_told_apart_by_both_references():
    cube, gt = two_materials(1.0)
    bounds = pixel_bounds(cube, gt)
    assert bounds.centroid > 0.99 and bounds.qda > 0.99


def test_noise_lowers_the_references():
    clean = pixel_bounds(*two_materials(1.0))
    noisy = pixel_bounds(*two_materials(150.0))
    assert noisy.centroid < clean.centroid - 0.05
    assert noisy.qda < clean.qda - 0.05


def test_identical_materials_cannot_be_told_apart():
    # same spectrum and brightness: no per-pixel classifier does better than chance on the halves
    bounds = pixel_bounds(*two_materials(5.0, same=True))
    assert bounds.centroid < 0.8 and bounds.qda < 0.8


def test_references_bound_the_unsupervised_segmenter():
    cube, gt = two_materials(25.0, seed=3)
    from m2s2hil.analysis.metrics.scores import score_clusters

    found = score_clusters(gt, SpectralSegmenter().analyse(cube).labels)[0].macro_dice
    assert pixel_bounds(cube, gt).qda >= found - 0.02


def test_one_material_is_trivially_bounded_and_bad_shapes_are_refused():
    cube, gt = two_materials(1.0)
    assert pixel_bounds(cube, np.where(gt > 0, 1, 0)).qda == 1.0
    with pytest.raises(AnalysisInputError, match="gt"):
        pixel_bounds(cube, gt[:40])


def test_features_are_the_segmenters_defaults():
    cube, _ = two_materials(1.0)
    f = pixel_features(cube)
    assert f.shape == (11, 48, 48)
    assert np.allclose(np.linalg.norm(f[:10], axis=0), 1.0)
    assert pixel_features(cube, 0.0).shape == (10, 48, 48)


def test_a_class_smaller_than_the_feature_count_is_handled():
    cube, gt = two_materials(1.0)
    gt[8:10, 8:11] = 3  # six pixels, eleven features: a singular covariance without shrinkage
    bounds = pixel_bounds(cube, gt)
    assert 0.5 < bounds.qda <= 1.0 and 0.5 < bounds.centroid <= 1.0
