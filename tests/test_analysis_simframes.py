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
