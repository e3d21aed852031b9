"""Capture-time QC: the score on hand-made cubes, the flags, the engine hook and the HTML report."""

from __future__ import annotations

import base64
import re

import cv2
import numpy as np
import pytest

from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.qc import (
    CaptureQC,
    QcConfig,
    capture_stability,
    estimate_noise,
    qc_of_meta,
    qc_summary,
)
from m2s2hil.analysis.report.session_html import write_session_report
from m2s2hil.analysis.study.stability import simulate_session
from m2s2hil.analysis.study.synthetic import synthetic_scene
from m2s2hil.store.session import SessionStore


def square_cube(level: float = 500.0, size: int = 64, lo: int = 16, hi: int = 48) -> np.ndarray:
    cube = np.zeros((10, size, size), np.float32)
    spectrum = np.linspace(0.5, 1.0, 10, dtype=np.float32)
    cube[:, lo:hi, lo:hi] = level * spectrum[:, None, None]
    return cube


def test_a_noise_free_frame_scores_one():
    res = capture_stability(square_cube())
    assert res.score == 1.0 and res.flags == () and res.noise_dn == 0.0
    assert res.n_materials == 1 and res.foreground_fraction == pytest.approx(32 * 32 / 64**2)


def test_saturated_object_pixels_count_as_disagreeing_by_hand():
    cube = square_cube()
    sat = np.zeros((64, 64), bool)
    sat[16:48, 16:32] = True  # half of the object (512 of 1024 pixels)
    res = capture_stability(cube, sat)
    # class 1: TP = 512, FN = 512; the "spoiled" label: FP = 512 → IoU = 512 / (512 + 512 + 512)
    assert res.ious == pytest.approx((1 / 3,) * 4)
    assert res.score == pytest.approx(1 / 3)
    assert res.saturated_fraction == 0.5 and res.flags == ("unstable", "saturated")


def test_noise_lowers_the_score_monotonically():
    got = []
    for noise in (0.005, 0.05, 0.2):
        cube, _ = synthetic_scene((96, 96), 4, noise=noise, seed=3)
        got.append(capture_stability(cube, full_scale=1.0))
    scores = [r.score for r in got]
    assert scores[0] > scores[1] > scores[2]
    assert scores[0] > 0.97 and "unstable" in got[2].flags and "unstable" not in got[0].flags
    again = capture_stability(synthetic_scene((96, 96), 4, noise=0.2, seed=3)[0], full_scale=1.0)
    assert again.ious == got[2].ious  # seeded: the same frame gives the same score


def test_noise_estimate_recovers_sigma():
    rng = np.random.default_rng(0)
    cube = 100.0 + rng.normal(0.0, 2.0, (3, 128, 128)).astype(np.float32)
    sigma = estimate_noise(cube, np.ones((128, 128), bool))
    assert sigma == pytest.approx([2.0, 2.0, 2.0], rel=0.06)


def test_flags_for_empty_dark_and_cut_frames():
    assert capture_stability(np.full((10, 32, 32), 7.0, np.float32)).flags == ("no_object",)
    dim = capture_stability(square_cube(level=20.0), full_scale=1023)
    assert "underexposed" in dim.flags and dim.level == pytest.approx(20.0 / 1023, rel=1e-3)
    cut = capture_stability(square_cube(lo=0, hi=40))
    assert "object_cut" in cut.flags and cut.border_fraction > 0.05
    with pytest.raises(AnalysisInputError, match="threshold"):
        QcConfig(threshold=1.5)
    with pytest.raises(AnalysisInputError, match="saturated"):
        capture_stability(square_cube(), np.zeros((8, 8), bool))


def test_summary_by_hand():
    class F:
        def __init__(self, eid, meta):
            self.event_id, self.meta = eid, meta

    frames = [
        F("a", {"qc": {"score": 0.5, "flags": ["unstable"], "threshold": 0.8}}),
        F("b", {"qc": {"score": 0.95, "flags": []}}),
        F("c", {"qc": 0.85}),
        F("d", {}),
    ]
    s = qc_summary(frames)
    assert s["frames"] == 4 and s["scored"] == 3 and s["threshold"] == 0.8
    assert s["median"] == 0.85 and s["min"] == 0.5 and s["mean"] == pytest.approx(2.3 / 3)
    assert s["flagged"] == 1 and s["flagged_frames"] == [
        {"event_id": "a", "score": 0.5, "flags": ["unstable"]}
    ]
    assert s["flag_counts"]["unstable"] == 1 and sum(s["histogram"]["counts"]) == 3
    assert qc_of_meta({"qc": None}) == (None, [])


