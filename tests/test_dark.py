"""Dark frames: the exact I = max(R − D, 0) step, master darks and the on-disk dark library."""

from __future__ import annotations

import json
from datetime import UTC, datetime

import numpy as np
import pytest

from m2s2hil.errors import M2S2Error
from m2s2hil.processing.dark import DarkLibrary, MasterDark, build_master_dark, subtract_dark
from m2s2hil.processing.errors import (
    DarkLibraryError,
    DarkMismatchError,
    DarkNotFoundError,
    FrameShapeError,
    ProcessingError,
)

FS = 1023


def test_subtract_dark_edge_values_exact():
    raw = np.array([[0, 0, 1023, 1023, 500, 7], [65535, 1, 1022, 300, 300, 0]], dtype=np.uint16)
    dark = np.array([[0, 9, 0, 1023, 600, 7], [0, 65535, 5, 299, 301, 0]], dtype=np.uint16)
    out, sat = subtract_dark(raw, dark, full_scale=FS)
    expected = np.maximum(raw.astype(np.int64) - dark.astype(np.int64), 0)
    assert out.dtype == np.uint16
    np.testing.assert_array_equal(out, expected)
    # dark above raw clips to 0 rather than wrapping round to 65535-something
    assert out[0, 1] == 0 and out[0, 4] == 0 and out[1, 1] == 0 and out[1, 4] == 0
    # saturation flags the RAW value at (or above) full scale, even where the dark removes some of it
    np.testing.assert_array_equal(sat, raw >= FS)
    assert sat.dtype == np.bool_ and sat[0, 2] and sat[0, 3] and sat[1, 0] and not sat[1, 2]


def test_subtract_dark_reuses_buffers_and_accepts_master_dark():
    rng = np.random.default_rng(1)
    raw = rng.integers(0, 1024, (8, 12), dtype=np.uint16)
    d = build_master_dark(
        [rng.integers(0, 50, (8, 12), dtype=np.uint16)], exposure_s=0.01, gain=1, temperature_c=20
    )
    out = np.full((8, 12), 999, np.uint16)
    mask = np.ones((8, 12), bool)
    got, got_mask = subtract_dark(raw, d, out=out, sat_mask_out=mask, full_scale=FS)
    assert got is out and got_mask is mask
    np.testing.assert_array_equal(out, np.clip(raw.astype(int) - d.data.astype(int), 0, None))
    np.testing.assert_array_equal(mask, raw >= FS)


@pytest.mark.parametrize(
    "raw, dark",
    [
        (np.zeros((4, 4), np.int32), np.zeros((4, 4), np.uint16)),
        (np.zeros((4, 4), np.uint16), np.zeros((4, 5), np.uint16)),
        (np.zeros((4, 4), np.uint16), np.zeros((4, 4), np.float32)),
        (np.zeros((2, 4, 4), np.uint16), np.zeros((2, 4, 4), np.uint16)),
    ],
)
def test_subtract_dark_rejects_bad_frames(raw, dark):
    with pytest.raises(FrameShapeError):
        subtract_dark(raw, dark, full_scale=FS)


def test_master_dark_mean_and_median():
    frames = np.array([[[1, 10]], [[2, 10]], [[6, 40]]], dtype=np.uint16)
    mean = build_master_dark(
        frames, exposure_s=0.1, gain=2.0, temperature_c=[25.0, 25.5, 26.0], camera="SN42"
    )
    med = build_master_dark(frames, reduce="median", exposure_s=0.1, gain=2.0, temperature_c=25.0)
    np.testing.assert_array_equal(mean.data, [[3, 20]])
    np.testing.assert_array_equal(med.data, [[2, 10]])
    assert mean.data.dtype == np.uint16
    assert mean.n_frames == 3 and mean.camera_serial == "SN42" and mean.reduce == "mean"
    assert mean.temperature_c == pytest.approx(25.5) and mean.temperature_spread_c == pytest.approx(1.0)
    assert med.reduce == "median"
    datetime.fromisoformat(mean.created)  # ISO 8601


def test_master_dark_read_noise_and_noise_reduction():
    rng = np.random.default_rng(7)
    frames = np.clip(np.rint(rng.normal(100.0, 3.0, (16, 64, 64))), 0, None).astype(np.uint16)
    d = build_master_dark(frames, exposure_s=1.0, gain=1.0, temperature_c=20.0)
    assert d.read_noise_dn == pytest.approx(3.0, rel=0.1)
    # averaging 16 frames: the master's own noise is ~3/4 DN (plus rounding), far below one frame's
    assert np.std(d.data.astype(float)) < 1.2


def test_master_dark_refuses_bad_series():
    ok = np.zeros((2, 4, 4), np.uint16)
    with pytest.raises(DarkMismatchError, match="span"):
        build_master_dark(ok, exposure_s=1, gain=1, temperature_c=[20.0, 23.5], tolerance_c=2.0)
    with pytest.raises(ProcessingError):
        build_master_dark([], exposure_s=1, gain=1, temperature_c=20)
    with pytest.raises(FrameShapeError):
        build_master_dark(
            [np.zeros((4, 4), np.uint16), np.zeros((4, 5), np.uint16)], exposure_s=1, gain=1, temperature_c=20
        )
    with pytest.raises(FrameShapeError):
        build_master_dark(np.zeros((2, 4, 4), np.float32), exposure_s=1, gain=1, temperature_c=20)
    with pytest.raises(ProcessingError):
        build_master_dark(ok, reduce="max", exposure_s=1, gain=1, temperature_c=20)  # type: ignore[arg-type]


