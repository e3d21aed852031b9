"""PCA band selection on synthetic cubes whose informative bands are known."""

from __future__ import annotations

import numpy as np
import pytest

from m2s2hil.analysis.bands import select_bands_pca
from m2s2hil.analysis.errors import AnalysisInputError


def _factor_cube(seed: int, shape: tuple[int, int] = (50, 80)) -> np.ndarray:
    """Three latent factors; each drives one 'pure' band (amplitude 1) and noisy half-amplitude copies.

    Factor 1 (largest, 4 bands) is pure in band 5, factor 2 in band 9, factor 3 in band 10 (1-based),
    so the rule "largest |loading| on PC i" must return 5, 9, 10.
    """
    rng = np.random.default_rng(seed)
    n = shape[0] * shape[1]
    groups = [(3.0, [2, 3, 5], 4, 0.3), (2.0, [6, 7], 8, 0.2), (1.5, [0, 1], 9, 0.4)]
    cube = np.empty((10, n))
    for scale, noisy, pure, noise in groups:
        f = rng.normal(scale=scale, size=n)
        cube[pure] = f
        for b in noisy:
            cube[b] = 0.5 * f + rng.normal(scale=noise * scale, size=n)
    return cube.reshape(10, *shape)


@pytest.mark.parametrize("standardize", [True, False])
def test_known_informative_bands(standardize: bool) -> None:
    sel = select_bands_pca(_factor_cube(0), k=3, standardize=standardize)
    assert sel.bands == (4, 8, 9)
    assert sel.bands_1based == (5, 9, 10)
    assert sel.loadings.shape == (3, 10)
    assert np.all(np.diff(sel.explained_variance_ratio) <= 0)


def test_several_cubes_and_subsampling() -> None:
    cubes = [_factor_cube(1), _factor_cube(2)]
    sel = select_bands_pca(cubes, k=2, n_components=4, max_pixels=3000, seed=3)
    assert sel.bands_1based == (5, 9)
    assert sel.n_pixels == 3000 and sel.loadings.shape == (4, 10)


def test_standardisation_ignores_a_loud_uncorrelated_band() -> None:
    cube = _factor_cube(4)
    cube[0] = np.random.default_rng(9).normal(scale=40.0, size=cube.shape[1:])
    assert select_bands_pca(cube, k=1, standardize=False).bands_1based == (1,)
    assert select_bands_pca(cube, k=2, standardize=True).bands_1based == (5, 9)


def test_mask_limits_the_pixels() -> None:
    cube = _factor_cube(5)
    mask = np.ones(cube.shape[1:], dtype=bool)
    mask[:10] = False
    cube[1, :10] = 1e4 * np.random.default_rng(0).normal(size=(10, cube.shape[2]))  # junk outside the mask
    assert select_bands_pca(cube, k=1, standardize=False).bands_1based == (2,)
    assert select_bands_pca(cube, k=3, masks=[mask]).bands_1based == (5, 9, 10)


def test_loadings_table_is_one_based_and_marks_picks() -> None:
    sel = select_bands_pca(_factor_cube(0), k=3)
    table = sel.loadings_table(bands_nm=(431, 479, 515, 567, 611, 666, 719, 775, 820, 877))
    lines = table.splitlines()
    assert len(lines) == 2 + 10
    assert lines[2].startswith("| 1 | 431 |")
    assert "*" in lines[2 + 4].split("|")[3]  # band 5, PC1 column
    assert "*" in lines[2 + 9].split("|")[5]  # band 10, PC3 column


def test_bad_arguments() -> None:
    cube = _factor_cube(0, (8, 8))
    with pytest.raises(AnalysisInputError, match="k"):
        select_bands_pca(cube, k=11)
    with pytest.raises(AnalysisInputError, match="n_components"):
        select_bands_pca(cube, k=3, n_components=2)
    with pytest.raises(AnalysisInputError, match=r"cubes\[1\]"):
        select_bands_pca([cube, cube[:5]], k=2)
    with pytest.raises(AnalysisInputError, match="masks"):
        select_bands_pca(cube, masks=[np.ones((3, 3), bool)])
