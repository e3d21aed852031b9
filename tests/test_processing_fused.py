"""The one-pass dark + saturation + super-pixel path equals the two-step chain it replaces."""

from __future__ import annotations

import numpy as np
import pytest

from m2s2hil.config import CameraModel
from m2s2hil.processing.chain import FrameProcessor
from m2s2hil.processing.dark import build_master_dark, subtract_dark
from m2s2hil.processing.errors import FrameShapeError
from m2s2hil.processing.groundtruth import mosaic_of, synthetic_scene
from m2s2hil.processing.mosaic import MosaicLayout
from m2s2hil.processing.stability import (
    LOW_SNR,
    cell_mask,
    check_phase,
    low_light_warning,
    phase_warning,
    saturation_warning,
    sublattice_stats,
)
from m2s2hil.processing.superpixel import SuperPixelDemosaicer

CAM = CameraModel(width=64, height=48)  # 12 cell rows: the QC rows are cell rows 0 and 8
LAYOUT = MosaicLayout.from_camera(CAM)
FS = CAM.full_scale


def _two_step(raw, dark, read_noise=None):
    """(cube, cell mask, warnings) the way the chain computed them before the fused kernel."""
    if dark is None:
        corrected, sat = raw, raw >= FS
    else:
        corrected, sat = subtract_dark(raw, dark, full_scale=FS)
    cube = SuperPixelDemosaicer(LAYOUT, raw.shape).process(corrected).copy()
    warnings = [
        w for w in (saturation_warning(sat, FS, 0), phase_warning(check_phase(corrected, LAYOUT))) if w
    ]
    if dark is not None:
        msg = low_light_warning(corrected, read_noise, LAYOUT.n)
        if msg:
            warnings.append(msg)
    return cube, cell_mask(sat, LAYOUT.n), warnings


def _random_dark(rng, high, shape=(48, 64)):
    frames = rng.integers(0, high, (3, *shape), dtype=np.uint16)
    return build_master_dark(frames, exposure_s=0.01, gain=1.0, temperature_c=25.0)


@pytest.mark.timeout(600)  # compiles the kernel on a cold numba cache
@pytest.mark.parametrize("seed", range(6))
def test_fused_equals_two_step_on_random_frames(seed):
    rng = np.random.default_rng(seed)
    # darks up to 300 DN over raw values down to 0: many negative differences, clipped at 0
    dark = _random_dark(rng, 300)
    raw = rng.integers(0, FS + 1, (48, 64), dtype=np.uint16)
    raw[rng.random(raw.shape) < 0.02] = FS  # the 10-bit maximum: saturated
    raw[rng.random(raw.shape) < 0.005] = 65535  # above full scale (a corrupt pixel) counts too
    raw[rng.random(raw.shape) < 0.05] = 0
    fp = FrameProcessor("superpixel", CAM, dark=dark)
    frame = fp.process(raw)
    cube, mask, warnings = _two_step(raw, dark, dark.read_noise_dn)
    np.testing.assert_array_equal(frame.cube, cube)
    np.testing.assert_array_equal(frame.saturated_mask, mask)
    assert frame.warnings == warnings and any("full scale" in w for w in warnings)
    assert (cube == 0).any() and mask.any()  # the clipped differences and the flags were exercised


def test_fused_clears_the_mask_and_handles_no_dark():
    rng = np.random.default_rng(7)
    fp = FrameProcessor("superpixel", CAM)
    hot = rng.integers(0, FS, (48, 64), dtype=np.uint16)
    hot[5, 7] = FS
    frame = fp.process(hot)
    assert frame.saturated_mask[1, 1] and frame.saturated_mask.sum() == 1
    cool = np.minimum(hot, FS - 1)  # the next frame: nothing clipped, the mask must clear
    frame = fp.process(cool)
    cube, mask, warnings = _two_step(cool, None)
    np.testing.assert_array_equal(frame.cube, cube)
    np.testing.assert_array_equal(frame.saturated_mask, mask)
    assert not frame.saturated_mask.any() and frame.warnings == warnings == []


