"""Clipping masks in the evaluation: a stored cube's mask rebuilt from its raw frame, given to the
segmenters that take it, to label mTC (shifted with the cube) and to the sweep fit (issue 23)."""

from __future__ import annotations

import csv
import hashlib
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from cli_support import run_cli

from m2s2hil.analysis.evaluation.evaluate import evaluate_job
from m2s2hil.analysis.evaluation.jobs import FileRef, collect_jobs
from m2s2hil.analysis.evaluation.loading import load_dark, load_frame, load_truth
from m2s2hil.analysis.evaluation.options import EvalOptions
from m2s2hil.analysis.evaluation.sweeps import fit_sweep
from m2s2hil.analysis.metrics.scores import score_clusters
from m2s2hil.analysis.segmenters.registry import register_segmenter
from m2s2hil.analysis.segmenters.spectral import SpectralSegmenter
from m2s2hil.analysis.segmenters.sweep import SweepSegmenter
from m2s2hil.analysis.study.stability import simulate_session
from m2s2hil.config import CameraModel
from m2s2hil.processing.chain import FrameProcessor
from m2s2hil.processing.stability import cube_saturation
from m2s2hil.store.frame_files import decode_tiff


@pytest.fixture(scope="module")
def jobs(tmp_path_factory):
    """Voyager B2 under the strong LED bars at 50 ms: its bright materials clip (about 1.5 s)."""
    root = tmp_path_factory.mktemp("sessions")
    path = simulate_session(root, satellite="voyager", build="B2", lighting=("strong",), tilts=("E0",),
                            azimuth_step_deg=180.0, exposure={"strong": 0.05}, size=128,
                            session_id="sim-clipped", store_cubes=True)
    found, _ = collect_jobs(path)
    assert len(found) == 2 and all(j.cube is not None and j.raw is not None for j in found)
    return found


class Probe:
    """Records the masks it is given; labels the foreground as one segment."""

    name = "probe"

    def __init__(self) -> None:
        self.masks: list[np.ndarray | None] = []

    def segment(self, cube: np.ndarray, *, saturated: np.ndarray | None = None) -> np.ndarray:
        self.masks.append(saturated)
        return (cube.sum(axis=0) > 0).astype(np.int64)


class Plain:
    """A segmenter of the plain protocol (no ``saturated``), as a lab may register one."""

    name = "plain"

    def segment(self, cube: np.ndarray) -> np.ndarray:
        return (cube.sum(axis=0) > 0).astype(np.int64)


def test_a_stored_cubes_mask_is_rebuilt_from_its_raw_frame_as_the_processor_gave_it(jobs):
    for job in jobs:
        stored = load_frame(job)  # the stored cube; its mask from the raw frame
        processed = load_frame(job, reprocess=job.method)  # the raw through the processor again
        raw = decode_tiff(open(job.raw.path, "rb").read())[0]  # noqa: SIM115
        at_capture = FrameProcessor(job.method, CameraModel.model_validate(job.camera), dark=load_dark(job))
        given = at_capture.process(raw).saturated_mask
        assert stored.mask_error is None and stored.saturated is not None
        assert stored.saturated.shape == stored.cube.shape  # which bands, per pixel
        np.testing.assert_array_equal(stored.saturated.any(axis=0), given)  # the processor's, pixel by pixel
        assert 0.05 < stored.clipped_fraction < 0.6  # clipped, not everywhere
        per_band = stored.saturated.mean(axis=(1, 2))
        assert per_band.min() < 0.5 * per_band.max()  # some bands clip far more often than others
        np.testing.assert_array_equal(stored.saturated, processed.saturated)
        np.testing.assert_array_equal(stored.cube, processed.cube)
        # reprocessed at full resolution: the raw mask spread by that method's support
        wb = load_frame(job, reprocess="wb")
        np.testing.assert_array_equal(wb.saturated_pixels, cube_saturation(raw >= 1023, "wb", 4))
        assert wb.saturated.shape[1:] == raw.shape and wb.clipped_fraction > stored.clipped_fraction
        assert load_frame(job, masks=False).saturated is None


