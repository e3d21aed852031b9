"""``m2s2hil evaluate`` on a simulated session captured by the real engine, in process and on Dask."""

from __future__ import annotations

import csv
import io
import json

import cv2
import numpy as np
import pytest
from cli_support import run_cli

from m2s2hil.analysis import SpectralSegmenter, match_clusters, segmentation_scores
from m2s2hil.analysis.evaluation.evaluate import evaluate_jobs
from m2s2hil.analysis.evaluation.jobs import EvaluationError, collect_jobs
from m2s2hil.analysis.evaluation.options import EvalOptions
from m2s2hil.analysis.evaluation.parallel import SchedulerUnavailable, dask_client
from m2s2hil.analysis.report.evaluation_files import write_evaluation
from m2s2hil.analysis.study.stability import simulate_session
from m2s2hil.store.export import export_session
from m2s2hil.store.session import SessionStore


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    root = tmp_path_factory.mktemp("sessions")
    return simulate_session(
        root,
        satellite="voyager",
        build="B2",
        lighting=("weak", "directional"),
        tilts=("E0",),
        azimuth_step_deg=90.0,
        size=256,
        session_id="sim-eval",
    )


@pytest.fixture(scope="module")
def evaluated(session, tmp_path_factory):
    jobs, sources = collect_jobs(session)
    res = evaluate_jobs(jobs, EvalOptions(), workers=0, sources=sources)
    out = tmp_path_factory.mktemp("evaluation")
    return jobs, res, write_evaluation(res, out), out


def majority_by_loops(lab: np.ndarray, n: int) -> np.ndarray:
    h, w = lab.shape[0] // n, lab.shape[1] // n
    out = np.zeros((h, w), np.int64)
    for i in range(h):
        for j in range(w):
            vals, counts = np.unique(lab[i * n : (i + 1) * n, j * n : (j + 1) * n], return_counts=True)
            out[i, j] = vals[np.argmax(counts)]
    return out


@pytest.mark.slow  # shares a module fixture that evaluates a captured session (about 9 s)
def test_jobs_come_with_truth_labels_stored_by_the_engine(evaluated):
    jobs, res, _, _ = evaluated
    # cubes are computed from raw + dark when read (issue 14), not stored
    assert len(jobs) == 8 and all(j.labels is not None and j.raw is not None and j.dark for j in jobs)
    assert {j.lighting for j in jobs} == {"weak", "directional"} and all(j.n_classes == 5 for j in jobs)
    assert not res.errors and res.has_truth
    for r in res.records:
        assert set(r["results"]) == {"spectral", "rgb"}
        assert 0.0 <= r["results"]["spectral"]["dice"] <= 1.0
        assert 0.0 < r["results"]["spectral"]["mtc"] <= 1.0 and "mtc" not in r["results"]["rgb"]


