"""One simulator frame for the analysis tests: a satellite's build at E1, azimuth 30°, weak light
unless told otherwise (``simulated_frames`` keywords)."""

from __future__ import annotations

from typing import Any

from m2s2hil.analysis.study.simframes import SimFrame, simulated_frames


def one_frame(satellite: str, build: str, **conditions: Any) -> SimFrame:
    kw: dict[str, Any] = {"lightings": ["weak"], "elevations": ["E1"], "azimuths": [30.0], **conditions}
    return next(iter(simulated_frames(satellites=[satellite], builds=[build], **kw)))
