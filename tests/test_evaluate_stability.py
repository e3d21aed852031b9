"""The failure study on a tiny simulated rig: every scenario is captured, scored and charted."""

from __future__ import annotations

import csv
import io

import cv2
import pytest

from m2s2hil.analysis.study.stability import SCENARIOS, stability_study


@pytest.mark.slow  # a capture and an evaluation per scenario: ~15 s
@pytest.mark.timeout(600)  # generous: a loaded machine stretches it, it does not fail it
def test_stability_study_small(tmp_path):
    chosen = {k: SCENARIOS[k] for k in ("diffuse", "low light (0.2 ms)", "saturation (50 ms)")}
    rows = stability_study(
        tmp_path / "sessions",
        tmp_path / "out",
        size=128,
        azimuth_step_deg=180.0,
        segmenters=("spectral", "rgb"),
        scenarios=chosen,
        workers=0,
    )
    assert [(r["scenario"], r["segmenter"]) for r in rows] == [
        (s, seg) for s in chosen for seg in ("spectral", "rgb")
    ]
    by = {(r["scenario"], r["segmenter"]): r for r in rows}
    assert by[("diffuse", "spectral")]["images"] == 4  # weak + strong, 2 azimuths
    assert all(0 < r["mtc"] <= 1 and 0 <= r["dice"] <= 1 for r in rows)
    # QC sees both failures: every low-light frame is underexposed, every 50 ms frame saturated
    assert by[("low light (0.2 ms)", "spectral")]["qc_flagged"] == 2
    assert by[("saturation (50 ms)", "spectral")]["qc_flagged"] == 2
    assert by[("saturation (50 ms)", "spectral")]["qc_mean"] < by[("diffuse", "spectral")]["qc_mean"]
    data = list(csv.DictReader(io.StringIO((tmp_path / "out" / "stability.csv").read_text())))
    assert len(data) == 6
    md = (tmp_path / "out" / "stability.md").read_text()
    assert "| saturation (50 ms) | rgb | 2 |" in md
    for name in ("stability.png", "speed_accuracy.png"):
        assert cv2.imread(str(tmp_path / "out" / name)) is not None