@pytest.mark.slow  # shares a module fixture that evaluates a captured session (about 9 s)
def test_scores_match_an_independent_recomputation(evaluated, session):
    """Read the stored files ourselves, reduce the labels with plain loops, segment and score."""
    jobs, res, _, _ = evaluated
    job, r = jobs[3], res.records[3]
    with SessionStore.open_path(session) as st:  # the store's own cube, computed from raw + dark
        cube = st.read_cube(job.image_id.split("/", 1)[1])
    full = cv2.imread(job.labels.path, cv2.IMREAD_UNCHANGED)
    gt = majority_by_loops(full, full.shape[0] // cube.shape[1])
    pred = SpectralSegmenter().segment(cube)
    s = segmentation_scores(gt, match_clusters(gt, pred).relabelled)
    got = r["results"]["spectral"]
    assert got["dice"] == pytest.approx(s.macro_dice)
    assert got["precision"] == pytest.approx(s.macro_precision)
    assert got["recall"] == pytest.approx(s.macro_recall)


@pytest.mark.slow  # shares a module fixture that evaluates a captured session (about 9 s)
def test_report_files(evaluated):
    _, res, written, out = evaluated
    assert {
        "table2.csv",
        "table2.md",
        "per_image.csv",
        "by_lighting.csv",
        "significance.md",
        "table2.png",
        "mtc.png",
        "speed_accuracy.png",
        "summary.json",
    } <= set(written)
    rows = list(csv.DictReader(io.StringIO((out / "table2.csv").read_text())))
    assert len(rows) == 1 and rows[0]["satellite"] == "Voyager" and rows[0]["classes"] == "5"
    dice_multi = np.mean([r["results"]["spectral"]["dice"] for r in res.records])
    assert float(rows[0]["dice_multi"]) == pytest.approx(dice_multi)
    mtc_dir = np.mean(
        [r["results"]["spectral"]["mtc"] for r in res.records if r["lighting"] == "directional"]
    )
    assert float(rows[0]["mtc_directional"]) == pytest.approx(mtc_dir)
    assert rows[0]["mtc_strong"] == ""
    md = (out / "table2.md").read_text()
    assert "| Voyager | B2 | 5 | E0 | 8 |" in md and "ρ = 0.9" in md
    per_image = list(csv.DictReader(io.StringIO((out / "per_image.csv").read_text())))
    assert len(per_image) == 16 and {p["segmenter"] for p in per_image} == {"spectral", "rgb"}
    for name in ("table2.png", "mtc.png", "speed_accuracy.png"):
        img = cv2.imread(str(out / name))
        assert img is not None and img.shape[0] > 200 and img.std() > 10
    summary = json.loads((out / "summary.json").read_text())
    assert summary["images_with_truth"] == 8 and summary["compute"]["scheduler"] == "in-process"
    assert {p["segmenter"] for p in summary["speed_accuracy"]} == {"spectral", "rgb"}


@pytest.mark.slow  # starts a local Dask cluster
def test_local_dask_cluster_gives_the_same_records(session, evaluated):
    jobs, res, _, _ = evaluated
    dres = evaluate_jobs(jobs[:3], EvalOptions(), workers=2, processes=False)
    assert dres.compute["workers"] == 2 and dres.compute["scheduler"].startswith("inproc://")
    assert [r["image_id"] for r in dres.records] == [r["image_id"] for r in res.records[:3]]
    for a, b in zip(dres.records, res.records[:3], strict=True):
        assert a["results"]["spectral"]["dice"] == b["results"]["spectral"]["dice"]
        assert a["results"]["rgb"]["recall"] == b["results"]["rgb"]["recall"]


@pytest.mark.slow  # starts a Dask scheduler
def test_existing_scheduler_over_tcp(evaluated):
    from distributed import LocalCluster

    jobs, res, _, _ = evaluated
    with LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, protocol="tcp://", dashboard_address=None
    ) as cluster:
        addr = cluster.scheduler_address
        assert addr.startswith("tcp://")
        dres = evaluate_jobs(jobs[4:6], EvalOptions(), scheduler=addr)
        assert dres.compute["scheduler"] == addr and dres.compute["workers"] == 1
        assert cluster.scheduler.status.name == "running"  # an existing cluster is left running
    assert [r["results"]["spectral"]["mtc"] for r in dres.records] == [
        r["results"]["spectral"]["mtc"] for r in res.records[4:6]
    ]


def test_scheduler_address_errors():
    with pytest.raises(SchedulerUnavailable, match="tcp://host:8786"), dask_client("localhost:8786"):
        pass
    with (
        pytest.raises(SchedulerUnavailable, match="cannot reach"),
        dask_client("tcp://127.0.0.1:9", timeout_s=1),
    ):
        pass


def test_cli_evaluate_and_report(session, tmp_path):
    out = tmp_path / "ev"
    res = run_cli("evaluate", session, "--out", out, "--workers", "0", "--limit", "2", "--mtc", "none")
    assert res.exit_code == 0, res.output
    assert "| Voyager | B2 | 5 | E0 | 2 |" in res.output
    assert (out / "table2.md").is_file() and (out / "table2.png").is_file() and not (out / "mtc.png").exists()
    html = tmp_path / "r.html"
    res = run_cli("report", "sim-eval", "--root", session.parent, "--out", html)
    assert res.exit_code == 0, res.output
    assert "QC: 8 frame(s)" in res.output and html.is_file()


