"""The paper's Segment Anything baseline (2.4.1), as an optional extra.

Needs ``pip install 'm2s2hil[sam]'`` (segment-anything + torch) and a checkpoint file
the user supplies (e.g. ``sam_vit_h_4b8939.pth``; weights cannot be downloaded on the
rig machines). Both are checked when the segmenter is built, the package is imported
only at the first image. ``model_type`` is ``"auto"`` (the default: the architecture is read off
the checkpoint's tensors, ``sam_model.architecture_of``), names one (``vit_h``, the paper's;
``vit_l``; ``vit_b``) or is a ``sam_model.SamArchitecture``; the weights are loaded strictly
by ``sam_model.build_sam_model`` (``tests/test_sam_tiny.py`` runs the whole path on a tiny
randomly initialised model saved as a checkpoint). ``device="cuda"`` runs the model on a GPU.
Alternatively pass ``mask_generator``: any callable taking an ``(H, W, 3)`` uint8 image and
returning SAM-style mask records — that is how the compositing is tested without torch.

Pipeline per cube (``mode="bands"``, the multispectral variant):

1. for each selected band (1-based; paper: PCA-picked 5, 9, 10): scale the band to
   uint8 between its 0.5th and 99.5th percentiles, replicate to 3 channels, generate
   masks;
2. de-duplicate at IoU ≥ ``dedup_iou`` (0.9) and, if ``top_k`` is set (the paper's mTC
   runs use k = number of classes), keep the k best masks;
3. composite small-to-large into a label map (``compositing.composite_masks``) with an
   Otsu background prior on that band (the complement of
   ``spectral.foreground_mask``: Otsu on log intensity);
4. fuse the band maps: majority vote after label alignment, or ``binary=True`` for the
   foreground/background fusion of the paper's HIL mTC runs.

``mode="image"`` runs steps 2–3 once on a 3-channel cube taken as an RGB image (all
three channels scaled by the same percentiles, keeping colour ratios): the RGB baseline.
"""

from __future__ import annotations

import copy
import importlib.util
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np

from m2s2hil.analysis.arrays import as_cube
from m2s2hil.analysis.bands import PAPER_BANDS
from m2s2hil.analysis.errors import AnalysisInputError, SegmenterUnavailableError
from m2s2hil.analysis.segmenters.compositing import (
    MaskRecord,
    binary_fusion,
    composite_masks,
    deduplicate_masks,
    majority_vote,
    top_k_masks,
)
from m2s2hil.analysis.segmenters.sam_model import SAM_ARCHITECTURES, SamArchitecture, build_sam_model
from m2s2hil.analysis.segmenters.spectral import foreground_mask
from m2s2hil.analysis.segmenters.torchvision_shim import ensure_torchvision

MaskGenerator = Callable[[np.ndarray], Sequence[MaskRecord]]
INSTALL_HINT = "install the extra with `pip install 'm2s2hil[sam]'` (segment-anything and torch)"