def _dark(value: int, *, exposure=0.01, gain=1.0, temp=25.0, when="2026-11-24T10:00:00+00:00") -> MasterDark:
    return build_master_dark(
        np.full((2, 8, 8), value, np.uint16),
        exposure_s=exposure,
        gain=gain,
        temperature_c=temp,
        camera="TOUCAN-1",
        created=datetime.fromisoformat(when).astimezone(UTC),
    )


def test_library_round_trip_and_selection(tmp_path):
    lib = DarkLibrary(tmp_path / "darks")
    lib.put(_dark(10, temp=20.0))
    lib.put(_dark(11, temp=25.5))
    lib.put(_dark(12, temp=25.5, when="2026-11-24T12:00:00+00:00"))  # newer, same temperature
    lib.put(_dark(13, exposure=0.02, temp=25.0))
    lib.put(_dark(14, gain=4.0, temp=25.0))
    got = lib.get(0.01, 1.0, 25.0)
    assert int(got.data[0, 0]) == 12  # closest temperature, newest of the tie
    assert (
        got.exposure_s == 0.01 and got.gain == 1.0 and got.n_frames == 2 and got.camera_serial == "TOUCAN-1"
    )
    assert got.created == "2026-11-24T12:00:00+00:00"
    assert int(lib.get(0.02, 1.0, 26.0).data[0, 0]) == 13
    assert int(lib.get(0.01, 4.0, 24.0).data[0, 0]) == 14
    assert int(lib.get(0.01, 1.0, 21.0).data[0, 0]) == 10
    assert len(lib.entries()) == 5


@pytest.mark.parametrize(
    "request_, problem",
    [((0.05, 1.0, 25.0), "exposure"), ((0.01, 2.0, 25.0), "gain"), ((0.01, 1.0, 30.0), "temperature")],
)
def test_library_mismatch_is_an_error_unless_allowed(tmp_path, request_, problem):
    lib = DarkLibrary(tmp_path)
    lib.put(_dark(10, temp=25.0))
    with pytest.raises(DarkMismatchError, match=problem) as info:
        lib.get(*request_)
    assert isinstance(info.value, M2S2Error)
    assert info.value.available and info.value.wanted["exposure_s"] == request_[0]
    d = lib.get(*request_, allow_mismatch=True)
    assert int(d.data[0, 0]) == 10  # the closest one, its provenance says what it really is
    assert d.mismatch(*request_, 2.0)


def test_library_tolerance_is_honoured(tmp_path):
    lib = DarkLibrary(tmp_path)
    lib.put(_dark(10, temp=25.0))
    assert int(lib.get(0.01, 1.0, 26.9, tolerance_c=2.0).data[0, 0]) == 10
    with pytest.raises(DarkMismatchError):
        lib.get(0.01, 1.0, 26.9, tolerance_c=1.0)


def test_library_empty_and_damaged(tmp_path):
    lib = DarkLibrary(tmp_path)
    with pytest.raises(DarkNotFoundError):
        lib.get(0.01, 1.0, 25.0)
    tif = lib.put(_dark(10))
    blob = bytearray(tif.read_bytes())
    blob[-1] ^= 0xFF
    tif.write_bytes(bytes(blob))
    with pytest.raises(DarkLibraryError, match="checksum"):
        lib.get(0.01, 1.0, 25.0)
    side = tif.with_suffix(".json")
    side.write_text(json.dumps({"format": "something-else"}))
    with pytest.raises(DarkLibraryError, match="format"):
        lib.get(0.01, 1.0, 25.0)


def test_subtract_dark_in_place():
    raw = np.array([[5, 1023, 0, 40]], dtype=np.uint16)
    dark = np.array([[7, 3, 0, 10]], dtype=np.uint16)
    out, sat = subtract_dark(raw, dark, out=raw, full_scale=FS)
    assert out is raw
    np.testing.assert_array_equal(raw, [[0, 1020, 0, 30]])
    np.testing.assert_array_equal(sat, [[False, True, False, False]])  # flagged from the raw value
    with pytest.raises(FrameShapeError, match="dark"):
        subtract_dark(raw, dark, out=dark, full_scale=FS)


def test_master_dark_is_hashed_once_and_cannot_change_after():
    """The digest goes into every corrected frame's metadata: computed once, from pixels that
    can no longer be edited in place (an edit would make every later frame's record wrong)."""
    import hashlib

    frames = [np.full((8, 8), v, np.uint16) for v in (10, 12)]
    md = build_master_dark(frames, exposure_s=0.01, gain=1.0, temperature_c=25.0)
    prov = md.provenance()
    assert prov["sha256"] == hashlib.sha256(np.ascontiguousarray(md.data).tobytes()).hexdigest()
    assert "data" not in prov and prov["shape"] == [8, 8] and prov["n_frames"] == 2
    with pytest.raises(ValueError, match="read-only"):
        md.data[0, 0] = 99
    assert md.provenance() == prov