def test_fused_keeps_the_qc_warnings():
    """Phase and low-light checks see the same rows of the corrected mosaic as before."""
    scene = synthetic_scene(CAM, 64, seed=3)
    cube_in = scene.cube[:, :48, :64]
    dark = build_master_dark(
        np.clip(np.rint(np.random.default_rng(9).normal(30, 3.0, (8, 48, 64))), 0, None).astype(np.uint16),
        exposure_s=0.01,
        gain=1.0,
        temperature_c=25.0,
    )
    for raw in (
        mosaic_of(cube_in + 30, LAYOUT, FS, offset=(0, 1)),  # phase error
        mosaic_of(cube_in * (10.0 / cube_in.max()) + 30, LAYOUT, FS, read_noise_dn=3.0),  # dim
    ):
        frame = FrameProcessor("superpixel", CAM, dark=dark).process(raw)
        cube, mask, warnings = _two_step(raw, dark, dark.read_noise_dn)
        np.testing.assert_array_equal(frame.cube, cube)
        np.testing.assert_array_equal(frame.saturated_mask, mask)
        assert frame.warnings == warnings and warnings


def test_process_raw_refuses_mismatched_buffers():
    sp = SuperPixelDemosaicer(LAYOUT, (48, 64))
    raw = np.zeros((48, 64), np.uint16)
    ok = np.zeros((12, 16), bool)
    with pytest.raises(FrameShapeError):
        sp.process_raw(raw, np.zeros((48, 60), np.uint16), FS, ok)
    with pytest.raises(FrameShapeError):
        sp.process_raw(raw, None, FS, np.zeros((12, 15), bool))
    with pytest.raises(FrameShapeError):
        sp.process_raw(raw, None, FS, ok, np.zeros((1, 4, 64), np.uint16))  # needs 2 QC rows
    with pytest.raises(FrameShapeError):
        sp.process_raw(raw[:, ::-1], None, FS, ok)


@pytest.mark.parametrize("seed", range(4))
def test_low_light_percentile_from_histogram_is_exact(seed):
    """uint16 mosaics take the histogram route, float ones np.partition: the same 95th percentile."""
    rng = np.random.default_rng(seed)
    mosaic = rng.integers(0, 12 + 40 * seed, (48, 64), dtype=np.uint16)
    got = low_light_warning(mosaic, 100.0, LAYOUT.n)
    assert got is not None and got == low_light_warning(mosaic.astype(np.float32), 100.0, LAYOUT.n)


@pytest.mark.parametrize("seed", range(3))
def test_low_light_fast_path_decides_as_the_percentile(seed):
    """uint16 mosaics first count the samples below the bound and compute the percentile only to
    warn: the same verdict and text as np.partition on either side of the bound and on it."""
    rng = np.random.default_rng(seed)
    mosaic = rng.integers(0, 300 + 200 * seed, (48, 64), dtype=np.uint16)
    sample = mosaic.reshape(12, 4, 16, 4)[::8, :, ::8, :].ravel()
    p95 = float(np.partition(sample, int(0.95 * (sample.size - 1)))[int(0.95 * (sample.size - 1))])
    verdicts = []
    for factor in (0.9, 0.999, 1.0, 1.001, 1.1):
        read_noise = p95 / LOW_SNR * factor
        got = low_light_warning(mosaic, read_noise, LAYOUT.n)
        assert got == low_light_warning(mosaic.astype(np.float32), read_noise, LAYOUT.n)
        verdicts.append(got is not None)
    assert verdicts == [False, False, False, True, True]  # at the bound itself: SNR = 5, no warning


@pytest.mark.parametrize(
    ("n", "shape", "row_step", "step"), [(4, (48, 64), 1, 8), (3, (27, 33), 2, 3), (5, (50, 35), 3, 1)]
)
def test_low_light_percentile_sampling_matches_partition(n, shape, row_step, step):
    """The compiled histogram samples the same cells as the strided view (any n, steps, ragged ends)."""
    mosaic = np.random.default_rng(n).integers(0, 900, shape, dtype=np.uint16)
    got = low_light_warning(mosaic, 1000.0, n, step, row_step=row_step)
    assert got is not None and got == low_light_warning(
        mosaic.astype(np.float32), 1000.0, n, step, row_step=row_step
    )


