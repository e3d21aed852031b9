"""Calibration: crosstalk correction and white-reference normalisation invert known distortions."""

from __future__ import annotations

import json

import numpy as np
import pytest

from m2s2hil.config import CameraModel
from m2s2hil.errors import UsageError
from m2s2hil.processing.calibration import (
    CalibrationStep,
    CameraCalibration,
    load_calibration,
    save_calibration,
)
from m2s2hil.processing.chain import FrameProcessor
from m2s2hil.processing.demosaic import get_demosaicer
from m2s2hil.processing.errors import CalibrationError
from m2s2hil.processing.mosaic import MosaicLayout, sample_cube

# 16-bit so that quantising the synthetic raw frames costs < 1e-4 relative
CAM = CameraModel(width=64, height=64, bit_depth=16)
LAYOUT = MosaicLayout.from_camera(CAM)
NB = CAM.n_bands


def mixing_matrix(seed: int = 0) -> np.ndarray:
    """A plausible crosstalk matrix: 1 on the diagonal, a few % leaking from the neighbouring bands."""
    rng = np.random.default_rng(seed)
    m = np.eye(NB)
    for b in range(NB):
        for d in (-2, -1, 1, 2):
            if 0 <= b + d < NB:
                m[b, b + d] = rng.uniform(0.01, 0.06) / abs(d)
    return m


def mix(m: np.ndarray, cube: np.ndarray) -> np.ndarray:
    return np.einsum("bj,jyx->byx", m, cube)


def test_crosstalk_correction_inverts_the_mixing():
    rng = np.random.default_rng(1)
    true = rng.uniform(10, 1000, (NB, 16, 24)).astype(np.float32)
    m = mixing_matrix()
    measured = mix(m, true).astype(np.float32)
    assert np.abs(measured - true).max() > 5  # the distortion is real
    step = CalibrationStep(CameraCalibration(crosstalk=m), get_demosaicer("wb", LAYOUT, (16, 24)))
    got = step.apply(measured.copy())
    np.testing.assert_allclose(got, true, rtol=1e-5)


