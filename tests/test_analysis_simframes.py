"""The analysis' simulated frames carry what the renderer knows: the light on each pixel."""

from __future__ import annotations

import numpy as np
from sim_frame import one_frame


def test_a_frame_under_the_spotlight_knows_its_shadows():
    lit = one_frame("voyager", "B2", size=256)
    spot = one_frame("voyager", "B2", size=256, lightings=["directional"], spot_angle_deg=80.0)
    for f in (lit, spot):
        assert f.irradiance is not None and f.irradiance.shape == f.cube.shape[1:]

    def shadow(f) -> float:  # lit by under a tenth of the light on its well-lit faces
        light = f.irradiance[f.gt > 0]
        return float(np.mean(light < 0.1 * np.percentile(light, 95)))

    assert shadow(lit) == 0.0
    assert shadow(spot) > 0.02  # 4 % of the object at this view


def test_a_shorter_bracket_reads_an_over_exposed_frames_clipped_bands():
    import pytest

    from m2s2hil.analysis.errors import AnalysisInputError

    over = one_frame("voyager", "B2", size=256, peak_fraction=1.5)
    merged = one_frame("voyager", "B2", size=256, peak_fraction=1.5, bracket=0.25)
    clipped = float(over.band_saturated.any(axis=0)[over.gt > 0].mean())
    assert clipped > 0.2  # half the object has a band clipped at 150 % of full scale
    assert not merged.band_saturated.any()  # each read from the quarter exposure
    obj = over.gt > 0
    fine = obj & ~over.saturated  # where neither clipped, the merge keeps the first frame's scale
    assert np.median(merged.cube[:, fine] / np.maximum(over.cube[:, fine], 1)) == pytest.approx(1, abs=0.05)
    assert merged.cube[:, obj & over.saturated].max() > over.cube[:, obj & over.saturated].max()
    with pytest.raises(AnalysisInputError, match="not be 1"):
        one_frame("voyager", "B2", size=256, bracket=1.0)