@pytest.fixture(scope="module")
def captured(tmp_path_factory):
    hook = CaptureQC(QcConfig(threshold=0.9))
    folder = simulate_session(
        tmp_path_factory.mktemp("qc"),
        satellite="iss",
        build="B2",
        lighting=("strong", "directional"),
        azimuth_step_deg=120.0,
        size=256,
        qc=hook,
        session_id="qc-run",
    )
    return folder, hook


def test_the_engine_runs_qc_on_every_frame_during_capture(captured):
    folder, hook = captured
    with SessionStore.open_path(folder) as store:
        frames = store.frames()
        stored = qc_summary(frames)
    assert len(frames) == 6
    for fr in frames:
        qc = fr.meta["qc"]
        assert 0.0 <= qc["score"] <= 1.0 and isinstance(qc["flags"], list) and qc["qc_version"] == 1
        assert qc["flagged"] == bool(qc["flags"]) and qc["elapsed_s"] > 0
        assert ("unstable" in qc["flags"]) == (qc["score"] < 0.9)
    live = hook.summary()
    assert live["frames"] == stored["frames"] == 6
    assert live["median"] == stored["median"] and live["flagged"] == stored["flagged"]


def test_html_report_contact_sheet_and_qc_per_pose(captured, tmp_path):
    folder, _ = captured
    with SessionStore.open_path(folder) as store:
        path, summary = write_session_report(store, tmp_path / "r.html", thumb_px=48)
        frames = store.frames()
    html = path.read_text()
    assert html.count("<figure") == 6 and html.count("class=flagged") == summary["flagged"]
    for fr in frames:
        assert fr.event_id in html
        assert f"{fr.meta['qc']['score']:.3f}" in html
    assert "<h3>strong diffuse</h3>" in html and "<h3>directional</h3>" in html  # per-pose grids
    thumbs = re.findall(r"data:image/jpeg;base64,([A-Za-z0-9+/=]+)", html)
    assert len(thumbs) == 6
    img = cv2.imdecode(np.frombuffer(base64.b64decode(thumbs[0]), np.uint8), cv2.IMREAD_COLOR)
    assert img.shape[1] == 48 and img.std() > 0
    assert "data:image/png;base64," in html  # the histogram


def test_report_scores_frames_captured_without_qc(tmp_path):
    folder = simulate_session(
        tmp_path,
        satellite="hubble",
        build="B1",
        lighting=("weak",),
        azimuth_step_deg=180.0,
        size=128,
        qc=None,
        session_id="no-qc",
    )
    with SessionStore.open_path(folder) as store:
        assert all(fr.meta.get("qc") is None for fr in store.frames())
        path, summary = write_session_report(store)
    assert path == folder / "report.html"
    assert summary["computed_at_report"] == 2 and summary["scored"] == 2
    assert "scored at report time" in path.read_text()


@pytest.fixture(scope="module")
def clipped_report(tmp_path_factory):
    """An over-exposed session captured without QC: the report scores it, and flags it."""
    folder = simulate_session(tmp_path_factory.mktemp("clipped"), satellite="voyager", build="B2",
                              lighting=("strong",), azimuth_step_deg=180.0, exposure={"strong": 0.05},
                              size=128, qc=None, session_id="clipped-no-qc")
    with SessionStore.open_path(folder) as store:
        return write_session_report(store)


def test_the_coverage_map_shows_the_flags_scored_at_report_time(clipped_report):
    path, summary = clipped_report
    html = path.read_text()
    assert summary["computed_at_report"] == 2 and summary["flagged"] == 2
    assert "2 flagged" in html  # the map's sentence and legend count what the contact sheet flags
    svg = html[html.index("<svg"):html.index("</svg>")]
    assert svg.count(">⚑</text>") == summary["flagged"]


def test_the_report_fits_a_phone_screen(clipped_report, new_page):
    path, _ = clipped_report
    page = new_page(viewport={"width": 390, "height": 844})
    page.goto(path.resolve().as_uri())
    assert page.evaluate("document.documentElement.scrollWidth") <= 390  # wide tables scroll inside
