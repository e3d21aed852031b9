"""mTC: the seeded shifts, exact inverse, and scores computed by hand from those shifts."""

from __future__ import annotations

import numpy as np
import pytest

from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.metrics.mtc import band_fused_predictor, draw_shifts, mtc, translate, untranslate

# The documented draw: np.random.default_rng(42).integers(-3, 4, size=(8, 2)), rows (dx, dy).
PAPER_SHIFTS = ((-3, 2), (1, 0), (0, 3), (-3, 1), (-2, -3), (0, 3), (2, 2), (2, 2))


def test_seeded_draw_order() -> None:
    assert draw_shifts() == PAPER_SHIFTS
    assert draw_shifts(k=3) == PAPER_SHIFTS[:3]  # one call: the first rows do not depend on K
    assert all(-1 <= v <= 1 for s in draw_shifts(k=50, max_shift=1, seed=5) for v in s)
    with pytest.raises(AnalysisInputError):
        draw_shifts(k=0)


def test_translation_direction_and_exact_inverse() -> None:
    cube = np.zeros((2, 5, 6))
    cube[:, 1, 2] = 7.0
    moved = translate(cube, dx=2, dy=-1)
    assert moved[0, 0, 4] == 7.0 and moved[1, 0, 4] == 7.0  # right by 2, up by 1, all bands alike
    rng = np.random.default_rng(0)
    x = rng.normal(size=(3, 9, 11))
    for dx, dy in PAPER_SHIFTS:
        np.testing.assert_array_equal(untranslate(translate(x, dx, dy), dx, dy), x)


def test_pixelwise_predictor_scores_exactly_one() -> None:
    rng = np.random.default_rng(1)
    cube = rng.uniform(size=(4, 20, 24))
    result = mtc(lambda c: (c[0] > 0.5).astype(int) + (c[2] > 0.7), cube)
    assert result.score == 1.0
    assert result.ious == (1.0,) * 8
    assert result.shifts == PAPER_SHIFTS


def test_constant_predictor_scores_one() -> None:
    cube = np.zeros((3, 10, 10))
    assert mtc(lambda c: np.full(c.shape[1:], 2), cube).score == 1.0


def test_fixed_map_ignoring_input_gives_hand_value() -> None:
    # f ignores x and returns F = 1 on the left half (16×16). Rolled back by Δx, 2|Δx| columns
    # disagree: agree = 256 − 32|Δx|, IoU = agree/(agree + 2·disagree) = (8 − |Δx|)/(8 + |Δx|).
    fixed = np.zeros((16, 16), dtype=int)
    fixed[:, :8] = 1
    result = mtc(lambda c: fixed, np.zeros((3, 16, 16)))
    # |Δx| of the paper shifts: 3, 1, 0, 3, 2, 0, 2, 2
    expected = [5 / 11, 7 / 9, 1.0, 5 / 11, 6 / 10, 1.0, 6 / 10, 6 / 10]
    np.testing.assert_allclose(result.ious, expected)
    assert result.score == pytest.approx(np.mean(expected))  # 0.68586...


def test_fixed_map_rows_use_dy() -> None:
    fixed = np.zeros((16, 16), dtype=int)
    fixed[:8, :] = 1
    result = mtc(lambda c: fixed, np.zeros((1, 16, 16)))
    # |Δy|: 2, 0, 3, 1, 3, 3, 2, 2
    expected = [6 / 10, 1.0, 5 / 11, 7 / 9, 5 / 11, 5 / 11, 6 / 10, 6 / 10]
    np.testing.assert_allclose(result.ious, expected)


