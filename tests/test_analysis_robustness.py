"""Issue 23 item 1: the spectral segmenter holds its count of materials under low exposure and
clipping (``segmenters.normalise``: clipped bands and near-black pixels kept out of the fit).
Each test also runs the old behaviour (``robust=False``) where it failed, so it can fail."""

from __future__ import annotations

import numpy as np
import pytest
from sim_frame import one_frame

from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.segmenters.normalise import (
    PLATEAU_REL_TOL,
    clipped_bands,
    guided_denoise,
    neighbour_angle_deg,
    normalise_cube,
    pool_size,
    reliability,
    superpixel_means,
)
from m2s2hil.analysis.segmenters.spectral import SpectralSegmenter, foreground_mask
from m2s2hil.analysis.study.simframes import visible_materials
from m2s2hil.analysis.study.synthetic import exposed_scene


def n_segments(cube: np.ndarray, **options: object) -> int:
    return SpectralSegmenter(**options).analyse(cube).n_materials  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def dim_single_material():
    # Voyager B1 (silver only), weak light, exposed to 4 % of full scale, 64² cube
    return one_frame("voyager", "B1", size=256, peak_fraction=0.04)


def test_single_material_build_at_4_percent_peak_is_one_segment(dim_single_material):
    f = dim_single_material
    assert visible_materials(f.gt) == 1 and float(f.cube.max()) < 0.1 * 1023
    assert n_segments(f.cube) == 1
    assert n_segments(f.cube, robust=False) > 1  # the old behaviour split it


def test_k_at_10_and_150_percent_matches_k_at_60(n_materials: int = 4):
    cubes = {p: exposed_scene(p, (48, 48), n_materials)[0] for p in (0.1, 0.6, 1.5)}
    k = {p: n_segments(c) for p, c in cubes.items()}
    assert k[0.6] == n_materials
    assert k[0.1] == k[0.6] and k[1.5] == k[0.6]
    assert n_segments(cubes[1.5], robust=False) != n_materials  # clipping split materials before


def test_clipped_pixels_are_masked_and_labelled():
    cube, _ = exposed_scene(1.5, (64, 64), 3)
    fg, _ = foreground_mask(cube, "backdrop")
    truth = cube >= 1000.0  # exposed_scene clips at full scale 1000
    found = clipped_bands(cube, fg)
    # every clipped value is found; nothing more than the plateau's tolerance below full scale
    assert truth[:, fg].any() and np.all(found[truth & fg[None]])
    assert np.all(cube[found] >= 1000.0 * (1 - PLATEAU_REL_TOL))
    result = SpectralSegmenter().analyse(cube)
    assert result.unreliable is not None and result.fit is not None
    used = list(result.bands)
    sat = truth[used].any(axis=0) & fg
    assert sat.any() and np.all(result.unreliable[sat]) and not np.any(result.fit[sat])
    assert np.all(result.labels[sat] > 0)  # masked out of the fit, still labelled
    # a natural (unclipped) cube has no plateau, and neither has a dim, quantised one
    for peak in (0.6, 0.04):
        c, _ = exposed_scene(peak, (64, 64), 3)
        assert not clipped_bands(np.round(c * 2) / 2, fg).any()


def test_near_black_pixels_are_unreliable_and_a_given_mask_is_used():
    cube, _ = exposed_scene(0.6, (64, 64), 3)
    cube[:, 30:34, 10:20] *= 0.002  # a deep shadow inside the object
    fg, _ = foreground_mask(cube, "backdrop")
    rel = reliability(cube, fg)
    shadow = np.zeros(fg.shape, dtype=bool)
    shadow[30:34, 10:20] = True
    assert np.all(rel.dark[shadow & fg]) and rel.dark[fg & ~shadow].mean() < 0.01
    given = np.zeros(fg.shape, dtype=bool)
    given[20:24, 40:44] = True
    assert np.all(reliability(cube, fg, saturated=given).saturated[given & fg])
    with pytest.raises(AnalysisInputError):
        reliability(cube, fg, saturated=np.zeros((3, 3), dtype=bool))


def test_white_reference_and_exposure_normalisation():
    cube, _ = exposed_scene(0.6, (32, 32), 2)
    white = np.linspace(0.5, 1.0, cube.shape[0])
    out = normalise_cube(cube, white=white, exposure_s=0.01, gain=2.0)
    np.testing.assert_allclose(out[:, 5, 5], cube[:, 5, 5] / white / 0.02, rtol=1e-6)
    with pytest.raises(AnalysisInputError):
        normalise_cube(cube, white=np.zeros(cube.shape[0]))
    with pytest.raises(AnalysisInputError):
        normalise_cube(cube, white=np.ones(3))
    with pytest.raises(AnalysisInputError):
        SpectralSegmenter(snr_min=-1)


def test_pool_size_follows_the_measured_noise():
    assert pool_size(8.0, 2.0) == 16 and pool_size(1.5, 2.0) == 1 and pool_size(float("nan"), 2.0) == 1
    cube = np.arange(2 * 2 * 3, dtype=np.float64).reshape(2, 2, 3)
    seg = np.array([[0, 1, 1], [2, 2, 1]])
    means = superpixel_means(cube, seg)
    np.testing.assert_allclose(means[1], [(1 + 2 + 5) / 3, (7 + 8 + 11) / 3])
    np.testing.assert_allclose(means[2], [(3 + 4) / 2, (9 + 10) / 2])


