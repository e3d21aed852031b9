"""The frame processor end to end, the quality metrics' conventions, ground truth and the bench command."""

from __future__ import annotations

import numpy as np
import pytest

from m2s2hil.config import CameraModel
from m2s2hil.processing.chain import FrameProcessor
from m2s2hil.processing.dark import build_master_dark, subtract_dark
from m2s2hil.processing.demosaic import get_demosaicer
from m2s2hil.processing.errors import FrameShapeError, UnknownMethodError
from m2s2hil.processing.groundtruth import mosaic_of, synthetic_scene
from m2s2hil.processing.image_quality import Quality, evaluate, psnr_per_band, sam_deg, ssim_per_band
from m2s2hil.processing.mosaic import MosaicLayout

CAM = CameraModel(width=64, height=48)
LAYOUT = MosaicLayout.from_camera(CAM)


@pytest.mark.timeout(600)  # compiles the kernels on a cold numba cache (CI): minutes under load
def test_frame_processor_is_dark_then_demosaic():
    rng = np.random.default_rng(0)
    dark = build_master_dark(
        rng.integers(0, 60, (3, 48, 64), dtype=np.uint16),
        exposure_s=0.02,
        gain=1.0,
        temperature_c=24.0,
        camera="TOUCAN-3",
    )
    raw = rng.integers(0, 1024, (48, 64), dtype=np.uint16)
    fp = FrameProcessor("wb", CAM, dark=dark)
    frame = fp.process(raw)
    corrected, _ = subtract_dark(raw, dark, full_scale=CAM.full_scale)
    expected = get_demosaicer("wb", LAYOUT, raw.shape).process(corrected)
    np.testing.assert_array_equal(frame.cube, expected)
    assert frame.info["method"] == "wb" and frame.info["dark"]["camera_serial"] == "TOUCAN-3"
    assert frame.info["dark"]["sha256"] == dark.sha256()
    again = fp.process(raw[::-1].copy())
    assert again.cube is frame.cube  # preallocated and reused


def test_frame_processor_refuses_bad_input():
    with pytest.raises(UnknownMethodError):
        FrameProcessor("magic", CAM)
    with pytest.raises(FrameShapeError):
        FrameProcessor(
            "wb",
            CAM,
            dark=build_master_dark(np.zeros((1, 8, 8), np.uint16), exposure_s=1, gain=1, temperature_c=20),
        )
    fp = FrameProcessor("superpixel", CAM)
    with pytest.raises(FrameShapeError):
        fp.process(np.zeros((48, 64), np.float32))
    with pytest.raises(FrameShapeError):
        fp.process(np.zeros((64, 48), np.uint16))


def test_metric_conventions():
    rng = np.random.default_rng(1)
    ref = rng.uniform(10, 1000, (10, 40, 40))
    # PSNR with the full-scale peak, averaged over bands
    assert psnr_per_band(ref + 1.0, ref, peak=1023) == pytest.approx(np.full(10, 20 * np.log10(1023)))
    est = ref.copy()
    est[0] += 2.0  # band 0 only: MSE 4 there, 0 elsewhere -> inf
    p = psnr_per_band(est, ref, peak=1023)
    assert p[0] == pytest.approx(20 * np.log10(1023 / 2)) and np.isinf(p[1:]).all()
    # SAM: scale-free, 90° for orthogonal spectra, all-zero pixels left out
    assert sam_deg(3.0 * ref, ref) == pytest.approx(0.0, abs=1e-5)
    a = np.zeros((2, 1, 3))
    b = np.zeros((2, 1, 3))
    a[0, 0, 0], b[1, 0, 0] = 1.0, 1.0  # orthogonal
    a[:, 0, 1], b[:, 0, 1] = 1.0, 1.0  # identical
    assert sam_deg(a, b) == pytest.approx(45.0)  # pixel 2 is all zero: ignored
    # SSIM 1 on identical bands; the border is cut before anything is computed
    assert ssim_per_band(ref, ref, peak=1023) == pytest.approx(np.ones(10))
    spoiled = ref.copy()
    spoiled[:, :3] = 0
    assert evaluate(spoiled, ref, peak=1023, border=3).psnr_db == np.inf
    q = Quality.mean(
        [evaluate(ref + 1, ref, peak=1023, border=0), evaluate(ref + 2, ref, peak=1023, border=0)]
    )
    assert q.psnr_db == pytest.approx((20 * np.log10(1023) + 20 * np.log10(1023 / 2)) / 2)


