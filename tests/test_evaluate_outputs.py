"""Issue 15: the paper's binary SAM mTC end to end (fake mask generator), failures kept per metric,
PCA bands reported beside the paper's, charts that name ρ, mode and n, and valid JSON."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from m2s2hil.analysis.bands import select_bands_pca
from m2s2hil.analysis.evaluation import evaluate, table2
from m2s2hil.analysis.evaluation.evaluate import EvaluationResult, band_report, evaluate_job
from m2s2hil.analysis.evaluation.jobs import FrameJob
from m2s2hil.analysis.evaluation.loading import LoadedFrame
from m2s2hil.analysis.evaluation.options import EvalOptions, mtc_predictor
from m2s2hil.analysis.report import charts
from m2s2hil.analysis.report.evaluation_files import json_safe, write_evaluation
from m2s2hil.analysis.segmenters.registry import register_segmenter
from m2s2hil.analysis.segmenters.sam import SamSegmenter
from m2s2hil.analysis.study.synthetic import synthetic_scene

BANDS_NM = [431.0, 479.0, 515.0, 567.0, 611.0, 666.0, 719.0, 775.0, 820.0, 877.0]


def fake_masks(image: np.ndarray) -> list[dict]:
    """SAM-style records from intensity levels: the lit object, its brighter half, and six stripes."""
    v = image[:, :, 0].astype(np.int32)
    out = []
    for i, m in enumerate([v > 40, v > 140] + [np.zeros(v.shape, bool) for _ in range(6)]):
        if i >= 2:
            m[(i - 2) * 3 : (i - 2) * 3 + 2, :] = True
        out.append({"segmentation": m, "area": int(m.sum()), "predicted_iou": 0.99 - 0.01 * i,
                    "stability_score": 0.97})
    return out


def job(n_classes: int = 4) -> FrameJob:
    return FrameJob(image_id="s/1", source="s", satellite="voyager", build="B2", n_classes=n_classes,
                    elevation="E0", lighting="weak", azimuth_deg=0.0, camera={"bands_nm": BANDS_NM},
                    method="superpixel")


@pytest.fixture
def scene(monkeypatch):
    cube, gt = synthetic_scene((32, 32), 3, seed=4)
    frame = LoadedFrame(cube, None)  # no raw frame: no clipping mask
    monkeypatch.setattr(evaluate, "load_frame", lambda _job, _reprocess=None, masks=True, bracket=True: frame)
    monkeypatch.setattr(evaluate, "load_truth", lambda _job, _shape: gt)
    return cube, gt


def test_sam_binary_mtc_runs_end_to_end_with_top_k_classes(scene):
    opts = EvalOptions(multi="sam", mtc_mode="binary", segmenter_options={"mask_generator": fake_masks})
    rec = evaluate_job(job(n_classes=4), opts)
    assert rec["error"] is None
    sam = rec["results"]["sam"]
    assert "errors" not in sam, sam.get("errors")
    assert 0.0 <= sam["dice"] <= 1.0 and 0.0 < sam["mtc"] <= 1.0
    assert rec["results"]["sam-rgb"]["dice"] >= 0.0
    # the predictor is SAM itself in binary mode, top-k = the image's classes, the paper's bands
    seg = SamSegmenter(mask_generator=fake_masks)
    predict, align = mtc_predictor(seg, "sam", "binary", 10, n_classes=4)
    twin = predict.__self__
    assert not align and twin.binary and twin.top_k == 4 and twin.bands == (5, 9, 10)
    assert seg.top_k is None and not seg.binary  # the evaluated segmenter is left as it was
    cube, _ = scene
    assert set(np.unique(predict(cube))) <= {0, 1}


def test_a_failing_metric_keeps_the_other_metrics(scene, monkeypatch):
    class Broken:
        name = "broken"

        def segment(self, cube):
            raise RuntimeError("no model")

    register_segmenter("broken-test", lambda **_: Broken(), replace=True)

    def failing_mtc(*_a, **_k):
        raise ValueError("shift failed")

    monkeypatch.setattr(evaluate, "mtc", failing_mtc)
    rec = evaluate_job(job(), EvalOptions(extra=("broken-test",)))
    assert rec["error"] is None
    spectral = rec["results"]["spectral"]
    assert 0.0 <= spectral["dice"] <= 1.0 and "time_s" in spectral and "mtc" not in spectral
    assert spectral["errors"] == {"mtc": "ValueError: shift failed"}
    assert rec["results"]["rgb"]["dice"] >= 0.0 and "errors" not in rec["results"]["rgb"]
    assert rec["results"]["broken-test"] == {"errors": {"segment": "RuntimeError: no model"}}
    result = EvaluationResult([rec], EvalOptions(extra=("broken-test",)), ["s"], 0.1, {})
    assert [(e["segmenter"], e["step"]) for e in result.metric_errors] == [
        ("spectral", "mtc"), ("broken-test", "segment")]


def test_pca_bands_reported_beside_the_papers():
    rng = np.random.default_rng(1)
    samples = [rng.normal(size=(50, 10)).astype(np.float32) * np.linspace(1, 3, 10) for _ in range(3)]
    records = [{"pca_sample": s} for s in samples] + [{"pca_sample": np.zeros((0, 10), np.float32)}]
    rep = band_report(records, EvalOptions(mtc_mode="binary"), BANDS_NM)
    expect = select_bands_pca(np.concatenate(samples).T[:, :, np.newaxis])
    assert rep["pca_bands"] == sorted(expect.bands_1based)
    assert rep["pca_pick_order"] == list(expect.bands_1based)
    assert rep["paper_bands"] == [5, 9, 10] and rep["mtc_bands"] == [5, 9, 10] and rep["mtc_used"] == "paper"
    assert rep["pca_images"] == 4 and all("pca_sample" not in r for r in records)  # taken out of the records
    assert "| 1 | 431 |" in rep["loadings_table"]
    own = band_report([{"pca_sample": s} for s in samples],
                      EvalOptions(mtc_mode="binary", mtc_bands=expect.bands_1based))
    assert own["mtc_used"] == "pca"
    empty = band_report([], EvalOptions())
    assert empty["pca_bands"] is None and "pca_error" in empty


def _record(i: int, dice: float, mtc: float, light: str = "weak") -> dict:
    res = {"spectral": {"time_s": 0.1, "precision": 0.5, "recall": 0.5, "dice": dice, "micro_iou": 0.4,
                        "mtc": mtc},
           "rgb": {"time_s": 0.05, "precision": 0.4, "recall": 0.4, "dice": 0.4, "micro_iou": 0.3}}
    return {"image_id": f"s/{i}", "source": "s", "satellite": "voyager", "build": "B2", "classes": 5,
            "elevation": "E0", "lighting": light, "azimuth_deg": 0.0, "has_truth": True, "error": None,
            "results": res}


def test_summary_is_valid_json_and_charts_say_what_they_show(tmp_path):
    records = [_record(0, float("nan"), 0.97), _record(1, 0.6, 0.99), _record(2, 0.7, 0.95, "directional")]
    opts = EvalOptions(rho=0.5, mtc_mode="binary")
    result = EvaluationResult(records, opts, ["s"], 1.0, {"scheduler": "in-process"},
                              bands={"pca_bands": [2, 5, 9], "mtc_bands": [5, 9, 10], "mtc_used": "paper"})
    write_evaluation(result, tmp_path)

    def no_nan(token: str) -> float:
        raise AssertionError(f"invalid JSON constant {token}")

    summary = json.loads((tmp_path / "summary.json").read_text(), parse_constant=no_nan)
    assert summary["bands"]["pca_bands"] == [2, 5, 9] and summary["options"]["rho"] == 0.5
    sd = {p["segmenter"]: p for p in summary["speed_accuracy"]}
    assert sd["rgb"]["mtc_mean"] is None  # NaN written as null
    assert json_safe({"a": [float("inf"), np.float32(1.5), np.int64(2)]}) == {"a": [None, 1.5, 2]}
    md = (tmp_path / "table2.md").read_text()
    assert "PCA on these images" in md and "bands 2, 5, 9" in md
    assert "bands 5, 9, 10 (the paper's bands)" in md
    assert "ρ = 0.5" in (tmp_path / "significance.md").read_text()

    rows = table2.build_rows(records, multi="spectral", rgb="rgb", rho=0.5)
    assert "assumed ρ = 0.5" in charts.table2_figure(rows, rho=0.5).axes[0].get_title()
    fig = charts.mtc_figure(rows, mode="binary", segmenter="spectral")
    ax = fig.axes[0]
    assert ax.get_ylim()[0] == 0.0 and ax.get_ylim()[1] >= 1.0  # the full axis, not a zoom on 0.95–1
    assert "binary mode" in ax.get_title() and "3 images" in ax.get_title() and "spectral" in ax.get_title()
    labels = [t.get_text() for t in ax.texts]
    assert any("n=2" in t for t in labels) and any("n=1" in t for t in labels)
    assert "label mode" in charts.mtc_figure(rows, mode="labels").axes[0].get_title()
    assert math.isclose(rows[0].mtc["weak"][0], 0.98)
