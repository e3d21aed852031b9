"""Where demosaicing fails: saturation, very low light, aliasing, a wrong MSFA phase — and the warnings."""

from __future__ import annotations

import numpy as np
import pytest

from m2s2hil.config import CameraModel
from m2s2hil.processing.chain import FrameProcessor
from m2s2hil.processing.dark import build_master_dark
from m2s2hil.processing.demosaic import METHODS, get_demosaicer
from m2s2hil.processing.errors import UnknownMethodError
from m2s2hil.processing.groundtruth import mosaic_of, synthetic_scene
from m2s2hil.processing.image_quality import sam_map
from m2s2hil.processing.mosaic import MosaicLayout, cell_mean
from m2s2hil.processing.stability import (
    band_saturation,
    check_phase,
    grow_mask,
    support_radius,
)

CAM = CameraModel(width=128, height=128)
CAM16 = CameraModel(width=128, height=128, bit_depth=16)
LAYOUT = MosaicLayout.from_camera(CAM)
SCENE = synthetic_scene(CAM, 128, seed=3)


@pytest.mark.parametrize("method", METHODS)
def test_saturation_is_flagged_and_contained(method):
    bright = SCENE.cube * 2.0  # highlights beyond 10-bit full scale
    raw16 = mosaic_of(bright, LAYOUT, CAM16.full_scale)
    raw10 = np.minimum(raw16, CAM.full_scale)
    clipped = raw16 >= CAM.full_scale
    assert 0.02 < clipped.mean() < 0.6
    frame = FrameProcessor(method, CAM).process(raw10)
    assert any("full scale" in w for w in frame.warnings)
    mask = frame.saturated_mask
    d = get_demosaicer(method, LAYOUT, raw10.shape)
    if d.full_resolution:
        assert mask.shape == raw10.shape and mask[clipped].all()
    else:
        assert (
            mask.shape == (32, 32) and mask.sum() == np.any(clipped.reshape(32, 4, 32, 4), axis=(1, 3)).sum()
        )
    # outside the flag, the frame is what an unclipping sensor would have given
    ideal = FrameProcessor(method, CAM16).process(raw16).cube
    out = ~mask
    if method == "ppid":  # its band balancing uses whole-frame means, which clipping shifts a little
        np.testing.assert_allclose(frame.cube[:, out], ideal[:, out], rtol=0.03, atol=1.0)
    else:
        np.testing.assert_array_equal(frame.cube[:, out], ideal[:, out])
    # inside it, clipping did destroy the values
    assert np.abs(frame.cube[:, mask] - ideal[:, mask]).max() > 50


@pytest.mark.parametrize("method", METHODS)
def test_the_clipping_mask_rebuilt_from_the_raw_is_the_processors(method):
    """A stored cube does not keep its mask: ``band_saturation`` rebuilds it from the raw frame
    without demosaicing, and its ``any`` over bands must be exactly what the processor gave (with a
    dark too: the flag is the raw value at full scale, before the dark is subtracted)."""
    raw = np.minimum(mosaic_of(SCENE.cube * 2.0, LAYOUT, CAM16.full_scale), CAM.full_scale)
    dark = build_master_dark(np.stack([np.full(raw.shape, 40, np.uint16)] * 2), exposure_s=0.01, gain=1.0,
                              temperature_c=25.0)
    for proc in (FrameProcessor(method, CAM), FrameProcessor(method, CAM, dark=dark)):
        given = proc.process(raw).saturated_mask
        rebuilt = band_saturation(raw >= CAM.full_scale, method, LAYOUT).any(axis=0)
        assert given.any() and not given.all()
        np.testing.assert_array_equal(rebuilt, given)
    with pytest.raises(UnknownMethodError, match="unknown demosaicing method 'bilinear'"):
        band_saturation(raw >= CAM.full_scale, "bilinear", LAYOUT)


