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
