"""The segmenter interface and the registry of named segmenters.

A segmenter is any object with a ``name`` and ``segment(cube) -> labels``:

- ``cube``: float ``(bands, H, W)`` (a 3-channel cube for RGB input);
- ``labels``: int ``(H, W)``; 0 = background, 1..n = segment/cluster ids. Ids are not
  material ids — match them to ground-truth classes with
  ``m2s2hil.analysis.matching.match_clusters`` before scoring.

A segmenter may also take the processor's clipping mask, ``segment(cube, *, saturated=mask)``
(``segmenters.masks``): the spectral and sweep ones do; SAM and the RGB baselines do not, and
are called without it.

Built-in names (``create_segmenter(name, **options)``):

========== ===============================================================
spectral   ``SpectralSegmenter`` (default): foreground + GMM on unit spectra, clipped and
           near-black pixels out of the fit (``robust=False``: without that)
rgb        ``RgbBaseline(SpectralSegmenter)``: the same on what an IR-cut RGB camera sees
           (CIE 1931 → linear sRGB, ``rgb.camera_rgb``)
rgb-nir    the same on the paper's wavelength→RGB map with the near-infrared bands
           clamped into red (``rgb.render_rgb``): not what a camera sees
spectral-sweep ``SweepSegmenter``: the spectral segmenter with one mixture fitted on a whole
           sweep (``fit(cubes)`` first; ``evaluate`` fits one per session and lighting)
rgb-sweep  ``RgbBaseline(SweepSegmenter)``: the same on camera RGB
spectral-pose ``PoseSegmenter``: a frame labelled with the materials of the same pose under
           diffuse light (``use(reference)`` first; ``evaluate`` finds each pose's reference)
sam        ``SamSegmenter``: SAM per selected band, majority-vote fusion (optional extra)
sam-rgb    ``RgbBaseline(SamSegmenter(mode="image"))``: SAM on the camera RGB image
========== ===============================================================

Options ``bands_nm`` and ``ir_cut_nm`` (camera) or ``gamma`` and ``nir`` (``rgb-nir``) go to
the RGB rendering of the ``rgb*`` segmenters; ``pose_*`` options and ``seed`` go to
``spectral-pose``, which takes no other; every other option goes to the inner segmenter's
constructor.
"""

from __future__ import annotations

import difflib
from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

import numpy as np

from m2s2hil.analysis.arrays import as_cube, as_label_map
from m2s2hil.analysis.errors import AnalysisInputError, UnknownSegmenterError
from m2s2hil.analysis.segmenters.pose import PoseSegmenter
from m2s2hil.analysis.segmenters.rgb import RgbBaseline
from m2s2hil.analysis.segmenters.sam import SamSegmenter
from m2s2hil.analysis.segmenters.spectral import SpectralSegmenter
from m2s2hil.analysis.segmenters.sweep import SweepSegmenter


@runtime_checkable
class Segmenter(Protocol):
    """``segment(cube (bands, H, W)) -> labels (H, W)``, 0 = background."""

    name: str

    def segment(self, cube: np.ndarray) -> np.ndarray: ...


Factory = Callable[..., Segmenter]
_REGISTRY: dict[str, Factory] = {}

_RGB_OPTIONS = ("bands_nm", "gamma", "nir", "ir_cut_nm")


def register_segmenter(name: str, factory: Factory, *, replace: bool = False) -> None:
    """Make ``factory(**options)`` available as ``create_segmenter(name, **options)``."""
    if not name or not name.replace("-", "").replace("_", "").isalnum():
        raise AnalysisInputError("name", f"segmenter names are letters, digits, '-' and '_', got {name!r}")
    if name in _REGISTRY and not replace:
        raise AnalysisInputError("name", f"segmenter {name!r} is already registered")
    _REGISTRY[name] = factory


def segmenter_names() -> list[str]:
    return sorted(_REGISTRY)


def create_segmenter(name: str, **options: Any) -> Segmenter:
    """Instantiate a registered segmenter; unknown names raise UnknownSegmenterError."""
    try:
        factory = _REGISTRY[name]
    except KeyError:
        close = difflib.get_close_matches(name, list(_REGISTRY), n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise UnknownSegmenterError(
            f"unknown segmenter {name!r}; known: {', '.join(segmenter_names())}{hint}"
        ) from None
    try:
        return factory(**options)
    except TypeError as exc:  # an option the constructor does not take
        raise AnalysisInputError("options", f"segmenter {name!r}: {exc}") from exc


def run_segmenter(segmenter: Segmenter, cube: object) -> np.ndarray:
    """Validate the cube, segment it, and check the label map the segmenter returned."""
    arr = as_cube(cube)
    labels = as_label_map(segmenter.segment(arr), f"labels from {segmenter.name}")
    if labels.shape != arr.shape[1:]:
        where = f"labels from {segmenter.name}"
        raise AnalysisInputError(where, f"shape {labels.shape}, expected {arr.shape[1:]}")
    return labels


def _split_rgb(options: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    rgb = {k: options.pop(k) for k in _RGB_OPTIONS if k in options}
    return rgb, options


def _spectral(**options: Any) -> Segmenter:
    return SpectralSegmenter(**options)


def _rgb_spectral(**options: Any) -> Segmenter:
    rgb, rest = _split_rgb(dict(options))
    return RgbBaseline(SpectralSegmenter(**rest), **rgb)


def _rgb_nir_spectral(**options: Any) -> Segmenter:
    rgb, rest = _split_rgb(dict(options))
    return RgbBaseline(SpectralSegmenter(**rest), rendering="bruton", **rgb)


def _sweep(**options: Any) -> Segmenter:
    return SweepSegmenter(**options)


def _rgb_sweep(**options: Any) -> Segmenter:
    rgb, rest = _split_rgb(dict(options))
    return RgbBaseline(SweepSegmenter(**rest), **rgb)


def _pose(**options: Any) -> Segmenter:
    # The options of an evaluation go to all its segmenters; the reference's segmenter takes the rest.
    return PoseSegmenter(**{k: v for k, v in options.items() if k.startswith("pose_") or k == "seed"})


def _sam(**options: Any) -> Segmenter:
    return SamSegmenter(**options)


def _sam_rgb(**options: Any) -> Segmenter:
    rgb, rest = _split_rgb(dict(options))
    rest.setdefault("mode", "image")
    return RgbBaseline(SamSegmenter(**rest), **rgb)


register_segmenter("spectral", _spectral)
register_segmenter("rgb", _rgb_spectral)
register_segmenter("rgb-nir", _rgb_nir_spectral)
register_segmenter("spectral-sweep", _sweep)
register_segmenter("rgb-sweep", _rgb_sweep)
register_segmenter("spectral-pose", _pose)
register_segmenter("sam", _sam)
register_segmenter("sam-rgb", _sam_rgb)