def white_setup(shape, *, cell_field: bool, uniform: bool, seed: int = 2):
    """measured = M·(F·E·ρ), white = M·(F·E·ρ_w): reflectance ρ, a band-independent light/vignetting
    field F (linear, or constant per 4×4 cell), a per-band illuminant E, the white panel's ρ_w."""
    rng = np.random.default_rng(seed)
    h, w = shape
    if uniform:
        rho = np.broadcast_to(rng.uniform(0.05, 0.95, NB)[:, None, None], (NB, h, w))
    else:
        rho = np.repeat(np.repeat(rng.uniform(0.05, 0.95, (NB, h // 4, w // 4)), 4, axis=1), 4, axis=2)
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    field = 0.55 + 0.3 * xx + 0.15 * yy
    if cell_field:
        field = np.repeat(np.repeat(field[::4, ::4], 4, axis=0), 4, axis=1)
    illum = np.linspace(0.4, 1.0, NB)[:, None, None]
    rho_w = np.full(NB, 0.95)
    scene = 60000.0 * field[None] * illum * rho
    white = 60000.0 * field[None] * illum * rho_w[:, None, None]
    return rho, rho_w, scene, white


@pytest.mark.parametrize("with_crosstalk", [False, True])
def test_white_reference_returns_reflectance_superpixel(with_crosstalk):
    # super-pixel averages a band over its positions in the cell: exact when F is constant per cell
    rho, rho_w, scene, white = white_setup((64, 64), cell_field=True, uniform=False)
    m = mixing_matrix(3) if with_crosstalk else np.eye(NB)
    raw = sample_cube(mix(m, scene), LAYOUT, full_scale=CAM.full_scale)
    calib = CameraCalibration(
        crosstalk=m if with_crosstalk else None,
        white_mosaic=sample_cube(mix(m, white), LAYOUT, dtype=None),
        white_reflectance=rho_w,
    )
    frame = FrameProcessor("superpixel", CAM, calibration=calib).process(raw)
    np.testing.assert_allclose(frame.cube, rho[:, ::4, ::4], rtol=0, atol=1e-4)  # 0.5 DN rounding ≈ 4e-5
    uncorrected = FrameProcessor("superpixel", CAM).process(raw).cube
    assert np.abs(uncorrected / 60000.0 - rho[:, ::4, ::4]).max() > 0.05


@pytest.mark.parametrize("with_crosstalk", [False, True])
def test_white_reference_returns_reflectance_wb(with_crosstalk):
    # full resolution: a uniform reflectance under a linear field keeps every band linear, which WB
    # reproduces exactly away from the border
    rho, rho_w, scene, white = white_setup((64, 64), cell_field=False, uniform=True)
    m = mixing_matrix(4) if with_crosstalk else np.eye(NB)
    raw = sample_cube(mix(m, scene), LAYOUT, full_scale=CAM.full_scale)
    calib = CameraCalibration(
        crosstalk=m if with_crosstalk else None,
        white_mosaic=sample_cube(mix(m, white), LAYOUT, dtype=None),
        white_reflectance=rho_w,
    )
    cube = FrameProcessor("wb", CAM, calibration=calib).process(raw).cube
    b = 12
    np.testing.assert_allclose(cube[:, b:-b, b:-b], rho[:, b:-b, b:-b], rtol=0, atol=1e-4)
    uncorrected = FrameProcessor("wb", CAM).process(raw).cube
    assert np.abs(uncorrected[:, b:-b, b:-b] / 60000.0 - rho[:, b:-b, b:-b]).max() > 0.05


def test_calibration_file_round_trip(tmp_path):
    rng = np.random.default_rng(5)
    white = rng.uniform(100, 1000, (64, 64)).astype(np.float32)
    layout = [[3, 1, 2, 0], [4, 5, 6, 7], [8, 9, 0, 1], [2, 3, 4, 5]]
    calib = CameraCalibration(
        camera_serial="TOUCAN-7",
        layout=tuple(map(tuple, layout)),
        crosstalk=mixing_matrix(),
        white_mosaic=white,
        white_reflectance=np.full(NB, 0.98),
    )
    path = save_calibration(tmp_path / "cal" / "toucan.json", calib, bands_nm=list(CAM.bands_nm))
    got = load_calibration(path, CAM)
    assert got.camera_serial == "TOUCAN-7" and got.layout == tuple(map(tuple, layout))
    np.testing.assert_allclose(got.crosstalk, calib.crosstalk)
    np.testing.assert_array_equal(got.white_mosaic, white)
    np.testing.assert_allclose(got.white_reflectance, 0.98)
    fp = FrameProcessor("superpixel", CAM, calibration=got)
    assert fp.layout.pattern == tuple(map(tuple, layout))  # the calibration file's layout wins
    assert fp.info["calibration"]["camera_serial"] == "TOUCAN-7"
    ppid = FrameProcessor("ppid", CAM, calibration=got).demosaicer
    assert not ppid.balance  # PPID balances its bands with the white reference's levels, not per frame


def _write(tmp_path, doc) -> str:
    p = tmp_path / "cal.json"
    p.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return str(p)


@pytest.mark.parametrize(
    "doc, key",
    [
        ("{not json", ""),
        ({"format": "vendor-xml"}, "format"),
        ({"format": "m2s2hil-calibration/1", "colour": 1}, "colour"),
        ({"format": "m2s2hil-calibration/1", "bands_nm": [431, 479]}, "bands_nm"),
        ({"format": "m2s2hil-calibration/1", "layout": [[0, 1], [1, 0]]}, "layout"),
        ({"format": "m2s2hil-calibration/1", "crosstalk": [[1, 0], [0, 1]]}, "crosstalk"),
        ({"format": "m2s2hil-calibration/1", "crosstalk": np.ones((10, 10)).tolist()}, "crosstalk"),
        (
            {"format": "m2s2hil-calibration/1", "white_reference": {"file": "nope.tiff"}},
            "white_reference.file",
        ),
        ({"format": "m2s2hil-calibration/1", "white_reference": "white.tiff"}, "white_reference"),
    ],
)
def test_bad_calibration_files_are_typed_errors(tmp_path, doc, key):
    with pytest.raises(CalibrationError) as info:
        load_calibration(_write(tmp_path, doc), CAM)
    assert info.value.key == key
    assert isinstance(info.value, UsageError)
    assert "cal.json" in str(info.value)


def test_missing_file_and_bad_white(tmp_path):
    with pytest.raises(CalibrationError, match="no such file"):
        load_calibration(tmp_path / "absent.json", CAM)
    calib = CameraCalibration(white_mosaic=np.ones((64, 64), np.float32), white_reflectance=np.ones(NB))
    path = save_calibration(tmp_path / "c.json", calib)
    doc = json.loads(path.read_text())
    doc["white_reference"]["reflectance"] = 3.0
    (tmp_path / "r.json").write_text(json.dumps(doc))
    with pytest.raises(CalibrationError) as info:
        load_calibration(tmp_path / "r.json", CAM)
    assert info.value.key == "white_reference.reflectance"
    tif = tmp_path / "c_white.tiff"
    tif.write_bytes(tif.read_bytes()[:-8] + b"\0" * 8)
    with pytest.raises(CalibrationError, match="checksum"):
        load_calibration(path, CAM)
    path = save_calibration(
        tmp_path / "s.json", CameraCalibration(white_mosaic=np.ones((32, 32), np.float32))
    )
    with pytest.raises(CalibrationError, match="sensor is 64×64"):
        load_calibration(path, CAM)
