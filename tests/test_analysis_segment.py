"""Segmenters behind one interface: registry, the spectral default, the SAM pipeline with a fake generator."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from m2s2hil.analysis.errors import AnalysisInputError, SegmenterUnavailableError, UnknownSegmenterError
from m2s2hil.analysis.matching import match_clusters
from m2s2hil.analysis.metrics.scores import segmentation_scores
from m2s2hil.analysis.segmenters.registry import (
    Segmenter,
    create_segmenter,
    register_segmenter,
    run_segmenter,
    segmenter_names,
)
from m2s2hil.analysis.segmenters.rgb import RgbBaseline
from m2s2hil.analysis.segmenters.sam import SamSegmenter, to_uint8
from m2s2hil.analysis.segmenters.spectral import SpectralSegmenter
from m2s2hil.analysis.study.synthetic import synthetic_scene


def matched_scores(gt: np.ndarray, labels: np.ndarray):
    return segmentation_scores(gt, match_clusters(gt, labels).relabelled)


# --- spectral ------------------------------------------------------------------------------------


def test_spectral_recovers_three_materials() -> None:
    cube, gt = synthetic_scene((48, 48), 3, seed=0)
    result = SpectralSegmenter(seed=0).analyse(cube)
    assert result.n_materials == 3
    assert set(np.unique(result.labels)) == {0, 1, 2, 3}
    s = matched_scores(gt, result.labels)
    assert s.macro_dice > 0.98 and s.macro_recall > 0.98
    sizes = np.bincount(result.labels.ravel())[1:]
    assert list(sizes) == sorted(sizes, reverse=True)  # ids ordered by pixel count
    assert np.isfinite(result.threshold) and min(result.bic, key=result.bic.get) >= 3


def test_spectral_ignores_brightness_and_is_deterministic() -> None:
    cube, gt = synthetic_scene((40, 40), 3, seed=4)
    half = cube.copy()
    half[:, :, :20] *= 0.5  # one half in shadow: same materials, darker
    a = SpectralSegmenter(seed=1).segment(half)
    assert matched_scores(gt, a).macro_dice > 0.97
    np.testing.assert_array_equal(a, SpectralSegmenter(seed=1).segment(half))


def test_spectral_with_superpixel_smoothing() -> None:
    cube, gt = synthetic_scene((48, 48), 3, noise=0.03, seed=1)
    labels = SpectralSegmenter(smooth=True, n_superpixels=150).segment(cube)
    assert matched_scores(gt, labels).macro_dice > 0.95


def test_spectral_constant_cube_has_no_foreground() -> None:
    result = SpectralSegmenter().analyse(np.full((10, 16, 16), 0.3))
    assert result.n_materials == 0 and not result.labels.any()


def test_spectral_rejects_bad_parameters_and_cubes() -> None:
    with pytest.raises(AnalysisInputError, match="max_materials"):
        SpectralSegmenter(max_materials=0)
    with pytest.raises(AnalysisInputError, match="covariance_type"):
        SpectralSegmenter(covariance_type="round")  # type: ignore[arg-type]
    with pytest.raises(AnalysisInputError, match="cube"):
        SpectralSegmenter().segment(np.zeros((2, 3, 4, 5)))
    with pytest.raises(AnalysisInputError, match="NaN"):
        SpectralSegmenter().segment(np.full((3, 4, 4), np.nan))


# --- registry --------------------------------------------------------------------------------------


def test_registry_builds_named_segmenters() -> None:
    assert {"spectral", "rgb", "sam", "sam-rgb"} <= set(segmenter_names())
    spectral = create_segmenter("spectral", max_materials=4)
    assert isinstance(spectral, SpectralSegmenter) and spectral.max_materials == 4
    assert isinstance(spectral, Segmenter)
    rgb = create_segmenter("rgb-nir", gamma=1.0, nir="black", seed=3)
    assert isinstance(rgb, RgbBaseline) and rgb.gamma == 1.0 and rgb.segmenter.seed == 3
    assert rgb.rendering == "bruton" and rgb.name == "rgb-nir-spectral"
    cam = create_segmenter("rgb", ir_cut_nm=650.0)
    assert cam.rendering == "camera" and cam.ir_cut_nm == 650.0 and cam.name == "rgb-spectral"
    with pytest.raises(AnalysisInputError, match="Bruton"):
        create_segmenter("rgb", nir="clamp")  # the NIR variant only under its own name
    with pytest.raises(UnknownSegmenterError, match="did you mean 'spectral'"):
        create_segmenter("spectrl")
    with pytest.raises(AnalysisInputError, match="options"):
        create_segmenter("spectral", n_clusters=3)


def test_register_and_run_validates_output() -> None:
    class Halves:
        name = "test-halves"

        def segment(self, cube: np.ndarray) -> np.ndarray:
            out = np.zeros(cube.shape[1:], dtype=int)
            out[:, cube.shape[2] // 2 :] = 1
            return out

    class Wrong:
        name = "test-wrong"

        def segment(self, cube: np.ndarray) -> np.ndarray:
            return np.zeros((2, 2))

    register_segmenter("test-halves", Halves, replace=True)
    with pytest.raises(AnalysisInputError, match="already registered"):
        register_segmenter("test-halves", Halves)
    labels = run_segmenter(create_segmenter("test-halves"), np.ones((3, 4, 6)))
    assert labels.tolist() == [[0, 0, 0, 1, 1, 1]] * 4
    with pytest.raises(AnalysisInputError, match="test-wrong"):
        run_segmenter(Wrong(), np.ones((3, 4, 6)))


# --- SAM pipeline with a fake mask generator -------------------------------------------------------


class FakeMaskGenerator:
    """Stands in for SamAutomaticMaskGenerator.generate: one mask per connected region of equal
    grey level (channel 0), a lower-scored near-copy of each (to be de-duplicated), and one
    whole-image mask. Records the images it saw."""

    def __init__(self) -> None:
        self.images: list[np.ndarray] = []

    def __call__(self, image: np.ndarray) -> list[dict]:
        assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3
        self.images.append(image)
        grey = image[:, :, 0]
        masks = []
        for level in np.unique(grey):
            comps, n = ndimage.label(grey == level)
            for i in range(1, n + 1):
                seg = comps == i
                masks.append({"segmentation": seg, "area": int(seg.sum()), "predicted_iou": 0.95,
                              "stability_score": 0.97})
                masks.append({"segmentation": seg.copy(), "area": int(seg.sum()), "predicted_iou": 0.90,
                              "stability_score": 0.97})
        whole = np.ones(grey.shape, dtype=bool)
        masks.append({"segmentation": whole, "area": whole.size, "predicted_iou": 0.5,
                      "stability_score": 0.9})
        return masks


def _block_scene() -> tuple[np.ndarray, np.ndarray]:
    gt = np.zeros((24, 24), dtype=np.int32)
    gt[3:11, 3:21] = 1
    gt[13:21, 3:11] = 2
    gt[13:21, 13:21] = 3
    spectra = np.array([  # (class, band): background dark, materials distinct in bands 1-3
        [0.02, 0.02, 0.02, 0.02],
        [0.80, 0.30, 0.50, 0.60],
        [0.40, 0.90, 0.70, 0.60],
        [0.60, 0.50, 0.95, 0.60],
    ])
    return spectra[gt].transpose(2, 0, 1).astype(np.float32), gt


def test_sam_pipeline_per_band_and_fused() -> None:
    cube, gt = _block_scene()
    fake = FakeMaskGenerator()
    sam = SamSegmenter(mask_generator=fake, bands=(1, 2, 3), min_pixels=5)
    labels = sam.segment(cube)
    assert len(fake.images) == 3  # one image per selected band
    assert matched_scores(gt, labels).macro_dice == 1.0
    binary = SamSegmenter(mask_generator=FakeMaskGenerator(), bands=(1, 2, 3), binary=True).segment(cube)
    np.testing.assert_array_equal(binary, (gt > 0).astype(int))


def test_sam_top_k_keeps_the_best_instances() -> None:
    cube, gt = _block_scene()
    labels = SamSegmenter(mask_generator=FakeMaskGenerator(), bands=(2,), top_k=2, min_pixels=5).segment(cube)
    # 5 distinct masks after de-dup (4 regions + whole image); the 2 best by score (equal) then
    # by area are the background and region 1; the composite keeps region 1 only as foreground.
    assert set(np.unique(labels)) == {0, 1}
    np.testing.assert_array_equal(labels > 0, gt == 1)


def test_sam_image_mode_for_rgb() -> None:
    cube, gt = _block_scene()
    fake = FakeMaskGenerator()
    labels = SamSegmenter(mask_generator=fake, mode="image", min_pixels=5).segment(cube[:3])
    assert len(fake.images) == 1
    assert matched_scores(gt, labels).macro_dice == 1.0
    with pytest.raises(AnalysisInputError, match="3-channel"):
        SamSegmenter(mask_generator=fake, mode="image").segment(cube)


def test_to_uint8_scales_between_percentiles() -> None:
    band = np.linspace(0.0, 1.0, 201).reshape(1, 201)
    img = to_uint8(band, 0, 100)
    assert img.shape == (1, 201, 3) and img[0, 0, 0] == 0 and img[0, -1, 2] == 255
    assert img[0, 100, 1] == 128  # 0.5·255 rounded


def test_sam_without_model_raises_typed_error(tmp_path: Path) -> None:
    with pytest.raises(SegmenterUnavailableError, match="checkpoint"):
        SamSegmenter()
    with pytest.raises(SegmenterUnavailableError, match="does not exist"):
        create_segmenter("sam", checkpoint=tmp_path / "missing.pth")
    if importlib.util.find_spec("segment_anything") is None:
        ckpt = tmp_path / "sam_vit_h.pth"
        ckpt.write_bytes(b"not really weights")
        with pytest.raises(SegmenterUnavailableError, match=r"m2s2hil\[sam\]"):
            SamSegmenter(checkpoint=ckpt)


def test_spectral_single_band_is_its_foreground() -> None:
    cube, gt = synthetic_scene((32, 32), 3, seed=3)
    labels = SpectralSegmenter().segment(cube[4:5])
    assert set(np.unique(labels)) == {0, 1}
    assert ((labels > 0) == (gt > 0)).mean() > 0.99


@pytest.mark.slow  # ~5 s
def test_blas_thread_limit_does_not_change_the_result() -> None:
    cube, _ = synthetic_scene((32, 32), 3, seed=5)
    a = SpectralSegmenter(blas_threads=1).segment(cube)
    np.testing.assert_array_equal(a, SpectralSegmenter(blas_threads=None).segment(cube))
    with pytest.raises(AnalysisInputError, match="blas_threads"):
        SpectralSegmenter(blas_threads=0)
