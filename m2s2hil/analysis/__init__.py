"""Evaluation of segmentations, following the M2S2 paper (sections 2.4, 3).

Conventions (details in each module and in docs/analysis.md):
cubes are float ``(bands, H, W)``; label maps are int ``(H, W)`` with 0 = background;
band numbers are 0-based in the API and 1-based in reports.

- ``metrics``: per-class / macro precision, recall, Dice; micro-IoU.
- ``matching``: oracle Hungarian matching of cluster ids to ground-truth classes.
- ``significance``: paired t-test with an assumed correlation ρ and a ρ sweep.
- ``mtc``: ground-truth-free consistency under K random integer translations.
- ``bands``: PCA band selection.
- ``rgb``: wavelength→RGB (Bruton, γ = 0.8) and the RGB baseline.
- ``segment``: the ``Segmenter`` protocol and registry; ``spectral`` (default) and
  ``sam`` (optional extra) implement it; ``compositing`` holds the SAM mask→map steps.
- ``synthetic``: small scenes with known ground truth.
"""

from m2s2hil.analysis.bands import BandSelection, select_bands_pca
from m2s2hil.analysis.compositing import (
    binary_fusion,
    composite_masks,
    deduplicate_masks,
    majority_vote,
    top_k_masks,
)
from m2s2hil.analysis.errors import (
    AnalysisError,
    AnalysisInputError,
    SegmenterUnavailableError,
    UnknownSegmenterError,
)
from m2s2hil.analysis.matching import ClusterMatch, match_clusters
from m2s2hil.analysis.metrics import SegmentationScores, micro_iou, score_clusters, segmentation_scores
from m2s2hil.analysis.mtc import MTCResult, band_fused_predictor, draw_shifts, mtc
from m2s2hil.analysis.rgb import (
    RgbBaseline,
    band_colours,
    camera_rgb,
    camera_weights,
    render_rgb,
    wavelength_to_rgb,
)
from m2s2hil.analysis.segment import (
    Segmenter,
    create_segmenter,
    register_segmenter,
    run_segmenter,
    segmenter_names,
)
from m2s2hil.analysis.significance import PairedTest, format_sensitivity, paired_t_test, rho_sensitivity
from m2s2hil.analysis.spectral import SpectralSegmentation, SpectralSegmenter

__all__ = [
    "AnalysisError",
    "AnalysisInputError",
    "BandSelection",
    "ClusterMatch",
    "MTCResult",
    "PairedTest",
    "RgbBaseline",
    "SegmentationScores",
    "Segmenter",
    "SegmenterUnavailableError",
    "SpectralSegmentation",
    "SpectralSegmenter",
    "UnknownSegmenterError",
    "band_colours",
    "band_fused_predictor",
    "binary_fusion",
    "camera_rgb",
    "camera_weights",
    "composite_masks",
    "create_segmenter",
    "deduplicate_masks",
    "draw_shifts",
    "format_sensitivity",
    "majority_vote",
    "match_clusters",
    "micro_iou",
    "mtc",
    "paired_t_test",
    "register_segmenter",
    "render_rgb",
    "rho_sensitivity",
    "run_segmenter",
    "score_clusters",
    "segmentation_scores",
    "segmenter_names",
    "select_bands_pca",
    "top_k_masks",
    "wavelength_to_rgb",
]