def test_ppid_with_fixed_gains_contains_saturation_exactly():
    bright = SCENE.cube * 2.0
    raw16 = mosaic_of(bright, LAYOUT, CAM16.full_scale)
    raw10 = np.minimum(raw16, CAM.full_scale)
    levels = SCENE.cube.mean(axis=(1, 2))  # what a white reference would give
    clipped_d, ideal_d = (get_demosaicer("ppid", LAYOUT, raw10.shape) for _ in range(2))
    clipped_d.fix_gains(levels)
    ideal_d.fix_gains(levels)
    out = ~grow_mask(raw16 >= CAM.full_scale, clipped_d.support_radius)
    np.testing.assert_array_equal(clipped_d.process(raw10)[:, out], ideal_d.process(raw16)[:, out])


def test_no_saturation_no_flag():
    raw = mosaic_of(SCENE.cube * 0.5, LAYOUT, CAM.full_scale)
    fp = FrameProcessor("wb", CAM)
    frame = fp.process(raw)
    assert not frame.saturated_mask.any()
    assert frame.warnings == []
    # a saturated frame then a clean one: the mask is cleared, not left over
    fp.process(mosaic_of(SCENE.cube * 3.0, LAYOUT, CAM.full_scale))
    assert not fp.process(raw).saturated_mask.any()


def test_phase_error_is_detected_and_the_offset_recovers_the_frame():
    good = mosaic_of(SCENE.cube, LAYOUT, CAM.full_scale)
    assert not check_phase(good, LAYOUT).suspect
    assert not any("phase" in w for w in FrameProcessor("wb", CAM).process(good).warnings)
    for offset in [(0, 1), (1, 0), (1, 3)]:
        bad = mosaic_of(SCENE.cube, LAYOUT, CAM.full_scale, offset=offset)
        check = check_phase(bad, LAYOUT)
        assert check.suspect, offset
        warnings = FrameProcessor("wb", CAM).process(bad).warnings
        assert any("phase" in w for w in warnings)
        # demosaicing with the layout shifted by the reported offset is as good as a clean read
        fixed = get_demosaicer("wb", LAYOUT.shifted(*check.offset), bad.shape).process(bad)
        ref = get_demosaicer("wb", LAYOUT, good.shape).process(good)
        naive = get_demosaicer("wb", LAYOUT, bad.shape).process(bad)
        sam_fixed, sam_ref, sam_naive = (
            np.nanmean(sam_map(c, SCENE.cube)[12:-12, 12:-12]) for c in (fixed, ref, naive)
        )
        assert sam_fixed < 1.3 * sam_ref and sam_naive > 3 * sam_ref


def test_phase_check_is_inconclusive_on_a_grey_scene():
    yy, xx = np.mgrid[0:128, 0:128] / 128.0
    shading = 450 + 300 * np.sin(3 * xx) * np.cos(2 * yy)
    grey = np.broadcast_to(shading, (10, 128, 128))  # every band at the same level: nothing to go by
    check = check_phase(mosaic_of(grey, LAYOUT, CAM.full_scale, offset=(0, 1)), LAYOUT)
    assert not check.conclusive and not check.suspect


def _dark(read_noise: float, n: int = 8) -> object:
    rng = np.random.default_rng(9)
    frames = np.clip(np.rint(rng.normal(30, read_noise, (n, 128, 128))), 0, None).astype(np.uint16)
    return build_master_dark(frames, exposure_s=0.01, gain=1.0, temperature_c=25.0)


def test_low_light_warning():
    dark = _dark(3.0)
    dim = mosaic_of(SCENE.cube * (10.0 / SCENE.cube.max()) + 30, LAYOUT, CAM.full_scale, read_noise_dn=3.0)
    frame = FrameProcessor("superpixel", CAM, dark=dark).process(dim)
    assert any("SNR below 5" in w for w in frame.warnings)
    bright = mosaic_of(SCENE.cube + 30, LAYOUT, CAM.full_scale, read_noise_dn=3.0)
    assert not any("SNR" in w for w in FrameProcessor("superpixel", CAM, dark=dark).process(bright).warnings)


