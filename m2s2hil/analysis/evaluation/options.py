"""What an evaluation runs: ``EvalOptions`` and the segmenters it names.

Segmenter names: every registered name (``create_segmenter``) plus ``spectral-smooth`` /
``rgb-smooth`` (``smooth=True``: SLIC superpixel majority vote). Table 2 pairs the
multispectral segmenter with its RGB counterpart (``RGB_COUNTERPART``).

mTC predictors (``mtc_predictor``): ``mtc_mode="labels"`` uses the segmenter's full label
map, each shifted prediction aligned to the base one (a sampling segmenter through
``metrics.mtc.ResampledFit``: each prediction fits its own sample); ``"binary"`` is the paper's HIL
setting (bands 5, 9, 10 segmented one by one and fused as foreground/background; RGB
segmenters: their prediction's foreground). For SAM the binary predictor is the paper's exactly:
``SamSegmenter`` in binary mode over the selected bands with top-k = the image's number of
classes (``n_classes``: materials + background, as the paper counts), each band's masks
de-duplicated at IoU 0.9 before the top-k cut. ``EvalOptions.mtc_bands`` (1-based, default the
paper's 5, 9, 10) names the bands; the report states them beside the bands PCA picks on the
evaluated data.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from m2s2hil.analysis.bands import PAPER_BANDS
from m2s2hil.analysis.metrics.mtc import ResampledFit, band_fused_predictor
from m2s2hil.analysis.segmenters.registry import Segmenter, create_segmenter
from m2s2hil.analysis.segmenters.sam import SamSegmenter
from m2s2hil.errors import UsageError

MtcFor = Literal["multi", "all", "none"]
MtcMode = Literal["labels", "binary"]
RGB_COUNTERPART = {"spectral": "rgb", "spectral-smooth": "rgb-smooth", "spectral-sweep": "rgb-sweep",
                   "sam": "sam-rgb"}


@dataclass(frozen=True)
class EvalOptions:
    """What ``evaluate_job`` computes for each image."""

    multi: str = "spectral"
    rgb: str | None = None  # default: RGB_COUNTERPART[multi]
    extra: tuple[str, ...] = ()  # more segmenters (speed/accuracy chart, per-image CSV)
    segmenter_options: dict[str, Any] = field(default_factory=dict)
    mtc_for: MtcFor = "multi"
    mtc_mode: MtcMode = "labels"
    reprocess: str | None = None  # demosaicing method: recompute cubes from the raw
    rho: float = 0.9
    mtc_bands: tuple[int, ...] = PAPER_BANDS  # 1-based bands of the binary mTC predictor
    clip_masks: bool = True  # give segmenters each frame's clipping mask (segmenters.masks)
    bracket: bool = True  # merge a bracketed pose's exposures into its image (loading.load_frame)

    def __post_init__(self) -> None:
        if self.mtc_for not in ("multi", "all", "none"):
            raise UsageError(f"mtc must be one of multi, all, none; got {self.mtc_for!r}")
        if self.mtc_mode not in ("labels", "binary"):
            raise UsageError(f"mtc mode must be 'labels' or 'binary', got {self.mtc_mode!r}")
        if self.multi.startswith(("rgb", "sam-rgb")):
            raise UsageError(
                f"{self.multi!r} is an RGB baseline: choose the multispectral segmenter "
                f"({', '.join(RGB_COUNTERPART)}); its RGB counterpart is evaluated with it"
            )
        if is_pose(self.multi):
            raise UsageError(
                f"{self.multi!r} labels each frame from its pose under diffuse light and has no RGB "
                "counterpart for Table 2: evaluate it beside the multispectral segmenter (--also "
                f"{self.multi})"
            )
        if not -1.0 <= self.rho <= 1.0:
            raise UsageError(f"rho must lie in [-1, 1], got {self.rho}")
        if not self.mtc_bands or min(self.mtc_bands) < 1:
            raise UsageError(f"mtc bands are 1-based band numbers, got {self.mtc_bands!r}")

    @property
    def rgb_name(self) -> str:
        return self.rgb or RGB_COUNTERPART.get(self.multi, "rgb")

    @property
    def segmenters(self) -> tuple[str, ...]:
        names = [self.multi, self.rgb_name, *self.extra]
        return tuple(dict.fromkeys(names))


def make_segmenter(
    name: str, options: Mapping[str, Any] | None = None, *, bands_nm: Sequence[float] | None = None
) -> Segmenter:
    """A segmenter by name (see module docstring); ``bands_nm`` feeds the RGB rendering."""
    opts = dict(options or {})
    if not is_pose(name):  # the pose segmenter's own options (``segmenters.pose``)
        opts = {k: v for k, v in opts.items() if not k.startswith("pose_")}
    base = name
    if name.endswith("-smooth"):
        base = name[: -len("-smooth")]
        opts["smooth"] = True
    if base in ("rgb", "rgb-nir", "sam-rgb") and bands_nm is not None:
        opts.setdefault("bands_nm", tuple(float(b) for b in bands_nm))
    if base in ("sam", "sam-rgb"):
        opts = {k: v for k, v in opts.items() if k not in ("smooth",)}
    elif "checkpoint" in opts:
        opts.pop("checkpoint")
    seg = create_segmenter(base, **opts)
    if base != name:
        seg.name = name  # type: ignore[misc]
    return seg


def check_segmenters(options: EvalOptions) -> None:
    """Build every segmenter once here, so a missing model fails before any work is sent."""
    for name in options.segmenters:
        make_segmenter(name, options.segmenter_options)


# Per-thread cache, like the frame processors in ``loading``: worker threads of a threaded
# cluster must not share a segmenter.
_LOCAL = threading.local()


def cached_segmenter(name: str, options: EvalOptions, bands_nm: Sequence[float]) -> Segmenter:
    """``make_segmenter`` once per (name, segmenter options, bands) and worker thread."""
    key = (name, json.dumps(options.segmenter_options, sort_keys=True, default=str), tuple(bands_nm))
    segs: dict[tuple, Segmenter] | None = getattr(_LOCAL, "segmenters", None)
    if segs is None:
        segs = _LOCAL.segmenters = {}
    seg = segs.get(key)
    if seg is None:
        seg = segs[key] = make_segmenter(name, options.segmenter_options, bands_nm=bands_nm)
    return seg


def is_sweep(name: str) -> bool:
    """A segmenter fitted once on each sweep's frames (``segmenters.sweep``) before any is labelled."""
    return name.endswith("-sweep")