def test_cli_rejects_bad_input(session, tmp_path):
    res = run_cli("evaluate", tmp_path / "nothing", "--workers", "0")
    assert res.exit_code == EvaluationError.exit_code == 2 and res.stderr.startswith("error: "), res.output
    res = run_cli("evaluate", session, "--segmenter", "rgb", "--workers", "0")
    assert res.exit_code == 2 and "RGB baseline" in res.stderr, res.output
    res = run_cli("evaluate", session, "--reprocess", "bogus", "--workers", "0")
    assert res.exit_code == 2 and "bogus" in res.stderr, res.output


def test_cli_segmenter_options(session, tmp_path):
    out = tmp_path / "ev"
    res = run_cli("evaluate", session, "--out", out, "--workers", "0", "--limit", "1", "--mtc", "none",
                  "--option", "censored=false", "-O", "max_materials=6")
    assert res.exit_code == 0, res.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["options"]["segmenter_options"] == {"censored": False, "max_materials": 6}
    # refused before any image is read, with the option named
    for args, says in ((("--option", "nope=1"), "nope"), (("--option", "censored"), "KEY=VALUE"),
                       (("-O", "censored_min_share=2"), "censored_min_share"),
                       (("-O", "seed=1", "-O", "seed=2"), "twice")):
        res = run_cli("evaluate", session, "--out", tmp_path / "x", "--workers", "0", *args)
        error = [line for line in res.stderr.splitlines() if line.startswith("error: ")]
        assert res.exit_code == 2 and len(error) == 1 and says in error[0], res.output
        assert not (tmp_path / "x").exists()


def test_exported_dataset_without_labels_gets_mtc_only(tmp_path):
    # no darks: the export reads raws with frame_files.decode_tiff (see docs/evaluation.md)
    folder = simulate_session(
        tmp_path / "s",
        satellite="hubble",
        build="B1",
        lighting=("strong",),
        azimuth_step_deg=180.0,
        size=128,
        dark_frames=0,
        qc=None,
        session_id="exp",
    )
    with SessionStore.open_path(folder) as store:
        export_session(store, tmp_path / "ds")
    jobs, sources = collect_jobs(tmp_path / "ds")
    assert len(jobs) == 2 and all(j.labels is None and j.raw_kind == "png" for j in jobs)
    assert all("HIL16" in j.raw.path for j in jobs) and jobs[0].n_classes == 2
    res = evaluate_jobs(jobs, EvalOptions(), workers=0, sources=sources)
    assert not res.errors and not res.has_truth
    assert all(
        r["results"]["spectral"]["mtc"] > 0.5 and "dice" not in r["results"]["spectral"] for r in res.records
    )
    written = write_evaluation(res, tmp_path / "out")
    assert "table2.png" not in written and "mtc.png" in written
    md = (tmp_path / "out" / "table2.md").read_text()
    assert "only the ground-truth-free mTC" in md and "| Hubble | B1 | 2 | E0 | 2 | – |" in md


