"""PCA band choice with its stability: a bootstrap over frames."""

from __future__ import annotations

import numpy as np
import pytest

from m2s2hil.analysis.bands import select_bands_pca
from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.metrics.band_stability import _pick, band_stability


def _frame(rng: np.random.Generator, structured: bool, n: int = 150) -> np.ndarray:
    """Six bands. Structured: bands 1-3 follow one factor and 4-6 another, bands 1 and 4 most
    closely (the largest loadings); otherwise every band is independent noise."""
    if not structured:
        return rng.normal(size=(n, 6))
    z1, z2 = rng.normal(size=(2, n))
    e = rng.normal(size=(4, n))
    return np.column_stack([z1, 0.7 * z1 + 0.7 * e[0], 0.7 * z1 + 0.7 * e[1],
                            z2, 0.7 * z2 + 0.7 * e[2], 0.7 * z2 + 0.7 * e[3]])


def test_a_clear_structure_gives_a_stable_pick_noise_does_not() -> None:
    rng = np.random.default_rng(0)
    stable = band_stability([_frame(rng, True) for _ in range(10)], k=2, n_boot=100)
    assert stable.bands == (1, 4) and stable.n_frames == 10 and stable.n_boot == 100
    assert stable.pick_frequency >= 0.9 and stable.band_frequency[1] >= 0.9
    noise = band_stability([_frame(rng, False) for _ in range(10)], k=2, n_boot=100)
    assert noise.pick_frequency < 0.6 and len(noise.set_frequency) >= 3
    for s in (stable, noise):  # each resample picks k bands: frequencies add up
        assert sum(s.band_frequency.values()) == pytest.approx(2.0)
        assert sum(s.set_frequency.values()) == pytest.approx(1.0)
        assert list(s.set_frequency.values()) == sorted(s.set_frequency.values(), reverse=True)
    assert "bands 1, 4 on all 10 frames" in stable.summary()
    d = stable.as_dict()
    assert d["bands"] == [1, 4] and d["set_frequency"][0]["bands"] == [1, 4]


def test_band_stability_refuses_too_little() -> None:
    with pytest.raises(AnalysisInputError, match="at least 2 frames"):
        band_stability([np.ones((10, 4))])
    with pytest.raises(AnalysisInputError, match="bands"):
        band_stability([np.ones((10, 4)), np.ones((10, 5))])


def test_the_bootstrap_pick_is_select_bands_pca() -> None:
    rng = np.random.default_rng(4)
    for trial in range(5):
        frames = [rng.normal(size=(80, 10)) * rng.uniform(0.5, 3, 10) + rng.normal(size=(80, 1)) * trial
                  for _ in range(3)]
        pooled = np.concatenate(frames).T[:, :, np.newaxis]
        for standardize in (True, False):
            ref = select_bands_pca(pooled, k=3, standardize=standardize)
            assert _pick(frames, 3, standardize) == tuple(sorted(ref.bands_1based)), (trial, standardize)
