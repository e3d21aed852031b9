"""Calibration targets the simulated camera can look at instead of the mockup.

``white_panel``: a flat diffuse panel of known reflectance facing the camera and filling the
view, as an operator holds one for the white reference. Its signal is the lamps' irradiance on
a camera-facing surface (the same lights the mockup's shader uses) times the panel's reflectance
and each band's response, times a gentle radial fall-off (lens vignetting plus uneven lighting,
here 12 % from centre to corner: an assumption, not a measured TOUCAN figure).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from m2s2hil.simulators.shading import LightingParams, lights_from_lamps

TARGETS = ("mockup", "white_panel")
WHITE_REFLECTANCE = 0.99
FALLOFF = 0.12


def white_panel_pattern(band_response: np.ndarray, band_map: np.ndarray) -> np.ndarray:
    """(H, W) float32: each pixel's band response times the radial fall-off. It depends on the
    camera alone, so a frame source works it out once and scales it per frame."""
    h, w = band_map.shape
    y = np.linspace(-1.0, 1.0, h, dtype=np.float32)[:, None]
    x = np.linspace(-1.0, 1.0, w, dtype=np.float32)[None, :]
    field = 1.0 - np.float32(FALLOFF / 2.0) * (x * x + y * y)
    pattern = (np.asarray(band_response, dtype=np.float32)[band_map] * field).astype(np.float32)
    pattern.flags.writeable = False
    return pattern


def white_panel_rate(
    pattern: np.ndarray, lamp_output: Mapping[int, float], lamp_info: Mapping[int, Any],
    spot_angle_deg: float, params: LightingParams, reflectance: float = WHITE_REFLECTANCE,
) -> np.ndarray:
    """(H, W) float32 electrons/s per pixel for the panel under the lit lamps; ``pattern`` from
    :func:`white_panel_pattern`."""
    lights = lights_from_lamps(lamp_output, lamp_info, spot_angle_deg, params)
    facing = float(np.sum(lights.irradiance * np.maximum(lights.dirs[:, 2], 0.0))) + lights.ambient
    return pattern * np.float32(reflectance * facing)