def test_dim_cube_is_denoised_and_the_reference_is_not():
    dim, _ = exposed_scene(0.02, (96, 96), 3)
    for denoise in ("guided", "slic"):
        result = SpectralSegmenter(denoise=denoise).analyse(dim)
        assert result.pooled > 1 and result.n_materials == 3, denoise
    assert SpectralSegmenter(pool_target_deg=0).analyse(dim).pooled == 1
    bright, _ = exposed_scene(0.6, (96, 96), 3)
    assert SpectralSegmenter().analyse(bright).pooled == 1  # noise below the target: per pixel
    with pytest.raises(AnalysisInputError):
        SpectralSegmenter(denoise="median")  # type: ignore[arg-type]
    with pytest.raises(AnalysisInputError):
        SpectralSegmenter(fit_stride=-1)


def unit_of(cube: np.ndarray) -> np.ndarray:
    return cube / np.maximum(np.linalg.norm(cube, axis=0, keepdims=True), 1e-12)


def test_guided_filter_averages_the_noise_and_keeps_the_edge():
    # two materials of different shape, side by side, at a low signal: flat halves, one straight edge
    rng = np.random.default_rng(3)
    a, b = np.linspace(1.0, 2.0, 10), np.linspace(2.0, 1.0, 10)
    clean = np.empty((10, 48, 48))
    clean[:, :, :24] = 20.0 * a[:, None, None]
    clean[:, :, 24:] = 20.0 * b[:, None, None]
    noisy = clean + rng.normal(0.0, 2.0, clean.shape)
    fg = np.ones((48, 48), dtype=bool)
    out, radius = guided_denoise(noisy, fg, per=9)
    assert radius == 1
    inside = fg.copy()
    inside[:, 20:28] = False  # away from the edge
    before = neighbour_angle_deg(unit_of(noisy), inside)
    after = neighbour_angle_deg(unit_of(out), inside)
    assert after < 0.5 * before  # a 3×3 box: the noise falls by about 3
    # next to the edge each side keeps its own spectrum (a box filter would mix them half and half)
    for col, ref in ((23, a), (24, b)):
        cos = unit_of(out)[:, :, col].T @ (ref / np.linalg.norm(ref))
        assert np.degrees(np.arccos(np.clip(np.median(cos), -1, 1))) < 3.0


def test_noise_foreground_finds_a_shadowed_face_the_log_rule_misses():
    # a dark backdrop at the noise floor (rectified, as after dark subtraction), a lit face and a
    # face in the spotlight's shadow at about four noise SDs of energy
    rng = np.random.default_rng(5)
    cube = np.clip(rng.normal(0.0, 1.0, (10, 64, 64)), 0.0, None)
    cube[:, 10:30, 10:50] += 60.0
    cube[:, 34:54, 10:50] += 4.0
    shadow = np.zeros((64, 64), dtype=bool)
    shadow[34:54, 10:50] = True
    log_rule, _ = foreground_mask(cube, "backdrop")
    noise_rule, _ = foreground_mask(cube, "noise")
    assert log_rule[shadow].mean() < 0.5  # the old rule hands most of the shadow to the backdrop
    assert noise_rule[shadow].mean() > 0.95
    backdrop = np.ones((64, 64), dtype=bool)
    backdrop[8:56, 8:52] = False
    assert noise_rule[backdrop].mean() < 0.01


def test_clipped_bands_stay_with_a_per_pixel_mask():
    cube, _ = exposed_scene(1.5, (64, 64), 3)
    fg, _ = foreground_mask(cube, "backdrop")
    rel = reliability(cube, fg)
    assert rel.saturated.any() and list(rel.bands) == list(range(cube.shape[0]))
    # a band clipped on (nearly) the whole object leaves too little unclipped: it goes
    flat = cube.copy()
    flat[0][fg] = 1000.0
    gone = reliability(flat, fg)
    assert 0 not in gone.bands and len(gone.bands) == cube.shape[0] - 1
    with pytest.raises(AnalysisInputError):
        SpectralSegmenter(merge_noise=-1)
    with pytest.raises(AnalysisInputError):
        SpectralSegmenter(pool_target_deg=-1)


def test_a_group_without_an_interior_is_not_a_material():
    from m2s2hil.analysis.segmenters.spectral import cored_groups

    fg = np.zeros((40, 40), dtype=bool)
    fg[2:38, 2:38] = True
    plane = np.zeros((40, 40), np.int64)
    plane[2:38, 20] = 1  # a one-pixel seam: blends along a boundary
    plane[5:10, 5:10] = 2  # a 5 × 5 part: 9 interior pixels
    comp = plane[fg]
    assert cored_groups(comp, fg, 3, 5).tolist() == [True, False, True]
    assert cored_groups(comp, fg, 3, 10).tolist() == [True, False, False]
    # nothing with an interior: the group with the largest one stays, so the object keeps a label
    assert cored_groups(np.where(comp == 0, 1, comp), fg, 3, 10_000).tolist() == [False, True, False]


def test_the_interior_test_is_wired_and_checked():
    cube = np.zeros((10, 48, 48))
    cube[:, 8:40, 8:24] = 100.0 * np.linspace(1.0, 2.0, 10)[:, None, None]
    cube[:, 8:40, 24:40] = 100.0 * np.linspace(2.0, 1.0, 10)[:, None, None]
    cube += np.random.default_rng(0).normal(0.0, 1.0, cube.shape)
    assert n_segments(cube) == 2
    assert n_segments(cube, min_core_fraction=0.6) == 1  # neither half has 60 % of the object inside
    assert n_segments(cube, robust=False, min_core_fraction=0.6) == 2  # the issue-15 segmenter: unchanged
    with pytest.raises(AnalysisInputError, match="min_core_fraction"):
        SpectralSegmenter(min_core_fraction=1.0)
