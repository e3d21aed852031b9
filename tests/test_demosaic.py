"""Demosaicing: one interface, exactness on constants and per-band ramps, any periodic n×n layout."""

from __future__ import annotations

import numpy as np
import pytest

from m2s2hil.config import DEFAULT_LAYOUT, CameraModel
from m2s2hil.errors import UsageError
from m2s2hil.processing.demosaic import METHODS, get_demosaicer
from m2s2hil.processing.errors import FrameShapeError, LayoutError, UnknownMethodError
from m2s2hil.processing.mosaic import MosaicLayout, cell_mean, sample_cube
from m2s2hil.processing.nearest import nearest_offsets

TOUCAN = MosaicLayout.from_pattern(DEFAULT_LAYOUT, 10)
LAYOUTS = {
    "4x4 default": TOUCAN,
    "2x2 bayer-like": MosaicLayout.from_pattern([[0, 1], [1, 2]]),
    "3x3 nine bands": MosaicLayout.from_pattern(np.arange(9).reshape(3, 3)),
    "3x3 with duplicates": MosaicLayout.from_pattern([[0, 1, 2], [3, 4, 0], [1, 2, 3]]),
    "5x5 seven bands": MosaicLayout.from_pattern((np.arange(25) % 7).reshape(5, 5)),
}


def ramp_cube(layout: MosaicLayout, size: int, *, seed: int = 0, whole: bool = False) -> np.ndarray:
    """Each band its own plane a_b + g_b·x + h_b·y (different slopes per band); ``whole``: whole-number
    offsets and non-zero slopes, so the ramp is exactly a uint16 mosaic."""
    rng = np.random.default_rng(seed)
    nb = layout.n_bands
    if whole:
        a, (g, h) = rng.integers(500, 700, nb), rng.choice([-3, -2, -1, 1, 2, 3], (2, nb))
    else:
        a, g, h = rng.uniform(100, 300, nb), rng.uniform(-2, 2, nb), rng.uniform(-2, 2, nb)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    return a[:, None, None] + g[:, None, None] * xx + h[:, None, None] * yy


def interior(a: np.ndarray, b: int) -> np.ndarray:
    return a[:, b:-b, b:-b]


def test_methods_and_unknown_name():
    assert METHODS == ("superpixel", "nearest", "wb", "ppid")
    with pytest.raises(UnknownMethodError) as info:
        get_demosaicer("bilinear", TOUCAN, (16, 16))
    assert isinstance(info.value, UsageError)
    for m in METHODS:
        assert m in str(info.value)


def test_accepts_camera_model_and_output_shapes():
    cam = CameraModel(width=64, height=32)
    for m in METHODS:
        d = get_demosaicer(m, cam, (32, 64))
        full = d.full_resolution
        assert d.out_shape == ((10, 32, 64) if full else (10, 8, 16))
        assert full == (m != "superpixel")


@pytest.mark.parametrize("name", list(LAYOUTS))
@pytest.mark.parametrize("method", METHODS)
def test_constant_is_reproduced_exactly(method, name):
    layout = LAYOUTS[name]
    size = 10 * layout.n
    levels = np.rint(np.linspace(50, 900, layout.n_bands))  # integers: the mosaic is uint16
    cube = np.broadcast_to(levels[:, None, None], (layout.n_bands, size, size))
    mos = sample_cube(cube, layout)
    out = get_demosaicer(method, layout, mos.shape).process(mos)
    expected = np.broadcast_to(levels[:, None, None].astype(np.float32), out.shape)
    np.testing.assert_allclose(out, expected, rtol=2e-6)  # everywhere, borders included


@pytest.mark.parametrize("name", list(LAYOUTS))
@pytest.mark.parametrize("method", ["wb", "ppid"])
def test_per_band_ramp_is_reproduced_exactly_in_the_interior(method, name):
    layout = LAYOUTS[name]
    n = layout.n
    # PPID on a uint16 ramp: production feeds it raw frames only, and its float32 specialisation
    # would be a second cold compile of the costliest kernel (~40 s) for this test alone; WB keeps
    # the float32 input the white reference gives it
    cube = ramp_cube(layout, 12 * n, whole=method == "ppid")
    mos = sample_cube(cube, layout, dtype=np.uint16 if method == "ppid" else None)
    out = get_demosaicer(method, layout, mos.shape).process(mos)
    np.testing.assert_allclose(interior(out, 3 * n), interior(cube, 3 * n), rtol=2e-6, atol=2e-4)
    # ... and the test can fail: the same ramp read with the wrong layout is far off
    wrong = get_demosaicer(method, layout.shifted(0, 1), mos.shape).process(mos)
    assert np.abs(interior(wrong, 3 * n) - interior(cube, 3 * n)).max() > 1.0