@pytest.mark.slow  # captures nothing new, but fits and evaluates two sweeps of the module's session
def test_a_sweep_segmenter_is_fitted_once_per_sweep_and_labels_its_frames(session):
    """``--segmenter spectral-sweep``: one mixture per session and lighting (evaluation.sweeps),
    each image labelled with its own sweep's, as the segmenter does it directly."""
    from m2s2hil.analysis.evaluation.loading import load_cube, load_truth
    from m2s2hil.analysis.evaluation.sweeps import fit_sweeps, sweep_key
    from m2s2hil.analysis.metrics.scores import score_clusters
    from m2s2hil.analysis.segmenters.sweep import SweepModel, SweepSegmenter

    jobs, sources = collect_jobs(session)
    options = EvalOptions(multi="spectral-sweep", mtc_for="none")
    assert options.segmenters == ("spectral-sweep", "rgb-sweep")
    fitted = fit_sweeps(jobs, options)
    models = {(sweep_key(j), name): model for j in fitted for name, model in j.sweep}
    assert {key[0][3] for key in models} == {"weak", "directional"} and len(models) == 4
    assert all(isinstance(m, SweepModel) and m.frames == 4 for m in models.values())
    for j in fitted:  # every image of a sweep carries the very same model
        assert dict(j.sweep)["spectral-sweep"] is models[(sweep_key(j), "spectral-sweep")]
    res = evaluate_jobs(jobs, options, workers=0, sources=sources)
    weak = [j for j in jobs if j.lighting == "weak"]
    direct = SweepSegmenter()
    direct.fit(load_cube(j) for j in weak)
    for j in weak:
        cube = load_cube(j)
        labels = direct.segment(cube)
        rec = next(r for r in res.records if r["image_id"] == j.image_id)
        got = rec["results"]["spectral-sweep"]
        assert "errors" not in got and "errors" not in rec["results"]["rgb-sweep"]
        assert got["n_segments"] == len(np.unique(labels[labels > 0]))
        truth = load_truth(j, cube.shape[1:])
        assert got["dice"] == pytest.approx(score_clusters(truth, labels)[0].macro_dice)


def test_a_sweep_that_cannot_be_fitted_is_each_images_error(session, tmp_path):
    from dataclasses import replace

    from m2s2hil.analysis.evaluation.evaluate import evaluate_job
    from m2s2hil.analysis.evaluation.jobs import FileRef
    from m2s2hil.analysis.evaluation.sweeps import fit_sweep

    jobs, _ = collect_jobs(session)
    options = EvalOptions(multi="spectral-sweep", mtc_for="none")
    gone = [replace(j, cube=FileRef(str(tmp_path / "gone.tif")), raw=None) for j in jobs[:2]]
    why = fit_sweep(("spectral-sweep", gone), options)
    assert isinstance(why, str) and "could not be fitted" in why and "no frames to fit" in why
    rec = evaluate_job(replace(jobs[0], sweep=(("spectral-sweep", why),)), options)
    assert rec["error"] is None  # the image itself reads; only the sweep segmenters fail on it
    assert "could not be fitted" in rec["results"]["spectral-sweep"]["errors"]["segment"]
    assert "no model fitted" in rec["results"]["rgb-sweep"]["errors"]["segment"]


def test_cli_evaluates_with_a_sweep_segmenter(session, tmp_path):
    out = tmp_path / "ev"
    res = run_cli("evaluate", session, "--out", out, "--workers", "0", "--segmenter", "spectral-sweep",
                  "--mtc", "none")
    assert res.exit_code == 0, res.output
    summary = json.loads((out / "summary.json").read_text())
    assert "spectral-sweep" in json.dumps(summary) and "rgb-sweep" in json.dumps(summary)
    assert "| Voyager | B2 | 5 | E0 | 8 |" in res.output


def test_each_frame_records_its_exposure_and_a_sweep_mixing_exposures_is_scaled_to_its_first(session):
    """Sweep segmenters see one brightness per material: an auto-exposed sweep's cubes are scaled to
    its first frame's exposure × gain before they are fitted and labelled (evaluation.sweeps)."""
    from dataclasses import replace

    from m2s2hil.analysis.evaluation.loading import load_cube
    from m2s2hil.analysis.evaluation.sweeps import fit_sweeps, scaled_to_sweep, sweep_cube

    jobs, _ = collect_jobs(session)
    assert all(j.exposure is not None and j.exposure > 0 for j in jobs)  # from the frames' records
    weak = [j for j in jobs if j.lighting == "weak"]
    assert len({j.exposure for j in weak}) == 1  # the plan's fixed exposure: nothing to scale
    assert [j.sweep_scale for j in scaled_to_sweep(weak)] == [1.0] * len(weak)
    mixed = [replace(j, exposure=j.exposure * f) for j, f in zip(weak, (1.0, 2.0, 0.5, 4.0), strict=True)]
    assert [j.sweep_scale for j in scaled_to_sweep(mixed)] == pytest.approx([1.0, 0.5, 2.0, 0.25])
    unknown = [replace(mixed[0], exposure=None), *mixed[1:]]
    assert [j.sweep_scale for j in scaled_to_sweep(unknown)] == [1.0] * len(weak)  # one missing: as given
    fitted = fit_sweeps(mixed + [j for j in jobs if j.lighting != "weak"],
                        EvalOptions(multi="spectral-sweep", mtc_for="none"))
    assert [j.sweep_scale for j in fitted[:4]] == pytest.approx([1.0, 0.5, 2.0, 0.25])
    assert all(j.sweep_scale == 1.0 for j in fitted[4:])
    cube = load_cube(fitted[3])
    assert np.allclose(sweep_cube(cube, fitted[3]), cube * 0.25)