def test_ground_truth_spectra_reach_the_near_infrared():
    from m2s2hil.processing import groundtruth as gt

    wl = gt.WAVELENGTHS
    srf = gt.band_responses(CameraModel())
    assert srf.shape == (10, len(wl)) and np.allclose(srf.sum(axis=1), 1.0)
    assert wl[np.argmax(srf[9])] == 877.0
    earth, names = gt.earthlib_spectra()
    assert "canopy" in names
    veg = earth[names.index("canopy")]
    nir, red = np.searchsorted(wl, 850), np.searchsorted(wl, 670)
    assert veg[nir] > 2 * veg[red]  # the vegetation red edge: measured, not extrapolated
    cc, _ = gt.colorchecker_spectra()
    assert np.allclose(cc[:, np.searchsorted(wl, 800) :], cc[:, [np.searchsorted(wl, 780)]])  # held constant
    scene = gt.colorchecker_scene(CameraModel(), "astronaut", size=64)
    assert scene.cube.shape == (10, 64, 64) and scene.cube.max() == pytest.approx(0.9 * 1023, rel=1e-5)
    assert scene.cube.min() >= 0


@pytest.mark.timeout(600)  # compiles the kernels on a cold numba cache (CI): minutes under load
def test_bench_command_prints_the_table_and_writes_the_chart(tmp_path):
    from importlib import resources

    import typer
    from typer.testing import CliRunner

    from m2s2hil.commands.bench import app

    toml = resources.files("m2s2hil").joinpath("data/default_rig.toml").read_text()
    rig = tmp_path / "small.toml"
    rig.write_text(toml.replace("width = 2048", "width = 128").replace("height = 2048", "height = 128"))
    root = typer.Typer()
    root.add_typer(app, name="bench")
    chart = tmp_path / "chart.png"
    res = CliRunner().invoke(
        root,
        [
            "bench",
            "demosaic",
            "--rig",
            str(rig),
            "--scenes",
            "synthetic",
            "--frames",
            "2",
            "--rounds",
            "1",
            "--chart",
            str(chart),
            "--markdown",
        ],
    )
    assert res.exit_code == 0, res.output
    for m in ("superpixel", "nearest", "wb", "ppid"):
        assert f"| {m} |" in res.output
    assert chart.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    bad = CliRunner().invoke(root, ["bench", "demosaic", "--methods", "wb,magic", "--rig", str(rig)])
    assert bad.exit_code != 0 and "magic" in str(bad.exception)


def test_accuracy_harness_takes_any_cube_mosaic_pair():
    from m2s2hil.processing.bench import measure_accuracy

    scene = synthetic_scene(CAM, 48, seed=5)
    res = measure_accuracy(LAYOUT, CAM.full_scale, [scene], ["nearest", "wb", "ppid"], ssim=False)
    psnr = {m: q.psnr_db for m, (q, _) in res.items()}
    assert psnr["wb"] > psnr["nearest"]  # the literature's order holds on this scene
    assert all(np.isfinite(list(psnr.values())))
    mos = mosaic_of(scene.cube, LAYOUT, CAM.full_scale)
    assert mos.dtype == np.uint16 and mos.max() <= CAM.full_scale


def test_thread_cap_gives_the_same_frame():
    import numba

    raw = np.random.default_rng(2).integers(0, 1024, (48, 64), dtype=np.uint16)
    capped = FrameProcessor("ppid", CAM, threads=1)
    a = capped.process(raw).cube.copy()
    assert numba.get_num_threads() == numba.config.NUMBA_NUM_THREADS  # restored after the call
    np.testing.assert_array_equal(a, FrameProcessor("ppid", CAM).process(raw).cube)
    from m2s2hil.processing.errors import ProcessingError

    with pytest.raises(ProcessingError):
        FrameProcessor("wb", CAM, threads=0)
