"""Issue 23, fifth pass: clipped pixels as censored data (``segmenters.censored``) and clip plateaus
spread over a few DN by dark subtraction (``normalise.clipped_bands``). Each behaviour is also run
the way it failed before (``censored=False``, or a plateau anchored at the band's maximum)."""

from __future__ import annotations

import numpy as np
import pytest

from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.metrics.scores import score_clusters
from m2s2hil.analysis.segmenters.censored import (
    explained,
    lower_bounds,
    merge_censored,
    observed_means,
    plateau_levels,
)
from m2s2hil.analysis.segmenters.normalise import PLATEAU_REL_TOL, clipped_bands, reliability
from m2s2hil.analysis.segmenters.spectral import SpectralSegmenter, foreground_mask, ranked
from m2s2hil.analysis.study.synthetic import exposed_scene, synthetic_scene

FULL_SCALE = 1000.0
DARK_SPREAD = 6  # DN: each pixel's dark value differs, so a clipped pixel reads full scale − its dark

# two bright materials whose peak bands clip on every pixel (shading 0.55-1.0 × 2000 DN > 1000 DN)
# at different bands, and a dim one that never clips
SPECTRA = np.array([
    [1.00, 1.00, 1.00, 0.45, 0.40, 0.35, 0.30, 0.28, 0.25, 0.22],
    [0.20, 0.25, 0.30, 0.35, 0.40, 1.00, 1.00, 1.00, 0.45, 0.40],
    [0.10, 0.11, 0.12, 0.13, 0.14, 0.15, 0.16, 0.17, 0.18, 0.19],
])


