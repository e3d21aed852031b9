"""Evaluation of segmentations, following the M2S2 paper (sections 2.4, 3).

Conventions (details in each module and in docs/analysis.md):
cubes are float ``(bands, H, W)``; label maps are int ``(H, W)`` with 0 = background;
band numbers are 0-based in the API and 1-based in reports.

Parts, each a subpackage, imports pointing down this list (pyproject ``[tool.importlinter]``):

- ``study``: simulated sessions, the capture-stability study, simulated and synthetic scenes.
- ``report``: the evaluation's report folder and charts; a session's HTML QC report.
- ``evaluation``: jobs, loading, options, the Dask driver, Table 2. ``qc`` (capture-time
  QC, a module) sits beside it.
- ``metrics``: precision, recall, Dice, micro-IoU (``scores``); mTC; the paired t-test.
- ``segmenters``: the ``Segmenter`` protocol and registry; ``spectral`` (default), ``sam``
  (optional extra), ``compositing`` (SAM mask→map steps, label-map fusion), ``rgb``.
- shared leaves: ``bands`` (PCA band selection, the paper's bands), ``matching`` (oracle
  Hungarian matching of cluster ids to classes), ``cie1931``, ``arrays``, ``errors``.

The names below load lazily (on first use), so importing one part, e.g. ``analysis.qc``,
does not import every other part and its libraries.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

_EXPORTS = {
    "BandSelection": "m2s2hil.analysis.bands",
    "select_bands_pca": "m2s2hil.analysis.bands",
    "binary_fusion": "m2s2hil.analysis.segmenters.compositing",
    "composite_masks": "m2s2hil.analysis.segmenters.compositing",
    "deduplicate_masks": "m2s2hil.analysis.segmenters.compositing",
    "majority_vote": "m2s2hil.analysis.segmenters.compositing",
    "top_k_masks": "m2s2hil.analysis.segmenters.compositing",
    "AnalysisError": "m2s2hil.analysis.errors",
    "AnalysisInputError": "m2s2hil.analysis.errors",
    "SegmenterUnavailableError": "m2s2hil.analysis.errors",
    "UnknownSegmenterError": "m2s2hil.analysis.errors",
    "ClusterMatch": "m2s2hil.analysis.matching",
    "match_clusters": "m2s2hil.analysis.matching",
    "SegmentationScores": "m2s2hil.analysis.metrics.scores",
    "micro_iou": "m2s2hil.analysis.metrics.scores",
    "score_clusters": "m2s2hil.analysis.metrics.scores",
    "segmentation_scores": "m2s2hil.analysis.metrics.scores",
    "MTCResult": "m2s2hil.analysis.metrics.mtc",
    "band_fused_predictor": "m2s2hil.analysis.metrics.mtc",
    "draw_shifts": "m2s2hil.analysis.metrics.mtc",
    "mtc": "m2s2hil.analysis.metrics.mtc",
    "RgbBaseline": "m2s2hil.analysis.segmenters.rgb",
    "band_colours": "m2s2hil.analysis.segmenters.rgb",
    "camera_rgb": "m2s2hil.analysis.segmenters.rgb",
    "camera_weights": "m2s2hil.analysis.segmenters.rgb",
    "render_rgb": "m2s2hil.analysis.segmenters.rgb",
    "wavelength_to_rgb": "m2s2hil.analysis.segmenters.rgb",
    "Segmenter": "m2s2hil.analysis.segmenters.registry",
    "create_segmenter": "m2s2hil.analysis.segmenters.registry",
    "register_segmenter": "m2s2hil.analysis.segmenters.registry",
    "run_segmenter": "m2s2hil.analysis.segmenters.registry",
    "segmenter_names": "m2s2hil.analysis.segmenters.registry",
    "PairedTest": "m2s2hil.analysis.metrics.significance",
    "format_sensitivity": "m2s2hil.analysis.metrics.significance",
    "paired_t_test": "m2s2hil.analysis.metrics.significance",
    "rho_sensitivity": "m2s2hil.analysis.metrics.significance",
    "SpectralSegmentation": "m2s2hil.analysis.segmenters.spectral",
    "SpectralSegmenter": "m2s2hil.analysis.segmenters.spectral",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'm2s2hil.analysis' has no attribute {name!r}")