def test_ignore_label_omits_background_from_the_sums() -> None:
    # Label 1 on 4 of 16 columns; ignoring 0: TP = 16(4 − |Δx|), FP + FN = 32|Δx|,
    # IoU = (4 − |Δx|)/(4 + |Δx|); counting 0 as well it is (8 − |Δx|)/(8 + |Δx|).
    fixed = np.zeros((16, 16), dtype=int)
    fixed[:, :4] = 1
    with_bg = mtc(lambda c: fixed, np.zeros((16, 16)))
    without_bg = mtc(lambda c: fixed, np.zeros((16, 16)), ignore_label=0)
    np.testing.assert_allclose(with_bg.ious, [(8 - abs(dx)) / (8 + abs(dx)) for dx, _ in PAPER_SHIFTS])
    expected = [1 / 7, 3 / 5, 1.0, 1 / 7, 2 / 6, 1.0, 2 / 6, 2 / 6]
    np.testing.assert_allclose(without_bg.ious, expected)


def test_explicit_shifts_override_the_draw() -> None:
    fixed = np.zeros((16, 16), dtype=int)
    fixed[:, :8] = 1
    r = mtc(lambda c: fixed, np.zeros((16, 16)), shifts=[(4, 0), (0, 5)])
    assert r.ious == pytest.approx([4 / 12, 1.0])
    assert r.as_dict()["shifts"] == [[4, 0], [0, 5]]


def test_band_fused_binary_predictor() -> None:
    # Three selected bands (1-based 1, 2, 3), each thresholded; fusion = majority, ties to foreground.
    cube = np.zeros((4, 1, 4))
    cube[0, 0] = [1, 1, 0, 0]
    cube[1, 0] = [1, 0, 1, 0]
    cube[2, 0] = [1, 0, 0, 0]
    cube[3, 0] = [1, 1, 1, 1]  # band 4 is not selected
    f = band_fused_predictor(lambda band: (band[0] > 0.5).astype(int) * 3, bands=(1, 2, 3))
    assert f(cube).tolist() == [[1, 0, 0, 0]]  # votes 3, 1, 1, 0 of 3
    g = band_fused_predictor(lambda band: (band[0] > 0.5).astype(int), bands=(1, 2))
    assert g(cube).tolist() == [[1, 1, 1, 0]]  # votes 2, 1, 1, 0 of 2: ties favour foreground
    # pixel-wise per band, hence translation invariant
    rng = np.random.default_rng(2)
    assert mtc(f, rng.uniform(size=(10, 12, 12))).score == 1.0
    with pytest.raises(AnalysisInputError, match="band 3"):
        f(np.zeros((2, 4, 4)))


def test_prediction_of_wrong_shape_is_rejected() -> None:
    with pytest.raises(AnalysisInputError, match="shape"):
        mtc(lambda c: np.zeros((3, 3), int), np.zeros((2, 8, 8)))
    with pytest.raises(AnalysisInputError):
        mtc(lambda c: np.zeros((8, 8), int), np.zeros((2, 2, 8, 8)))


def test_align_option_forgives_permuted_cluster_ids() -> None:
    # Pixel-wise segments from band 1, but the ids swap unless the marker pixel sits at (0, 0):
    # every shift below moves it, so each shifted prediction is the base with ids 1 <-> 2.
    def swapping(c: np.ndarray) -> np.ndarray:
        labels = np.where(c[1] > 0.5, 1, 2)
        return labels if c[0, 0, 0] == 1.0 else 3 - labels

    cube = np.zeros((2, 8, 8))
    cube[0, 0, 0] = 1.0
    cube[1, :, :3] = 1.0
    shifts = [(0, 1), (1, 0), (2, 3)]
    assert mtc(swapping, cube, shifts=shifts).score == 0.0
    assert mtc(swapping, cube, shifts=shifts, align=True).score == 1.0