def to_uint8(image: np.ndarray, low: float = 0.5, high: float = 99.5) -> np.ndarray:
    """Scale an ``(H, W)`` or ``(C, H, W)`` array to uint8 ``(H, W, 3)`` between two percentiles."""
    arr = np.asarray(image, dtype=np.float32)
    lo, hi = np.percentile(arr, [low, high])
    span = float(hi - lo) if hi > lo else 1.0
    scaled = np.clip((arr - lo) / span * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if scaled.ndim == 2:
        return np.repeat(scaled[:, :, None], 3, axis=2)
    return np.ascontiguousarray(np.moveaxis(scaled, 0, -1))


def _otsu_background(image: np.ndarray) -> np.ndarray | None:
    """Background prior: the complement of the segmenter's Otsu (log-energy) foreground."""
    if float(image.max()) == float(image.min()):
        return None
    return ~foreground_mask(image[np.newaxis])[0]


class SamSegmenter:
    """SAM automatic masks → semantic map per band → fused map (see module docstring)."""

    name = "sam"

    def __init__(
        self,
        checkpoint: str | Path | None = None,
        *,
        model_type: str | SamArchitecture = "auto",
        device: str = "cpu",
        mode: Literal["bands", "image"] = "bands",
        bands: Sequence[int] = PAPER_BANDS,
        binary: bool = False,
        top_k: int | None = None,
        dedup_iou: float = 0.9,
        min_coverage: float = 0.2,
        min_pixels: int = 10,
        background_prior: bool = True,
        generator_options: dict[str, Any] | None = None,
        mask_generator: MaskGenerator | None = None,
    ) -> None:
        if mode not in ("bands", "image"):
            raise AnalysisInputError("mode", f"expected 'bands' or 'image', got {mode!r}")
        self.bands = tuple(int(b) for b in bands)
        if mode == "bands" and (not self.bands or min(self.bands) < 1):
            raise AnalysisInputError("bands", f"expected 1-based band numbers, got {bands!r}")
        if top_k is not None and top_k < 1:
            raise AnalysisInputError("top_k", f"must be ≥ 1 or None, got {top_k}")
        self.mode = mode
        self.binary = bool(binary)
        self.top_k = top_k
        self.dedup_iou = float(dedup_iou)
        self.min_coverage = float(min_coverage)
        self.min_pixels = int(min_pixels)
        self.background_prior = bool(background_prior)
        self.name = "sam" if mode == "bands" else "sam-image"
        # The paper: "a high IoU/stability threshold" (values are SAM's own names).
        self.generator_options = {"pred_iou_thresh": 0.88, "stability_score_thresh": 0.95,
                                  **(generator_options or {})}
        self._generator: MaskGenerator | None = mask_generator
        self._model: Any = None  # the loaded segment_anything Sam (None until the first image)
        self.checkpoint: Path | None = None
        # None until the checkpoint is read when "auto"
        self.architecture: SamArchitecture | None
        if isinstance(model_type, SamArchitecture):
            self.architecture = model_type
        elif model_type in SAM_ARCHITECTURES:
            self.architecture = SAM_ARCHITECTURES[model_type]
        elif model_type == "auto":
            self.architecture = None
        else:
            raise AnalysisInputError("model_type", f"unknown SAM model {model_type!r}; known: auto, "
                                     f"{', '.join(sorted(SAM_ARCHITECTURES))} or a SamArchitecture")
        self.model_type = "auto" if self.architecture is None else self.architecture.name
        self.device = device
        if mask_generator is None:
            if checkpoint is None:
                raise SegmenterUnavailableError("sam", "no checkpoint: pass checkpoint=PATH to SAM weights")
            self.checkpoint = Path(checkpoint)
            if not self.checkpoint.is_file():
                raise SegmenterUnavailableError("sam", f"checkpoint {self.checkpoint} does not exist")
            if importlib.util.find_spec("segment_anything") is None:
                raise SegmenterUnavailableError("sam", f"package segment_anything not found; {INSTALL_HINT}")

    def paper_mtc(self, *, top_k: int | None, bands: Sequence[int] | None = None) -> SamSegmenter:
        """A copy in the paper's mTC setting: binary fusion, top-k = ``top_k`` masks per band
        (the number of classes) after de-duplication, over ``bands`` (1-based; default: this one's).
        The copy shares the loaded model."""
        if top_k is not None and top_k < 1:
            raise AnalysisInputError("top_k", f"must be ≥ 1 or None, got {top_k}")
        twin = copy.copy(self)
        twin.binary = True
        twin.top_k = top_k
        if bands is not None:
            chosen = tuple(int(b) for b in bands)
            if not chosen or min(chosen) < 1:
                raise AnalysisInputError("bands", f"expected 1-based band numbers, got {bands!r}")
            twin.bands = chosen
        twin._generator = self._load()  # one model in memory, not two
        return twin

    def _load(self) -> MaskGenerator:
        if self._generator is None:
            try:
                ensure_torchvision()  # segment_anything imports it; the CPU wheel has no matching one
                from segment_anything import SamAutomaticMaskGenerator
            except ImportError as exc:  # e.g. torch missing behind an installed segment_anything
                raise SegmenterUnavailableError("sam", f"{exc}; {INSTALL_HINT}") from exc
            assert self.checkpoint is not None  # checked at construction
            self._model, self.architecture = build_sam_model(self.architecture, self.checkpoint, self.device)
            try:
                self._generator = SamAutomaticMaskGenerator(self._model, **self.generator_options).generate
            except TypeError as exc:  # a misspelt generator option
                raise AnalysisInputError("generator_options", str(exc)) from exc
        return self._generator

    def label_image(self, image: np.ndarray, background: np.ndarray | None) -> np.ndarray:
        """One uint8 ``(H, W, 3)`` image → semantic map (dedup, top-k, compositing)."""
        masks = list(self._load()(image))
        masks = deduplicate_masks(masks, self.dedup_iou)
        if self.top_k is not None:
            masks = top_k_masks(masks, self.top_k)
        return composite_masks(masks, image.shape[:2], background=background,
                               min_coverage=self.min_coverage, min_pixels=self.min_pixels)

    def segment(self, cube: np.ndarray) -> np.ndarray:
        arr = as_cube(cube)
        if self.mode == "image":
            if arr.shape[0] != 3:
                raise AnalysisInputError("cube", f"mode='image' needs a 3-channel cube, got {arr.shape[0]}")
            bg = _otsu_background(arr.sum(axis=0)) if self.background_prior else None
            return self.label_image(to_uint8(arr), bg)
        if max(self.bands) > arr.shape[0]:
            raise AnalysisInputError("cube", f"has {arr.shape[0]} bands, band {max(self.bands)} was selected")
        maps = []
        for b in self.bands:
            band = arr[b - 1]
            bg = _otsu_background(band) if self.background_prior else None
            maps.append(self.label_image(to_uint8(band), bg))
        return binary_fusion(maps).astype(np.int32) if self.binary else majority_vote(maps).astype(np.int32)