@pytest.mark.slow  # evaluates the module's session with the sweep segmenters, through the CLI
def test_spectral_pose_labels_each_spotlit_frame_from_its_pose_under_diffuse_light(session, tmp_path):
    out = tmp_path / "ev"
    res = run_cli("evaluate", session, "--out", out, "--workers", "0", "--segmenter", "spectral-sweep",
                  "--also", "spectral-pose", "--mtc", "none")
    assert res.exit_code == 0, res.output
    rows = list(csv.DictReader(io.StringIO((out / "per_image.csv").read_text())))
    pose = {r["image_id"]: r for r in rows if r["segmenter"] == "spectral-pose"}
    sweep = {r["image_id"]: r for r in rows if r["segmenter"] == "spectral-sweep"}
    assert len(pose) == 8 and all(r["failed"] == "" for r in pose.values())
    lit = [i for i, r in pose.items() if r["lighting"] == "directional"]
    assert len(lit) == 4
    for i in lit:
        ref = pose[pose[i]["pose_reference"]]
        assert ref["lighting"] == "weak" and ref["azimuth_deg"] == pose[i]["azimuth_deg"]
        # the stage came back exactly
        assert (pose[i]["pose_shift_rows"], pose[i]["pose_shift_cols"]) == ("0", "0")
        assert float(pose[i]["time_s"]) > 0 and 0 <= float(pose[i]["dice"]) <= 1
    for i, r in pose.items():  # under diffuse light a frame is its own reference: the sweep's labels
        if r["lighting"] == "weak":
            assert r["pose_reference"] == i and float(r["dice"]) == pytest.approx(float(sweep[i]["dice"]))
    # told the materials, the spotlit frames score at least as the segmenter does on them alone
    assert np.mean([float(pose[i]["dice"]) for i in lit]) >= np.mean([float(sweep[i]["dice"]) for i in lit])
    bad = run_cli("evaluate", session, "--out", tmp_path / "ev2", "--segmenter", "spectral-pose")
    assert bad.exit_code != 0 and "--also spectral-pose" in bad.output and "Traceback" not in bad.output


def test_pose_references_are_found_or_their_absence_said(session):
    from dataclasses import replace

    from m2s2hil.analysis.evaluation.poses import attach_pose_references
    from m2s2hil.analysis.segmenters.pose import PoseReference

    jobs, _ = collect_jobs(session)
    lit = [j for j in jobs if j.lighting == "directional"]
    alone = attach_pose_references(lit, EvalOptions(extra=("spectral-pose",)))
    assert all("no frame of this pose under strong or weak diffuse light" in j.pose_ref for j in alone)
    unknown = attach_pose_references([replace(lit[0], azimuth_deg=None)],
                                     EvalOptions(extra=("spectral-pose",)))
    assert "no azimuth recorded" in unknown[0].pose_ref
    assert attach_pose_references(lit, EvalOptions()) == lit  # nothing asked, nothing attached
    # the evaluation's own segmenter is spectral: the reference sweep is fitted for spectral-pose
    found = attach_pose_references(jobs, EvalOptions(extra=("spectral-pose",)))
    weak = {j.azimuth_deg: j.image_id for j in jobs if j.lighting == "weak"}
    for j in found:
        assert isinstance(j.pose_ref, PoseReference), j.pose_ref
        assert j.pose_ref.image_id == weak[j.azimuth_deg] and j.pose_ref.labels.max() >= 1
