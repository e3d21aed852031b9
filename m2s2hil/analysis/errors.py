"""Typed errors of the analysis library.

Every error names the argument (or file) at fault and what is wrong with it, so an
``m2s2hil evaluate`` command or the capture-time QC can show it to a person unchanged.
"""

from __future__ import annotations

from m2s2hil.errors import UsageError


class AnalysisError(UsageError):
    """Base of the analysis library's deliberate errors (exit code 2: bad input)."""


class AnalysisInputError(AnalysisError):
    """An array or parameter that cannot be analysed.

    ``argument`` names the parameter at fault (``"gt"``, ``"cube"``, ``"rho"`` ...).
    """

    def __init__(self, argument: str, problem: str) -> None:
        self.argument = argument
        self.problem = problem
        super().__init__(f"{argument}: {problem}")


class UnknownSegmenterError(AnalysisError):
    """A segmenter name that is not registered."""


class SegmenterUnavailableError(AnalysisError):
    """A segmenter whose optional dependency or model checkpoint is missing.

    ``requirement`` says what to install or supply (e.g. ``pip install m2s2hil[sam]``).
    """

    def __init__(self, segmenter: str, requirement: str) -> None:
        self.segmenter = segmenter
        self.requirement = requirement
        super().__init__(f"segmenter {segmenter!r} is unavailable: {requirement}")
