"""Typed errors of the frame-processing stage.

All derive from ``m2s2hil.errors.M2S2Error``; the ones caused by bad input (an unknown
method name, a layout a method cannot handle, a calibration file that cannot be used)
are also ``UsageError`` so the CLI exits with code 2.
"""

from __future__ import annotations

from m2s2hil.errors import KeyedError, M2S2Error, UsageError


class ProcessingError(M2S2Error):
    """Base of every error raised on purpose by ``m2s2hil.processing``."""


class FrameShapeError(ProcessingError, UsageError):
    """A frame (raw, dark, white reference) whose shape or dtype does not fit."""


class DarkMismatchError(ProcessingError):
    """The dark frame asked for does not match the frame's exposure, gain or temperature.

    ``wanted`` describes the request, ``available`` the closest darks on hand.
    """

    def __init__(self, problem: str, *, wanted: dict | None = None, available: list[dict] | None = None):
        self.problem = problem
        self.wanted = wanted or {}
        self.available = available or []
        super().__init__(problem)


class DarkNotFoundError(DarkMismatchError):
    """The dark library holds no dark at all (or none for this sensor shape)."""


class DarkLibraryError(ProcessingError):
    """A dark library entry that cannot be read (missing file, checksum mismatch, bad sidecar)."""


class UnknownMethodError(ProcessingError, UsageError):
    """A demosaicing method name that is not one of ``METHODS``."""


class LayoutError(ProcessingError, UsageError):
    """An MSFA layout that is malformed or that a method refuses."""


class CalibrationError(ProcessingError, KeyedError):
    """A camera calibration file that cannot be used; ``source`` names the file, ``key`` the entry."""


class BracketError(ProcessingError, UsageError):
    """An exposure bracket whose frames cannot be merged: shapes, exposures or masks that do not agree."""
