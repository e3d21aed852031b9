"""Issue 15: previews and contact sheets are white-balanced (grey world, or the calibration's white
reference) and sRGB-encoded, so a neutral material looks neutral."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from m2s2hil.analysis.report.session_html import preview_rgb
from m2s2hil.engine.frames import calibrated_white, rgb_preview
from m2s2hil.processing.display import false_colour

BANDS = (431.0, 479.0, 515.0, 567.0, 611.0, 666.0, 719.0, 775.0, 820.0, 877.0)
# A warm lamp times the sensor's band response: the mid bands collect the most light.
RESPONSE = np.array([0.3, 0.6, 0.9, 1.0, 0.8, 0.5, 0.4, 0.3, 0.2, 0.1])


def grey_object(level: float = 0.18) -> np.ndarray:
    """A spectrally flat (neutral) square on a black backdrop, as the camera records it."""
    refl = np.zeros((32, 32))
    refl[8:24, 8:24] = level
    return (RESPONSE[:, None, None] * refl[None]).astype(np.float32)


def test_neutral_object_is_neutral_in_the_preview():
    cube = grey_object()
    img = rgb_preview(cube, BANDS)
    obj = img[10:22, 10:22].reshape(-1, 3).astype(int)
    assert np.ptp(obj.mean(axis=0)) <= 1  # R = G = B: no green cast
    assert obj.mean() == 255  # the object is the brightest thing: scaled to white
    old = np.stack([cube[i] for i in (5, 3, 1)], axis=-1)  # 666/567/479 nm, stretched, no balance
    assert old[12, 12, 1] > 1.5 * old[12, 12, 0]  # what the issue saw: neutral looks green
    assert np.array_equal(img, rgb_preview(np.moveaxis(cube, 0, -1), BANDS))  # (H, W, bands) too
    assert rgb_preview(None, BANDS) is None


def test_srgb_transfer_curve_on_a_grey_ramp():
    cube = grey_object()
    cube[:, 8:24, 8:16] *= 0.18  # left half of the object at 18 % of the right half
    img = rgb_preview(cube, BANDS)
    dark, bright = int(img[12, 10, 1]), int(img[12, 20, 1])
    assert bright == 255
    assert abs(dark - round(255 * (1.055 * 0.18 ** (1 / 2.4) - 0.055))) <= 1  # 118, not 46 (linear)


def test_calibrated_white_reference_replaces_grey_world():
    processor = SimpleNamespace(calibration=SimpleNamespace(white_mosaic=np.ones((4, 4)),
                                                            white_reflectance=np.full(10, 0.99)))
    white = calibrated_white(processor)
    assert white is not None and np.allclose(white, 0.99)
    assert calibrated_white(SimpleNamespace(calibration=None)) is None
    assert calibrated_white(SimpleNamespace(calibration=SimpleNamespace(white_mosaic=None))) is None
    no_refl = SimpleNamespace(white_mosaic=1, white_reflectance=None)
    flat = calibrated_white(SimpleNamespace(calibration=no_refl))
    # a reflectance cube of a red object: grey world would make it grey, the white reference keeps it red
    cube = np.zeros((10, 16, 16), np.float32)
    cube[:, 4:12, 4:12] = np.linspace(0.1, 0.8, 10)[:, None, None]
    img = rgb_preview(cube, BANDS, white=flat)
    assert img[8, 8, 0] > img[8, 8, 1] > img[8, 8, 2]
    balanced = rgb_preview(cube, BANDS)
    assert np.ptp(balanced[8, 8].astype(int)) <= 1


def test_contact_sheet_uses_the_same_rendering():
    cube = grey_object()
    assert np.array_equal(preview_rgb(cube, BANDS), false_colour(cube, BANDS))
    assert np.array_equal(preview_rgb(cube, BANDS), rgb_preview(cube, BANDS))