def clipped_scene(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(cube as the processor gives it, truth, clipped-before-dark mask (bands, H, W))."""
    clean, gt = synthetic_scene((64, 64), 3, spectra=SPECTRA, noise=0.0, background_level=0.01, seed=seed)
    rng = np.random.default_rng(seed)
    signal = clean.astype(np.float64) * 2000.0
    signal += rng.standard_normal(signal.shape) * np.sqrt(signal / 13.2 + 1.0)  # shot + read noise, DN
    clipped = signal >= FULL_SCALE
    dark = rng.integers(0, DARK_SPREAD + 1, size=gt.shape)[None].astype(np.float64)
    cube = np.clip(signal, 0.0, FULL_SCALE) - dark + DARK_SPREAD / 2  # dark-subtracted, a few DN wide
    return cube.astype(np.float32), gt, clipped


def test_a_plateau_spread_by_the_dark_is_found_whole():
    cube, gt, truth = clipped_scene()
    fg = gt > 0
    found = clipped_bands(cube, fg)
    assert truth[:, fg].mean() > 0.2
    assert np.all(found[truth & fg[None]])  # every clipped value
    assert np.all(cube[found] >= FULL_SCALE - 2 * DARK_SPREAD)  # and only values near the plateau
    # anchored at the band's maximum (the old rule), a tolerance of 0.4 % missed most of it
    top = cube.reshape(cube.shape[0], -1).max(axis=1)[:, None, None]
    old = cube >= top * (1 - PLATEAU_REL_TOL)
    assert old[truth & fg[None]].mean() < 0.9


def test_a_small_bright_part_is_not_a_plateau(monkeypatch):
    # ISS B3 at 60 % peak: 34 pixels of a bright part above a gap, no clipping, binned (0.4 % of the
    # maximum) fullest three bins below the top; a search over four top bins took them for a plateau
    cube, _ = exposed_scene(0.6, (64, 64), 3)
    fg, _ = foreground_mask(cube, "backdrop")
    counts = [4, 2, 7, 8, 5, 7, 1]  # bins from low to the band's maximum
    top = float(cube[4].max()) + 60.0
    delta = PLATEAU_REL_TOL * top
    values = [top - delta * (len(counts) - 1 - i) - delta / 2 for i, c in enumerate(counts) for _ in range(c)]
    values[-1] = top
    cube[4].ravel()[: len(values)] = values
    assert not clipped_bands(cube, fg)[4].any()
    monkeypatch.setattr("m2s2hil.analysis.segmenters.normalise.PLATEAU_SEARCH", 4)
    assert clipped_bands(cube, fg)[4].any()  # the wider search: the failure this guards against


def test_explained_needs_the_shape_and_the_clip_reached():
    m = np.array([[1.0, 2.0, 4.0, 2.0]])  # a material's mean spectrum
    levels = np.array([np.inf, np.inf, 1000.0, np.inf])
    x = np.array([
        [300.0, 600.0, 1000.0, 600.0],   # m at scale 300: band 2 would be 1200, clipped at 1000
        [300.0, 600.0, 1000.0, 300.0],   # band 3 does not fit m's shape
        [100.0, 200.0, 1000.0, 200.0],   # m at scale 100 puts band 2 at 400: it cannot have clipped
    ])
    seen = np.array([[True, True, False, True]] * 3)
    bounds = lower_bounds(x, seen, levels)
    assert explained(x, seen, m, bounds, tau_deg=3.0).tolist() == [True, False, False]
    # band 2 bent low by a clipped mosaic position (the processor's per-band mask, not the plateau):
    # its recorded 700 is the bound; m at scale 300 reaches 1200, at scale 100 only 400
    bent = np.array([[300.0, 600.0, 700.0, 600.0], [100.0, 200.0, 700.0, 200.0]])
    off_plateau = np.zeros((2, 4), bool)
    bounds = lower_bounds(bent, seen[:2], levels, off_plateau)
    assert bounds[:, 2].tolist() == [700.0, 700.0] and np.isinf(bounds[:, [0, 1, 3]]).all()
    assert explained(bent, seen[:2], m, bounds, tau_deg=3.0).tolist() == [True, False]
    values = np.array([[[5.0, 9.0]], [[1.0, 2.0]]])
    on_plateau = np.array([[[False, True]], [[False, False]]])
    assert plateau_levels(values, on_plateau).tolist() == [9.0, np.inf]


def test_groups_of_one_material_at_two_clip_patterns_merge():
    rng = np.random.default_rng(1)
    shape_a = np.array([1.0, 2.0, 3.0, 2.5, 2.0, 1.5])
    shape_b = np.array([3.0, 2.0, 1.0, 1.0, 2.0, 3.0])
    rows, seen, comp = [], [], []
    for g, (shape, clip) in enumerate([(shape_a, 2), (shape_a, 3), (shape_b, 0)]):
        for _ in range(40):
            x = shape * rng.uniform(200, 300) + rng.normal(0, 1, 6)
            ok = np.ones(6, dtype=bool)
            ok[clip] = False
            x[clip] = 1000.0
            rows.append(x)
            seen.append(ok)
            comp.append(g)
    x, ok, c = np.array(rows), np.array(seen), np.array(comp)
    means = observed_means(x, ok, c, 3)
    assert np.isnan(means[0, 2]) and np.isnan(means[1, 3]) and np.isfinite(means[0, 3])
    assert merge_censored(x, ok, c, 3, 3.0).tolist() == [0] * 80 + [1] * 40


def test_whole_materials_clipped_are_fitted_apart():
    cube, gt, _ = clipped_scene()
    before = SpectralSegmenter(censored=False).analyse(cube)
    now = SpectralSegmenter().analyse(cube)
    # without the censored fit only the dim material is fitted and every clipped pixel joins it
    assert before.n_materials == 1 and before.censored is None
    assert now.n_materials == 3 and now.censored is not None
    assert now.censored[(gt == 1) | (gt == 2)].mean() > 0.9 and not now.censored[gt == 3].any()
    dice_before = score_clusters(gt, before.labels)[0].macro_dice
    dice_now = score_clusters(gt, now.labels)[0].macro_dice
    assert dice_now > 0.9 > dice_before + 0.3


def test_a_given_count_bounds_the_censored_fit_too():
    """With the catalog's count the map has at most that many materials: the censored fit gets
    what the unclipped fit left (it used to add its own on top: 3 materials for a count of 1 or 2)."""
    cube, gt, _ = clipped_scene()
    for given in (1, 2, 3):
        a = SpectralSegmenter(n_materials=given).analyse(cube)
        assert a.n_materials == given, given
    assert SpectralSegmenter(n_materials=1).analyse(cube).censored is None  # no room: not fitted
    both = SpectralSegmenter(n_materials=2).analyse(cube)
    assert both.censored is not None and score_clusters(gt, both.labels)[0].macro_dice > 0.6


def test_an_unclipped_cube_is_not_touched():
    cube, _ = exposed_scene(0.6, (64, 64), 3)
    on, off = SpectralSegmenter().analyse(cube), SpectralSegmenter(censored=False).analyse(cube)
    assert on.censored is None and np.array_equal(on.labels, off.labels)


def test_ranked_numbers_by_size_and_the_share_is_checked():
    labels = np.array([[0, 3, 3], [3, 5, 5], [5, 5, 1]])
    assert ranked(labels).tolist() == [[0, 2, 2], [2, 1, 1], [1, 1, 3]]
    with pytest.raises(AnalysisInputError, match="censored_min_share"):
        SpectralSegmenter(censored_min_share=1.0)


def test_a_band_bent_by_a_clipped_mosaic_position_is_censored_only_with_the_per_band_mask():
    """One material brightening left to right until bands 3–5 clip. Where they clip, one of band 2's
    mosaic positions clipped too: the cell's mean is bent low, not at a plateau. The cube and a
    pixel mask take the bent shape for a material of its own; the per-band mask
    (``processing.stability.band_saturation``, what the evaluation gives) makes band 2 a lower
    bound there, and the material explains it."""
    rng = np.random.default_rng(0)
    spec = np.array([0.22, 0.33, 0.4, 0.44, 0.42, 0.36, 0.29, 0.23, 0.17, 0.1])
    yy, xx = np.mgrid[:64, :64]
    obj = (yy - 32) ** 2 + (xx - 32) ** 2 < 26**2
    cube = np.zeros((10, 64, 64), np.float32)
    cube[:, obj] = spec[:, None] * (1540.0 + 1980.0 * xx[obj] / 64)[None]
    cube += rng.normal(0.0, 3.0, cube.shape).astype(np.float32)
    full = 1023.0
    clipped = np.zeros(cube.shape, bool)
    for b in (2, 3, 4):
        clipped[b] = obj & (cube[b] > full)
        cube[b][clipped[b]] = full
    bent = obj & clipped[3] & (xx > 40)
    cube[1][bent] = 0.5 * (full + 0.6 * cube[1][bent])  # below the true value, above no plateau
    clipped[1] |= bent
    assert bent.sum() > 0.2 * obj.sum()
    seg = SpectralSegmenter()
    assert seg.analyse(cube).n_materials == 2
    assert seg.analyse(cube, saturated=clipped.any(axis=0)).n_materials == 2
    by_band = seg.analyse(cube, saturated=clipped)
    assert by_band.n_materials == 1 and by_band.censored is None
    rel = reliability(cube, obj, saturated=clipped)
    assert rel.clipped[1][bent].all() and not rel.plateau[1][bent].any()  # clipped, yet off the plateau
    with pytest.raises(AnalysisInputError, match="expected"):
        reliability(cube, obj, saturated=clipped[:4])