@pytest.mark.parametrize(("n", "shape", "step"), [(4, (48, 64), 8), (4, (256, 128), 1), (3, (27, 33), 2)])
def test_sublattice_stats_integer_sums_are_exact(n, shape, step):
    """uint16 mosaics are summed in int64: equal to float64 sums of the same values, also above
    4096 where the float32 squares of the generic route round."""
    mosaic = np.random.default_rng(step).integers(0, 65536, shape, dtype=np.uint16)
    mean, se = sublattice_stats(mosaic, n, step)
    rows = mosaic.reshape(shape[0] // n, n, shape[1]).astype(np.float64)[::step]
    count = rows.shape[0] * (shape[1] // n)
    s1 = rows.sum(axis=0).reshape(n, -1, n).sum(axis=1)
    s2 = (rows * rows).sum(axis=0).reshape(n, -1, n).sum(axis=1)
    assert np.array_equal(mean, s1 / count)
    assert np.array_equal(se, np.sqrt(np.maximum(s2 / count - (s1 / count) ** 2, 0.0) / count))
    small = (mosaic >> 6).astype(np.uint16)  # 10-bit values: the float route is exact too
    assert all(
        np.array_equal(a, b)
        for a, b in zip(
            sublattice_stats(small, n, step), sublattice_stats(small.astype(np.float32), n, step), strict=True
        )
    )


@pytest.mark.parametrize(
    "pattern",
    [
        [[0, 1, 2], [3, 4, 5], [6, 7, 0]],  # n = 3: the general path
        [[0, 0, 1, 2], [0, 3, 4, 5], [6, 7, 8, 9], [1, 2, 3, 4]],  # n = 4, a band on 3 positions
        [[0, 1], [1, 0]],
    ],
)
def test_process_raw_equals_two_step_for_other_layouts(pattern):
    layout = MosaicLayout.from_pattern(np.array(pattern), int(np.max(pattern)) + 1)
    n = layout.n
    rng = np.random.default_rng(n)
    shape = (12 * n, 10 * n)
    raw = rng.integers(0, FS + 1, shape, dtype=np.uint16)
    dark = rng.integers(0, 200, shape, dtype=np.uint16)
    corrected, sat = subtract_dark(raw, dark, full_scale=FS)
    expected = SuperPixelDemosaicer(layout, shape).process(corrected).copy()
    sp = SuperPixelDemosaicer(layout, shape)
    cells = np.empty(sp.out_shape[1:], bool)
    qc = np.empty((2, n, shape[1]), np.uint16)
    cube, n_sat = sp.process_raw(raw, dark, FS, cells, qc)
    np.testing.assert_array_equal(cube, expected)
    np.testing.assert_array_equal(cells, cell_mask(sat, n))
    np.testing.assert_array_equal(qc, corrected.reshape(12, n, shape[1])[::8])
    assert n_sat == int(sat.sum()) > 0


@pytest.mark.parametrize("full_scale", [0, 1, 65535, 65536])
def test_process_raw_counts_saturation_at_the_uint16_edges(full_scale):
    # the kernel tests a row's uint16 maximum first: full scales at or beyond the uint16 range
    # must still count exactly the raw pixels >= full_scale
    rng = np.random.default_rng(full_scale)
    raw = rng.integers(0, 1024, (48, 64), dtype=np.uint16)
    raw[5, 7] = 65535
    dark = rng.integers(0, 50, raw.shape, dtype=np.uint16)
    sp = SuperPixelDemosaicer(LAYOUT, raw.shape)
    cells = np.empty(sp.out_shape[1:], bool)
    cube, n_sat = sp.process_raw(raw, dark, full_scale, cells)
    sat = raw.astype(np.int64) >= full_scale
    assert n_sat == int(sat.sum())
    np.testing.assert_array_equal(cells, cell_mask(sat, LAYOUT.n))
    corrected, _ = subtract_dark(raw, dark, full_scale=FS)
    np.testing.assert_array_equal(cube, SuperPixelDemosaicer(LAYOUT, raw.shape).process(corrected))


@pytest.mark.parametrize("threads", [1, 2])
def test_process_raw_is_the_same_on_any_number_of_row_blocks(threads):
    # one block of cell rows per numba thread: the split (and the QC rows that straddle it) must not
    # show in the cube, the flags, the QC rows or the count
    from numba import get_num_threads, set_num_threads

    rng = np.random.default_rng(7)
    shape = (4 * 37, 4 * 9)  # 37 cell rows: blocks of unequal size
    raw = rng.integers(0, FS + 40, shape, dtype=np.uint16)
    dark = rng.integers(0, 200, shape, dtype=np.uint16)
    corrected, sat = subtract_dark(raw, dark, full_scale=FS)
    sp = SuperPixelDemosaicer(LAYOUT, shape)
    cells = np.empty(sp.out_shape[1:], bool)
    qc = np.empty((-(-37 // 8), 4, shape[1]), np.uint16)
    before = get_num_threads()
    set_num_threads(min(threads, before))
    try:
        cube, n_sat = sp.process_raw(raw, dark, FS, cells, qc)
    finally:
        set_num_threads(before)
    np.testing.assert_array_equal(cube, SuperPixelDemosaicer(LAYOUT, shape).process(corrected))
    np.testing.assert_array_equal(cells, cell_mask(sat, 4))
    np.testing.assert_array_equal(qc, corrected.reshape(37, 4, shape[1])[::8])
    assert n_sat == int(sat.sum()) > 0
