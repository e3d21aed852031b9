"""The camera RGB rendering (CIE 1931 → sRGB, IR cut) checked against colour-science, and the Bruton
wavelength→RGB values computed by hand from the ramps, the NIR rule, and the rendering."""

from __future__ import annotations

import numpy as np
import pytest

from m2s2hil.analysis.cie1931 import CIE1931_2DEG_5NM, XYZ_TO_LINEAR_SRGB
from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.segmenters.rgb import (
    TOUCAN_BANDS_NM,
    RgbBaseline,
    band_colours,
    camera_rgb,
    camera_weights,
    render_rgb,
    wavelength_to_rgb,
)
from m2s2hil.analysis.segmenters.spectral import SpectralSegmenter
from m2s2hil.analysis.study.synthetic import synthetic_scene

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
    assert base.name == "rgb-spectral" and base.rendering == "camera"
    assert labels.shape == gt.shape
    assert np.array_equal(labels, SpectralSegmenter(seed=0).segment(camera_rgb(cube)))
    assert ((labels > 0) == (gt > 0)).mean() > 0.95
    nir = RgbBaseline(SpectralSegmenter(seed=0), rendering="bruton")
    assert nir.name == "rgb-nir-spectral"
    assert np.array_equal(nir.segment(cube), SpectralSegmenter(seed=0).segment(render_rgb(cube)))
    with pytest.raises(AnalysisInputError, match="Bruton"):
        RgbBaseline(SpectralSegmenter(), nir="clamp")
    with pytest.raises(AnalysisInputError, match="IR cut"):
        RgbBaseline(SpectralSegmenter(), rendering="bruton", ir_cut_nm=700.0)


# --- camera rendering ---------------------------------------------------------------------------


def test_committed_cmf_table_is_the_cie_1931_observer() -> None:
    colour = pytest.importorskip("colour")
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    for nm, x, y, z in CIE1931_2DEG_5NM:
        assert (x, y, z) == pytest.approx(tuple(cmfs[nm]), rel=1e-5, abs=1e-9)
    assert np.allclose(XYZ_TO_LINEAR_SRGB, colour.models.RGB_COLOURSPACE_sRGB.matrix_XYZ_to_RGB)


def test_camera_sees_no_near_infrared() -> None:
    w = camera_weights()
    nm = np.array(TOUCAN_BANDS_NM)
    assert w.shape == (10, 3)
    assert np.all(w[nm >= 775] == 0)  # behind the 700 nm IR cut
    assert np.allclose(w.sum(axis=0), 1.0)  # a flat spectrum renders neutral at its own level
    # the Bruton map with NIR clamped gives 22.7 % of red to bands >= 775 nm (issue 15)
    bruton = band_colours()
    assert bruton[nm >= 775, 0].sum() / bruton[:, 0].sum() == pytest.approx(0.2268, abs=1e-3)
    # without the cut the CMFs alone leave ~0.01 % to those bands
    open_w = camera_weights(ir_cut_nm=780.0)
    share = np.abs(open_w[nm >= 775, 0]).sum() / np.abs(open_w[:, 0]).sum()
    assert 0 < share < 5e-4


def test_camera_weights_by_hand_for_two_bands() -> None:
    """Bands at 500 and 600 nm: hats 1→0 and 0→1 between them, constant outside; recompute by sums."""
    from m2s2hil.analysis.cie1931 import cmf_table

    nm_t, cmf = cmf_table()
    lam = np.arange(380.0, 701.0)
    bar = np.stack([np.interp(lam, nm_t, cmf[:, i]) for i in range(3)], axis=1)
    hat600 = np.clip((lam - 500.0) / 100.0, 0, 1)
    xyz = np.stack([(1 - hat600) @ bar, hat600 @ bar])
    rgb = xyz @ XYZ_TO_LINEAR_SRGB.T
    expect = rgb / rgb.sum(axis=0)
    assert camera_weights((500.0, 600.0)) == pytest.approx(expect)
    assert camera_weights((600.0, 500.0)) == pytest.approx(expect[::-1])  # order of bands kept
    cube = np.stack([np.full((2, 2), 2.0), np.full((2, 2), 2.0)])
    assert np.allclose(camera_rgb(cube, (500.0, 600.0)), 2.0, atol=1e-5)  # flat → neutral
    with pytest.raises(AnalysisInputError, match="ir_cut_nm"):
        camera_weights(ir_cut_nm=300.0)
    with pytest.raises(AnalysisInputError, match="bands_nm"):
        camera_weights((500.0, 500.0))