def _sam(method: str, raw: np.ndarray, truth: np.ndarray) -> np.ndarray:
    d = get_demosaicer(method, LAYOUT, raw.shape)
    ref = truth if d.full_resolution else cell_mean(truth, 4)
    return sam_map(d.process(raw), ref)


@pytest.mark.parametrize("method", METHODS)
def test_wrong_phase_breaks_every_method(method):
    clean = np.nanmean(
        _sam(method, mosaic_of(SCENE.cube, LAYOUT, CAM.full_scale), SCENE.cube)[12:-12, 12:-12]
    )
    shifted = mosaic_of(SCENE.cube, LAYOUT, CAM.full_scale, offset=(0, 1))
    bad = np.nanmean(_sam(method, shifted, SCENE.cube)[12:-12, 12:-12])
    assert bad > 3 * clean and bad > 5.0


@pytest.mark.parametrize("method", METHODS)
def test_aliasing_fine_gratings_create_false_colour(method):
    """One material (constant spectrum) under a zone plate: every spectral angle is an artefact; it
    stays small where the grating is coarse and grows past the sub-lattice's Nyquist limit."""
    size = 128
    yy, xx = np.mgrid[0:size, 0:size] - (size - 1) / 2.0
    r = np.hypot(yy, xx)
    pattern = 0.5 + 0.5 * np.cos(np.pi * 0.5 * r**2 / (size / 2.0))  # 0 .. 0.5 cycles/px at the edge
    spectrum = np.linspace(300, 900, 10)
    cube = spectrum[:, None, None] * (0.2 + 0.8 * pattern)[None]
    sam = _sam(method, mosaic_of(cube, LAYOUT, CAM.full_scale), cube)
    if sam.shape[0] != size:  # super-pixel: radius of each cell's centre
        r = np.hypot(*(np.mgrid[0 : size // 4, 0 : size // 4] * 4 + 1.5 - (size - 1) / 2.0))
    ring_lo, ring_hi = r < 5, (r > 40) & (r < 56)  # below 0.04 cycles/px, and 0.3-0.45 cycles/px
    low, high = np.nanmean(sam[ring_lo]), np.nanmean(sam[ring_hi])
    assert high > 5 * low and high > 2.0
    assert np.isfinite(sam[ring_hi]).all()


def test_which_bands_a_clipped_raw_pixel_spoils():
    """``band_saturation``: super-pixel, nearest and WB build each band from its own samples, so a
    clipped raw pixel spoils only its band (one cell, or the support around it); PPID's guide mixes
    every band, so all of them."""
    raw_mask = np.zeros((16, 16), bool)
    raw_mask[5, 6] = True  # cell (1, 1), position (1, 2)
    band = int(LAYOUT.array[1, 2])
    sp = band_saturation(raw_mask, "superpixel", LAYOUT)
    assert sp.shape == (LAYOUT.n_bands, 4, 4)
    assert np.argwhere(sp).tolist() == [[band, 1, 1]]
    for method in ("nearest", "wb"):
        full = band_saturation(raw_mask, method, LAYOUT)
        others = np.delete(full, band, axis=0)
        assert not others.any()
        np.testing.assert_array_equal(full[band], grow_mask(raw_mask, support_radius(method, LAYOUT.n)))
    for method, shape in (("superpixel", (4, 4)), ("wb", (16, 16))):  # nothing clipped: nothing flagged
        none = band_saturation(np.zeros_like(raw_mask), method, LAYOUT)
        assert none.shape == (LAYOUT.n_bands, *shape) and not none.any()
    ppid = band_saturation(raw_mask, "ppid", LAYOUT)
    assert all(np.array_equal(ppid[b], grow_mask(raw_mask, support_radius("ppid", LAYOUT.n)))
               for b in range(LAYOUT.n_bands))