def is_pose(name: str) -> bool:
    """A segmenter that labels a frame from its pose's diffuse frame (``segmenters.pose``)."""
    return name == "spectral-pose"


#: the sweep segmenter that labels each pose's reference for ``spectral-pose`` (evaluation.poses)
POSE_REFERENCE_SEGMENTER = "spectral-sweep"


def is_rgb(name: str) -> bool:
    return name.startswith(("rgb", "sam-rgb"))


def mtc_predictor(
    seg: Segmenter,
    name: str,
    mode: MtcMode,
    n_bands: int,
    *,
    n_classes: int | None = None,
    bands: Sequence[int] = PAPER_BANDS,
) -> tuple[Callable, bool]:
    """(predictor, align) for ``analysis.metrics.mtc`` (see the module docstring)."""
    if mode == "labels":
        # A sampling segmenter (SpectralSegmenter) fits a new sample per shift; otherwise a shift
        # refits the same pixels and mTC only tests order invariance (metrics.mtc, issue 23).
        if hasattr(seg, "sample_size") and hasattr(seg, "seed"):
            return ResampledFit(seg), True
        return seg.segment, True
    if is_rgb(name) or n_bands < max(bands):
        return (lambda c: (seg.segment(c) > 0).astype(np.int64)), False
    if isinstance(seg, SamSegmenter) and seg.mode == "bands":
        # SAM takes the whole cube and segments the selected bands itself (it refuses one-band cubes).
        return seg.paper_mtc(top_k=n_classes, bands=bands).segment, False
    return band_fused_predictor(seg.segment, bands, binary=True), False
