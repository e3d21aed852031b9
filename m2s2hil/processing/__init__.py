"""Frame processing: dark frames, MSFA demosaicing, calibration, quality metrics and benchmarks.

Submodules load lazily so that, e.g., ``m2s2hil.processing.dark`` does not pull in numba.
Main entry points::

    from m2s2hil.processing import METHODS, get_demosaicer, FrameProcessor
    from m2s2hil.processing.dark import build_master_dark, DarkLibrary, subtract_dark
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

_EXPORTS = {
    "METHODS": "m2s2hil.processing.demosaic",
    "Demosaicer": "m2s2hil.processing.demosaic",
    "get_demosaicer": "m2s2hil.processing.demosaic",
    "MosaicLayout": "m2s2hil.processing.mosaic",
    "sample_cube": "m2s2hil.processing.mosaic",
    "FrameProcessor": "m2s2hil.processing.chain",
    "ProcessedFrame": "m2s2hil.processing.chain",
    "MasterDark": "m2s2hil.processing.dark",
    "DarkLibrary": "m2s2hil.processing.dark",
    "build_master_dark": "m2s2hil.processing.dark",
    "subtract_dark": "m2s2hil.processing.dark",
    "CameraCalibration": "m2s2hil.processing.calibration",
    "load_calibration": "m2s2hil.processing.calibration",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'm2s2hil.processing' has no attribute {name!r}")