@pytest.mark.parametrize("name", list(LAYOUTS))
def test_superpixel_samples_the_ramp_at_each_bands_centroid(name):
    layout = LAYOUTS[name]
    n = layout.n
    cube = ramp_cube(layout, 8 * n, seed=1)
    d = get_demosaicer("superpixel", layout, (8 * n, 8 * n))
    out = d.process(sample_cube(cube, layout, dtype=None))
    cy, cx = d.centroids().T
    rng = np.random.default_rng(1)
    a, g, h = (
        rng.uniform(100, 300, layout.n_bands),
        rng.uniform(-2, 2, layout.n_bands),
        rng.uniform(-2, 2, layout.n_bands),
    )
    yy, xx = np.mgrid[0 : 8 * n : n, 0 : 8 * n : n].astype(np.float64)
    expected = (
        a[:, None, None]
        + g[:, None, None] * (xx + cx[:, None, None])
        + h[:, None, None] * (yy + cy[:, None, None])
    )
    np.testing.assert_allclose(out, expected, rtol=1e-6)  # exact everywhere, no border effect
    # bands whose centroid is off the cell centre are shifted against the cell-mean reference
    off_centre = np.hypot(cy - (n - 1) / 2, cx - (n - 1) / 2) > 0.1
    err = np.abs(out - cell_mean(cube.astype(np.float32), n)).max(axis=(1, 2))
    assert np.all(err[off_centre] > 0.05) and np.all(err[~off_centre] < 1e-3)


def test_superpixel_hand_computed_average_of_duplicates():
    mos = np.arange(64, dtype=np.uint16).reshape(8, 8)  # m[y, x] = 8y + x
    out = get_demosaicer("superpixel", TOUCAN, (8, 8)).process(mos)
    # band 0 sits at (0,0) and (2,2): cell (0,0) -> (0 + 18)/2, cell (0,1) -> (4 + 22)/2,
    # cell (1,0) -> (32 + 50)/2
    assert out[0, 0, 0] == 9.0 and out[0, 0, 1] == 13.0 and out[0, 1, 0] == 41.0
    # band 2 at (0,2) and (3,0): (2 + 24)/2; band 6 once at (1,2): 10 and, in cell (1,1), 8*5 + 6
    assert out[2, 0, 0] == 13.0
    assert out[6, 0, 0] == 10.0 and out[6, 1, 1] == 46.0
    # band 9 once at (2,1): cell (1,1) -> 8*6 + 5
    assert out[9, 1, 1] == 53.0


@pytest.mark.parametrize("name", list(LAYOUTS))
def test_nearest_copies_the_nearest_sample(name):
    layout = LAYOUTS[name]
    n = layout.n
    cube = ramp_cube(layout, 8 * n, seed=2)
    mos = sample_cube(cube, layout, dtype=None)
    out = get_demosaicer("nearest", layout, mos.shape).process(mos)
    dy, dx = nearest_offsets(layout)
    bands = layout.band_map(*mos.shape)
    yy, xx = np.mgrid[0 : 8 * n, 0 : 8 * n]
    for b in range(layout.n_bands):
        # exact at the band's own samples ...
        np.testing.assert_allclose(out[b][bands == b], cube[b][bands == b], rtol=1e-6)
        # ... and elsewhere a copy of the nearest one (so a ramp is a staircase, not reproduced)
        sy, sx = yy + dy[b, yy % n, xx % n], xx + dx[b, yy % n, xx % n]
        ok = (sy >= 0) & (sy < 8 * n) & (sx >= 0) & (sx < 8 * n)
        assert np.all(np.hypot(dy[b], dx[b]) < n)
        np.testing.assert_allclose(out[b][ok], cube[b][sy[ok], sx[ok]], rtol=1e-6)


@pytest.mark.parametrize("method", METHODS)
def test_output_is_preallocated_and_reused(method):
    rng = np.random.default_rng(3)
    d = get_demosaicer(method, TOUCAN, (32, 32))
    a = d.process(rng.integers(0, 1024, (32, 32), dtype=np.uint16))
    first = a.copy()
    b = d.process(rng.integers(0, 1024, (32, 32), dtype=np.uint16))
    assert a is b is d.out
    assert not np.array_equal(first, b)


@pytest.mark.parametrize("method", ["superpixel", "wb"])
def test_float_and_uint16_inputs_agree(method):
    rng = np.random.default_rng(4)
    mos = rng.integers(0, 1024, (32, 48), dtype=np.uint16)
    d = get_demosaicer(method, TOUCAN, mos.shape)
    a = d.process(mos).copy()
    np.testing.assert_array_equal(d.process(mos.astype(np.float32)), a)


def test_bad_frames_and_layouts_are_refused():
    d = get_demosaicer("wb", TOUCAN, (16, 16))
    with pytest.raises(FrameShapeError):
        d.process(np.zeros((16, 20), np.uint16))
    with pytest.raises(FrameShapeError):
        d.process(np.zeros((16, 16), np.int32))
    with pytest.raises(FrameShapeError, match="multiples of 4"):
        get_demosaicer("wb", TOUCAN, (18, 16))
    with pytest.raises(LayoutError, match="no position for bands"):
        MosaicLayout.from_pattern([[0, 1], [1, 0]], 3)
    with pytest.raises(LayoutError, match="square"):
        MosaicLayout.from_pattern([[0, 1, 2]])
    with pytest.raises(LayoutError, match="n ≥ 2"):
        get_demosaicer("ppid", MosaicLayout.from_pattern([[0]]), (8, 8))


def test_shifted_layout_is_what_an_offset_read_sees():
    rng = np.random.default_rng(5)
    cube = rng.uniform(0, 1000, (10, 16, 16))
    shifted_read = sample_cube(cube, TOUCAN)[:, 1:]  # the first column never arrives
    np.testing.assert_array_equal(shifted_read, sample_cube(cube[:, :, 1:], TOUCAN.shifted(0, 1)))
