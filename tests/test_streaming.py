"""Streaming row stores: the copy is exact whatever the alignment, stride or length of the row,
and the kernels that use it write the same cube into any output buffer."""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit

from m2s2hil.config import CameraModel
from m2s2hil.processing.chain import FrameProcessor
from m2s2hil.processing.demosaic import get_demosaicer
from m2s2hil.processing.streaming import ALIGN, aligned_empty, store_fence, stream_copy
from m2s2hil.processing.wb import WBTables


@njit(cache=True)
def _copy(dst, src):
    stream_copy(dst, src)
    store_fence()


@pytest.mark.parametrize("n", [0, 1, 15, 16, 17, 31, 48, 100, 2048])
@pytest.mark.parametrize("offset", [0, 1, 5, 15])
def test_stream_copy_is_exact_at_any_alignment_and_length(n, offset):
    rng = np.random.default_rng(n * 31 + offset)
    src = rng.standard_normal(n).astype(np.float32)
    src[: min(n, 3)] = [np.nan, np.inf, -0.0][: min(n, 3)]  # bits, not values, are copied
    guard = aligned_empty((n + 64,))
    guard[:] = 7.0
    dst = guard[offset : offset + n]  # starts ``offset`` floats past a cache line
    _copy(dst, src)
    assert dst.view(np.uint32).tolist() == src.view(np.uint32).tolist()
    assert (guard[:offset] == 7.0).all() and (guard[offset + n :] == 7.0).all()  # nothing outside


def test_stream_copy_into_strided_and_from_strided_rows():
    src = np.arange(64, dtype=np.float32)
    wide = np.zeros(128, np.float32)
    _copy(wide[::2], src)  # a strided destination takes ordinary stores
    assert (wide[::2] == src).all() and (wide[1::2] == 0).all()
    dst = np.zeros(32, np.float32)
    _copy(dst, src[::2])  # a strided source as well
    assert (dst == src[::2]).all()


def test_aligned_empty_starts_on_a_cache_line():
    for shape in [(10, 48, 64), (3,), (1, 1), (0, 5)]:
        a = aligned_empty(shape)
        assert a.shape == shape and a.dtype == np.float32 and a.flags.c_contiguous and a.flags.writeable
        assert a.size == 0 or a.ctypes.data % ALIGN == 0  # an empty array has no data to align
    assert aligned_empty((4, 4), np.uint16).dtype == np.uint16


def test_demosaicers_own_aligned_cubes():
    cam = CameraModel(width=64, height=48)
    for method in ("superpixel", "nearest", "wb", "ppid"):
        assert get_demosaicer(method, cam, (48, 64)).out.ctypes.data % ALIGN == 0


@pytest.mark.parametrize("offset", [0, 1, 3])
def test_wb_kernel_writes_the_same_cube_into_any_buffer(offset):
    """Rows that do not start on a cache line (an output of the caller's, offset by a few floats,
    and a width that is not a multiple of 16) get the same values as the demosaicer's own cube."""
    cam = CameraModel(width=72, height=48)
    rng = np.random.default_rng(offset)
    mosaic = rng.integers(0, 1024, (48, 72), dtype=np.uint16)
    d = get_demosaicer("wb", cam, mosaic.shape)
    ref = d.process(mosaic).copy()
    flat = aligned_empty((ref.size + 16,))
    out = flat[offset : offset + ref.size].reshape(ref.shape)
    out[:] = np.nan
    t = WBTables(d.layout, mosaic.shape[1])
    t.run(mosaic, out, 4)
    np.testing.assert_array_equal(out, ref)


def test_superpixel_cube_matches_its_definition_with_streamed_rows():
    """The fused super-pixel path streams its rows; its cube is still each band's mean of its
    cell positions (a 2048-wide frame: rows of 512 floats, all on cache lines)."""
    cam = CameraModel(width=2048, height=64)
    rng = np.random.default_rng(5)
    raw = rng.integers(0, 1024, (64, 2048), dtype=np.uint16)
    fp = FrameProcessor("superpixel", cam)
    cube = fp.process(raw).cube
    lay = fp.layout
    for b, ps in enumerate(lay.positions):
        want = np.mean([raw[r :: lay.n, c :: lay.n].astype(np.float32) for r, c in ps], axis=0)
        np.testing.assert_allclose(cube[b], want, rtol=0, atol=1e-4)