def test_segmenters_that_take_the_mask_get_it_and_score_as_given_it(jobs):
    probe = Probe()
    register_segmenter("probe-masks", lambda **_: probe, replace=True)
    register_segmenter("plain-masks", lambda **_: Plain(), replace=True)
    job = jobs[0]
    frame = load_frame(job)
    truth = load_truth(job, frame.cube.shape[1:])
    options = EvalOptions(extra=("probe-masks", "plain-masks"), mtc_for="none")
    rec = evaluate_job(job, options)
    assert rec["error"] is None and rec["clipped_fraction"] == pytest.approx(frame.clipped_fraction)
    np.testing.assert_array_equal(probe.masks[-1], frame.saturated)
    assert "errors" not in rec["results"]["plain-masks"]  # called with the cube alone
    # the default segmenter's scores are its own on the cube with that mask, and differ without it
    with_mask = SpectralSegmenter().segment(frame.cube, saturated=frame.saturated)
    assert rec["results"]["spectral"]["dice"] == pytest.approx(score_clusters(truth, with_mask)[0].macro_dice)
    off = evaluate_job(job, replace(options, clip_masks=False))
    assert probe.masks[-1] is None and off["clipped_fraction"] is None
    alone = SpectralSegmenter().segment(frame.cube)
    assert off["results"]["spectral"]["dice"] == pytest.approx(score_clusters(truth, alone)[0].macro_dice)
    assert not np.array_equal(with_mask, alone)  # the mask is not a no-op on this frame
    # the RGB baseline takes no mask: its scores are the same with and without
    assert rec["results"]["rgb"]["dice"] == pytest.approx(off["results"]["rgb"]["dice"])


def test_label_mtc_gets_the_mask_shifted_with_the_cube(jobs):
    probe = Probe()
    register_segmenter("probe-mtc", lambda **_: probe, replace=True)
    rec = evaluate_job(jobs[1], EvalOptions(extra=("probe-mtc",), mtc_for="all"))
    frame = load_frame(jobs[1])
    assert len(probe.masks) == 1 + 1 + 8  # the image, mTC's base and its eight shifts
    np.testing.assert_array_equal(probe.masks[1], frame.saturated)
    assert all(m is not None and m.sum() == frame.saturated.sum() for m in probe.masks[2:])
    assert any(not np.array_equal(m, frame.saturated) for m in probe.masks[2:])
    assert rec["results"]["probe-mtc"]["mtc"] == pytest.approx(1.0)


def test_a_raw_frame_that_fails_its_check_leaves_the_mask_out_not_the_image(jobs, tmp_path):
    bad = tmp_path / "raw.tif"
    bad.write_bytes(b"not a tiff")
    job = replace(jobs[0], raw=FileRef(str(bad), hashlib.sha256(b"another file").hexdigest()))
    rec = evaluate_job(job, EvalOptions(mtc_for="none"))
    assert rec["error"] is None and rec["clipped_fraction"] is None
    assert "sha256 does not match" in rec["mask_error"]
    assert 0.0 <= rec["results"]["spectral"]["dice"] <= 1.0


def test_the_sweep_fit_takes_each_frames_mask(jobs):
    options = EvalOptions(multi="spectral-sweep", mtc_for="none")
    model = fit_sweep(("spectral-sweep", jobs), options)
    frames = [load_frame(j) for j in jobs]
    direct = SweepSegmenter().fit([f.cube for f in frames], saturated=[f.saturated for f in frames])
    unmasked = SweepSegmenter().fit([f.cube for f in frames])
    assert model.rows == direct.rows and model.n_components == direct.n_components
    np.testing.assert_allclose(model.mixture.means_, direct.mixture.means_)
    assert unmasked.rows != direct.rows  # the masks took clipped cells out of the pool
    plain = fit_sweep(("spectral-sweep", jobs), replace(options, clip_masks=False))
    assert plain.rows == unmasked.rows
    rgb = fit_sweep(("rgb-sweep", jobs), options)  # the RGB sweep takes no mask, and still fits
    assert not isinstance(rgb, str), rgb


@pytest.mark.slow  # two evaluations through the CLI (a few seconds)
def test_cli_reports_the_clipped_share_and_can_leave_the_masks_out(jobs, tmp_path):
    session = str(Path(jobs[0].raw.path).parents[1])
    for flag, want in (((), True), (("--no-clip-masks",), False)):
        out = tmp_path / f"ev{want}"
        res = run_cli("evaluate", session, "--out", out, "--workers", "0", "--mtc", "none", *flag)
        assert res.exit_code == 0, res.output
        assert json.loads((out / "summary.json").read_text())["options"]["clip_masks"] is want
        rows = list(csv.DictReader((out / "per_image.csv").open()))
        shares = {r["clipped_fraction"] for r in rows}
        assert (all(0.05 < float(s) < 0.6 for s in shares) if want else shares == {""}), shares