# -- a shift that changes what is fitted (ResampledFit) ------------------------------------
class MedianSplit:
    """Splits its foreground at the median of a seeded sample of it: the split moves with the sample
    (shift-sensitive once the sample changes); ``fixed`` splits at 0.5 whatever it drew (stable)."""

    name = "median-split"
    foreground = "otsu"

    def __init__(self, sample_size: int = 10_000, seed: int = 0, fixed: bool = False) -> None:
        self.sample_size, self.seed, self.fixed = sample_size, seed, fixed
        self.calls: list[tuple[int, int]] = []

    def segment(self, cube: np.ndarray) -> np.ndarray:
        x = cube[0]
        fg = x > 0.05
        vals = x[fg]  # raster order: the same for every shift of an object off the border
        if vals.size > self.sample_size:
            vals = vals[np.random.default_rng(self.seed).choice(vals.size, self.sample_size, replace=False)]
        self.calls.append((self.seed, int(vals.size)))
        t = 0.5 if self.fixed else float(np.median(vals))
        return np.where(fg, np.where(x > t, 2, 1), 0)


def _ramp_disc(n: int = 48) -> np.ndarray:
    yy, xx = np.mgrid[:n, :n]
    disc = (yy - n / 2) ** 2 + (xx - n / 2) ** 2 < (n / 3) ** 2
    rng = np.random.default_rng(3)
    values = np.where(disc, 0.2 + 0.8 * xx / n + rng.normal(0, 0.02, (n, n)), 0.001)
    return np.stack([values, values])


def test_fixed_sampling_fits_the_same_pixels_after_a_shift_resampling_does_not() -> None:
    from m2s2hil.analysis.metrics.mtc import ResampledFit

    cube = _ramp_disc()
    n_fg = int((cube[0] > 0.05).sum())
    seg = MedianSplit(sample_size=n_fg // 2)  # the sample is below the pool, but drawn by index
    assert mtc(seg.segment, cube).score == 1.0  # issue 23: order invariance, not stability
    wrapped = ResampledFit(seg)
    r = mtc(wrapped, cube)
    assert 0.5 < r.score < 0.99
    # each prediction drew its own sample: seeds 0..8, a quarter of the foreground (the Otsu count)
    cap = wrapped.sample_size(cube)
    assert seg.calls[-9:] == [(k, cap) for k in range(9)] and 0.2 * n_fg < cap < 0.3 * n_fg
    stable = ResampledFit(MedianSplit(fixed=True))
    assert mtc(stable, cube).score == 1.0
    with pytest.raises(AnalysisInputError, match="sample_size"):
        ResampledFit(lambda c: c[0] > 0)
    with pytest.raises(AnalysisInputError, match="fraction"):
        ResampledFit(seg, fraction=0.0)


def test_resampled_spectral_segmenter_is_stable_on_a_clear_scene() -> None:
    from m2s2hil.analysis.metrics.mtc import ResampledFit
    from m2s2hil.analysis.segmenters.spectral import SpectralSegmenter
    from m2s2hil.analysis.study.synthetic import synthetic_scene

    cube, _ = synthetic_scene((48, 48), n_materials=3, noise=0.005, seed=1)
    r = mtc(ResampledFit(SpectralSegmenter(max_materials=5)), cube, k=4, align=True)
    assert r.score > 0.95


def test_the_clipping_mask_moves_with_each_shift() -> None:
    """A predictor that labels by the mask alone is stable only if the mask is shifted with the
    cube: it belongs to the pixels."""
    cube = np.zeros((2, 12, 12))
    mask = np.zeros((12, 12), bool)
    mask[3:7, 2:9] = True
    seen = []

    def by_mask(x: np.ndarray, *, saturated: np.ndarray) -> np.ndarray:
        seen.append(saturated.copy())
        return saturated.astype(np.int64)

    r = mtc(by_mask, cube, shifts=[(2, 1), (-3, 0)], saturated=mask)
    assert r.score == 1.0
    np.testing.assert_array_equal(seen[1], translate(mask, 2, 1))
    np.testing.assert_array_equal(seen[2], translate(mask, -3, 0))
    fixed = mtc(lambda x: mask.astype(np.int64), cube, shifts=[(2, 1)])  # a mask left in place
    assert fixed.score < 0.75
    with pytest.raises(AnalysisInputError, match="saturated"):
        mtc(by_mask, cube, saturated=mask[:5])
