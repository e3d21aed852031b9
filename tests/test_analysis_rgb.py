"""Wavelength→RGB values computed by hand from the Bruton ramps, the NIR rule, and the rendering."""

from __future__ import annotations

import numpy as np
import pytest

from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.rgb import RgbBaseline, band_colours, render_rgb, wavelength_to_rgb
from m2s2hil.analysis.spectral import SpectralSegmenter
from m2s2hil.analysis.synthetic import synthetic_scene

G = 0.8


@pytest.mark.parametrize(
    ("nm", "rgb"),
    [
        (431, (0.15**G, 0.0, 1.0)),  # R = (440−431)/60 = 0.15, factor 1
        (400, ((0.65 * 40 / 60) ** G, 0.0, 0.65**G)),  # factor 0.3 + 0.7·20/40 = 0.65
        (479, (0.0, (39 / 50) ** G, 1.0)),
        (500, (0.0, 1.0, 0.5**G)),
        (515, ((5 / 70) ** G, 1.0, 0.0)),
        (611, (1.0, (34 / 65) ** G, 0.0)),
        (700, (1.0, 0.0, 0.0)),  # factor 0.3 + 0.7·80/80 = 1
        (719, (0.83375**G, 0.0, 0.0)),  # factor 0.3 + 0.7·61/80
        (775, (0.34375**G, 0.0, 0.0)),
        (780, (0.3**G, 0.0, 0.0)),
    ],
)
def test_bruton_values(nm: float, rgb: tuple[float, float, float]) -> None:
    assert wavelength_to_rgb(nm) == pytest.approx(rgb)


def test_near_infrared_rule() -> None:
    assert wavelength_to_rgb(820) == pytest.approx((0.3**G, 0.0, 0.0))  # colour of 780 nm
    assert wavelength_to_rgb(877) == wavelength_to_rgb(820)
    assert wavelength_to_rgb(877, nir="black") == (0.0, 0.0, 0.0)
    assert wavelength_to_rgb(350) == pytest.approx((0.3**G, 0.0, 0.3**G))  # colour of 380 nm
    assert wavelength_to_rgb(611, gamma=1.0) == pytest.approx((1.0, 34 / 65, 0.0))
    with pytest.raises(AnalysisInputError, match="nir"):
        wavelength_to_rgb(820, nir="red")  # type: ignore[arg-type]
    with pytest.raises(AnalysisInputError, match="wavelength"):
        wavelength_to_rgb(-5)


def test_render_is_a_colour_weighted_band_mean() -> None:
    cube = np.stack([np.full((2, 3), 1.0), np.full((2, 3), 3.0)])  # bands at 431 and 611 nm
    rgb = render_rgb(cube, bands_nm=(431, 611))
    r431, r611 = 0.15**G, 1.0
    assert rgb.shape == (3, 2, 3)
    assert rgb[0, 0, 0] == pytest.approx((r431 * 1 + r611 * 3) / (r431 + r611))
    assert rgb[1, 0, 0] == pytest.approx(3.0)  # only 611 nm has green
    assert rgb[2, 0, 0] == pytest.approx(1.0)  # only 431 nm has blue
    no_blue = render_rgb(cube[1:], bands_nm=(611,))
    assert np.all(no_blue[2] == 0)  # a channel no band feeds stays 0
    with pytest.raises(AnalysisInputError, match="wavelengths"):
        render_rgb(cube, bands_nm=(431,))


def test_toucan_band_colours() -> None:
    colours = band_colours()
    assert colours.shape == (10, 3)
    assert np.all(colours[8:, 1:] == 0) and np.all(colours[7:, 0] > 0.38)  # NIR: dark red


def test_rgb_baseline_segments_the_rendering() -> None:
    cube, gt = synthetic_scene((40, 40), 3, seed=2)
    base = RgbBaseline(SpectralSegmenter(seed=0))
    labels = base.segment(cube)
    assert base.name == "rgb-spectral"
    assert labels.shape == gt.shape
    assert np.array_equal(labels, SpectralSegmenter(seed=0).segment(render_rgb(cube)))
    assert ((labels > 0) == (gt > 0)).mean() > 0.95
