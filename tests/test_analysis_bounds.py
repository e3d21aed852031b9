"""The supervised per-pixel references of ``analysis.metrics.bounds`` (issue 23: where the
segmenter fails, whether the pixels still told the materials apart)."""

from __future__ import annotations

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.metrics.bounds import frame_features, held_out_dice, pixel_bounds, pixel_features
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


def shaded_views(n: int, *, odd: int | None = None) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """``n`` views of the two-material square, each lit from another side (brightness falls 8-fold
    across the object, as under one lamp); in view ``odd`` the second material looks unlike it does
    in the others (a spectrum near the first's)."""
    cubes, gts = [], []
    for i in range(n):
        cube, gt = two_materials(2.0, seed=i)
        if i == odd:
            a = np.linspace(1.0, 2.0, 10)
            cube[:, gt == 2] = 100.0 * (a * np.linspace(0.9, 1.1, 10))[:, None] + cube[:, gt == 2] % 1
        ramp = np.geomspace(1 / 8, 1.0, 48)
        shade = ramp[None, None, :] if i % 2 else ramp[None, :, None]
        cubes.append(np.clip(cube * shade, 0, None))
        gts.append(gt)
    return cubes, gts


def test_held_out_views_are_labelled_from_the_others():
    cubes, gts = shaded_views(4)
    # every feature set with the Gaussian; the trees (a second each fold) once
    combos = (("segmenter", "qda"), ("pixel", "qda"), ("context", "qda"), ("segmenter", "boosting"))
    with threadpool_limits(1):  # the trees' OpenMP threads would contend with the other test workers
        for features, model in combos:
            dice = held_out_dice(cubes, gts, features=features, model=model)  # type: ignore[arg-type]
            assert len(dice) == 4 and min(dice) > 0.95, (features, model, dice)


def test_a_view_unlike_the_others_fails_held_out_though_it_fits_in_sample():
    cubes, gts = shaded_views(4, odd=2)
    dice = held_out_dice(cubes, gts, model="qda", features="pixel")
    assert dice[2] < 0.7 and min(dice[:2] + dice[3:]) > 0.95  # the others taught it the wrong look
    assert pixel_bounds(cubes[2], gts[2]).qda > 0.95  # fitted on itself it is easy


def test_frame_features_and_bad_views_are_typed():
    cube, gt = two_materials(1.0)
    assert [frame_features(cube, k).shape[0] for k in ("segmenter", "pixel", "context")] == [11, 20, 40]
    with pytest.raises(AnalysisInputError, match="features"):
        frame_features(cube, "colour")  # type: ignore[arg-type]
    with pytest.raises(AnalysisInputError, match="two or more"):
        held_out_dice([cube], [gt])
    with pytest.raises(AnalysisInputError, match="views\\[1\\]"):
        held_out_dice([cube, cube], [gt, gt[:10]])
    with pytest.raises(AnalysisInputError, match="model"):
        held_out_dice([cube, cube], [gt, gt], model="svm")  # type: ignore[arg-type]
