"""Exposure brackets in the capture plan (``Sweep.bracket``): planned, captured by the engine on
the simulated rig, merged by evaluation, kept apart by the exports, refused where they cannot work."""

from __future__ import annotations

import csv
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from cli_support import CliResult, run_cli
from engine_helpers import session, small_rig_config, small_sweep

from m2s2hil.analysis.evaluation.jobs import FileRef, collect_jobs, session_jobs
from m2s2hil.analysis.evaluation.loading import load_frame
from m2s2hil.analysis.report.session_html import write_session_report
from m2s2hil.analysis.study.stability import simulate_session
from m2s2hil.cli import capture_main
from m2s2hil.commands.capture import parse_bracket
from m2s2hil.daemon.admission import planned_dark_count, planned_frame_count
from m2s2hil.errors import UsageError
from m2s2hil.plan import MAX_BRACKET, PlanError, Sweep, bracket_base_id, parse_sweep
from m2s2hil.processing.bracket import merge_bracket
from m2s2hil.store.export import export_session
from m2s2hil.store.session import SessionStore

BASE = {"satellite": "iss", "build": "B3", "lighting": ["weak", "directional"], "tilts": ["E1"],
        "azimuth_step_deg": 90.0}


def test_a_bracketed_pose_is_its_frame_then_each_extra_exposure_at_the_same_pose():
    rig = small_rig_config()
    sweep = Sweep(**BASE, bracket={"dir": [16, 4]}, frames_per_pose=2)
    events = sweep.expand(rig)
    darks = {e.exposure_s for e in events if e.kind == "dark"}
    assert darks == {0.008, 0.003, 0.048, 0.012}  # one master dark per exposure, the bracket's too
    frames = [e for e in events if e.kind == "frame"]
    weak = [e for e in frames if e.lighting == "weak"]
    spot = [e for e in frames if e.lighting == "directional"]
    assert len(weak) == 4 * 2 and len(spot) == 4 * 2 * 3
    assert all(e.exposure_factor == 1.0 and not e.bracket_member for e in weak)
    # per pose and frame: its own, then x16, then x4, one after the other at one pose
    first = spot[:3]
    assert [e.exposure_factor for e in first] == [1.0, 16.0, 4.0]
    assert [e.exposure_s for e in first] == [0.003, 0.048, 0.012]
    pose = (first[0].azimuth_deg, first[0].tilt_deg, 0)
    assert {(e.azimuth_deg, e.tilt_deg, e.frame) for e in first} == {pose}
    assert [e.event_id.rsplit("/", 1)[-1] for e in first] == ["f0", "x16", "x4"]
    assert [e.dark_id for e in first] == ["dark/3000us/g1", "dark/48000us/g1", "dark/12000us/g1"]
    assert len({e.event_id for e in frames}) == len(frames)
    assert all(bracket_base_id(e.event_id) == first[0].event_id for e in first)
    assert bracket_base_id("weak/E1/az000/f0") == "weak/E1/az000/f0"
    # the plan's duration counts the extra exposures and readouts, not moves
    plain = Sweep(**BASE, frames_per_pose=2).estimate(rig)
    est = sweep.estimate(rig)
    assert est.breakdown["motion"] == pytest.approx(plain.breakdown["motion"])
    extra = 4 * 2 * (0.048 + 0.012)
    assert est.breakdown["exposure"] - plain.breakdown["exposure"] == pytest.approx(extra)
    assert est.counts["frames"] == plain.counts["frames"] + 16
    # the daemon's admission counts them without expanding the plan
    assert planned_frame_count(sweep) == len(frames)
    assert planned_dark_count(sweep) == len(darks)


@pytest.mark.parametrize(("bracket", "extra", "needle"), [
    ({"strong": [4]}, {}, "does not capture"),
    ({"dir": [1]}, {}, "factor 1 is the pose's own frame"),
    ({"dir": [4, 4]}, {}, "listed twice"),
    ({"dir": [2.0, 3.0, 4.0, 5.0, 6.0]}, {}, f"at most {MAX_BRACKET}"),
    ({"dir": [0]}, {}, "greater than 0"),
    ({"dir": ["16"]}, {}, "valid number"),
    ({"weak": [1000]}, {}, "outside the camera's"),  # 8 s at the plan's 8 ms
    ({"dir": [16]}, {"mode": "continuous"}, "stand still"),
])
def test_a_bracket_that_cannot_be_captured_is_a_plan_error_naming_the_field(bracket, extra, needle):
    with pytest.raises(PlanError) as err:
        parse_sweep({**BASE, "bracket": bracket, **extra}, "request")
    assert needle in str(err.value) and "request" in str(err.value)


def test_an_empty_bracket_and_the_published_names_normalise():
    sweep = parse_sweep({**BASE, "bracket": {"DIR": [16.0], "weak": []}})
    assert sweep.bracket == {"directional": [16.0]}
    assert Sweep.from_json(sweep.to_json()) == sweep


def test_the_capture_command_reads_brackets_for_every_condition_or_one():
    lights = ["weak", "directional"]
    assert parse_bracket(["16"], lights) == {"weak": [16.0], "directional": [16.0]}
    assert parse_bracket(["dir=4,16", "dir=16"], lights) == {"directional": [4.0, 16.0]}
    for bad in ("x", "dir=", "sun=4"):
        with pytest.raises(UsageError):
            parse_bracket([bad], lights)


def capture(*args: object) -> CliResult:
    return run_cli(*args, entry=capture_main, prog="capture")


def test_capture_dry_run_shows_the_bracket_and_its_events():
    r = capture("--sat", "iss", "--build", "B3", "--light", "dir", "--tilt", "E1", "--azimuth-step", "90",
                "--bracket", "16", "--dry-run")
    assert r.exit_code == 0, r.stderr
    assert re.search(r"bracket \(directional\)\s*│\s*x1, x16", r.stdout)
    assert "directional/E1/az000/f0/x16" in r.stdout
    r = capture("--sat", "iss", "--build", "B3", "--light", "dir", "--bracket", "16", "--mode", "continuous",
                "--dry-run")
    assert r.exit_code == 2 and "stop-and-go" in r.stderr and "Traceback" not in r.stderr


# ------------------------------------------------------------------ captured by the engine
@pytest.fixture(scope="module")
def bracketed(tmp_path_factory) -> Path:
    """ISS B3 under the spotlight at two azimuths, each pose again at 16 x (real engine, QC on)."""
    return simulate_session(tmp_path_factory.mktemp("bracket"), satellite="iss", build="B3",
                            lighting=("directional",), tilts=("E1",), azimuth_step_deg=180.0, size=128,
                            session_id="bracketed", bracket={"directional": [16.0]})


def test_the_engine_takes_each_extra_exposure_with_its_own_dark(bracketed):
    with SessionStore.open_path(bracketed) as store:
        frames = {f.event_id: f for f in store.frames()}
        darks = {d.dark_id: d for d in store.darks()}
    assert sorted(frames) == ["directional/E1/az000/f0", "directional/E1/az000/f0/x16",
                              "directional/E1/az180/f0", "directional/E1/az180/f0/x16"]
    for own_id in ("directional/E1/az000/f0", "directional/E1/az180/f0"):
        own, long = frames[own_id], frames[own_id + "/x16"]
        assert long.meta["exposure_s"] == pytest.approx(16 * own.meta["exposure_s"])
        assert darks[long.dark_id].exposure_s == pytest.approx(long.meta["exposure_s"])
        assert own.meta["pose"] == long.meta["pose"]  # no move between them
        assert own.meta["qc"]["score"] is not None  # the pose's own frame is checked ...
        assert long.meta["qc"] is None and "bracket member" in long.meta["qc_skipped"]  # ... not its bracket
        raw_own = store_raw(bracketed, own_id)
        raw_long = store_raw(bracketed, own_id + "/x16")
        assert raw_long.mean() > 4 * raw_own.mean()  # it collected more light


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, encoding="utf-8", newline="") as f:
        return list(csv.DictReader(f))


def store_raw(folder: Path, event_id: str) -> np.ndarray:
    with SessionStore.open_path(folder) as store:
        return store.read_raw(event_id)[0]


def test_auto_exposure_scales_the_bracket_from_the_metered_exposure(tmp_path):
    sweep = small_sweep(lighting=["directional"], azimuth_step_deg=180, exposure="auto",
                        bracket={"directional": [8.0]})
    with session(tmp_path, sweep) as s:
        s.engine.start()
        assert s.engine.wait(timeout=120)
        frames = {f.event_id: f for f in s.store.frames()}
        metered = [e["payload"]["exposure_s"] for e in s.store.events() if e["kind"] == "auto_exposure"]
    assert len(metered) == 1 and len(frames) == 4
    own = frames["directional/E1/az000/f0"].meta["exposure_s"]
    assert own == pytest.approx(metered[0])
    assert frames["directional/E1/az000/f0/x8"].meta["exposure_s"] == pytest.approx(round(8 * metered[0], 6))


def test_evaluation_merges_each_pose_with_its_bracket(bracketed):
    with SessionStore.open_path(bracketed) as store:
        jobs = session_jobs(store)
        every = session_jobs(store, brackets=False)
    assert len(every) == 4 and len(jobs) == 2  # an extra exposure is not an image of its own
    job = jobs[0]
    assert [m.event_id for m in job.bracket] == ["directional/E1/az000/f0/x16"]
    own = load_frame(job, bracket=False)
    merged = load_frame(job)
    assert own.bracket_frames == 1 and merged.bracket_frames == 2 and merged.bracket_error is None
    # the merge is processing.bracket's, each frame with its own dark, mask and exposure × gain
    long = load_frame(next(j for j in every if j.image_id.endswith("/x16")), bracket=False)
    assert own.saturated is not None and long.saturated is not None
    expected = merge_bracket([own.cube, long.cube], [job.exposure, job.bracket[0].exposure],
                             [own.saturated, long.saturated])
    np.testing.assert_array_equal(merged.cube, expected.cube)
    np.testing.assert_array_equal(merged.saturated, expected.clipped)
    assert long.saturated.any()  # the long frame clipped where the lit faces are ...
    assert not merged.saturated.any()  # ... and the short one did not, so nothing stays flagged
    # and the shadows are lifted out of the noise: the backdrop (no light) is quieter, on one scale
    dark = own.cube.sum(axis=0) < np.percentile(own.cube.sum(axis=0), 30)
    def noise(cube: np.ndarray) -> float:  # spread of each band over the backdrop, averaged
        return float(cube[:, dark].std(axis=1).mean())

    assert noise(merged.cube) < 0.4 * noise(own.cube)  # about 1/sqrt(17) of it, plus read noise
    assert float(np.median(merged.cube[:, ~dark])) == pytest.approx(float(np.median(own.cube[:, ~dark])),
                                                                    rel=0.2)


def test_a_bracket_that_cannot_be_merged_leaves_the_pose_its_own_frame_and_says_why(bracketed):
    with SessionStore.open_path(bracketed) as store:
        job = session_jobs(store)[0]
    own = load_frame(job, bracket=False).cube
    for member, why in ((replace(job.bracket[0], exposure=None), "no exposure recorded"),
                        (replace(job.bracket[0], raw=FileRef(str(bracketed / "gone.tiff"))), "gone.tiff")):
        frame = load_frame(replace(job, bracket=(member,)))
        assert frame.bracket_frames == 1 and why in (frame.bracket_error or ""), frame.bracket_error
        np.testing.assert_array_equal(frame.cube, own)


def test_evaluate_reports_the_merged_frames_per_image(bracketed, tmp_path):
    r = run_cli("evaluate", bracketed, "--out", tmp_path / "ev", "--workers", "0", "--mtc", "none")
    assert r.exit_code == 0, r.stderr
    rows = read_csv(tmp_path / "ev" / "per_image.csv")
    assert {row["image_id"].rsplit("/", 1)[-1] for row in rows} == {"f0"}
    assert {row["bracket_frames"] for row in rows} == {"2"}


def test_exports_keep_the_bracket_beside_the_release_layout(bracketed, tmp_path):
    out = tmp_path / "export"
    with SessionStore.open_path(bracketed) as store:
        export_session(store, out)
    hil = sorted(p.relative_to(out).as_posix() for p in (out / "HIL").rglob("*.png"))
    extra = sorted(p.relative_to(out).as_posix() for p in (out / "HILbracket").rglob("*.png"))
    assert hil == ["HIL/ISS/b3/e1/dir_0.png", "HIL/ISS/b3/e1/dir_1.png"]  # k: the azimuth index
    assert extra == ["HILbracket/ISS/b3/e1/dir_0_x16.png", "HILbracket/ISS/b3/e1/dir_1_x16.png"]
    rows = read_csv(out / "metadata" / "bracketed.csv")
    assert sorted((r["file"], float(r["exposure_factor"])) for r in rows) == [
        ("HIL/ISS/b3/e1/dir_0.png", 1.0), ("HIL/ISS/b3/e1/dir_1.png", 1.0),
        ("HILbracket/ISS/b3/e1/dir_0_x16.png", 16.0), ("HILbracket/ISS/b3/e1/dir_1_x16.png", 16.0)]
    jobs, _ = collect_jobs(out)  # the release's layout reads as before: one image per pose
    assert len(jobs) == 2


def test_the_zarr_export_records_the_factor_and_evaluates_one_image_per_pose(bracketed, tmp_path):
    pytest.importorskip("xarray", reason="the zarr export needs xarray (a test extra)")
    import xarray as xr

    out = tmp_path / "frames.zarr"
    with SessionStore.open_path(bracketed) as store:
        export_session(store, out, layout="zarr")
    ds = xr.open_zarr(out, consolidated=False)
    factors = dict(zip(ds["event_id"].values.tolist(), ds["exposure_factor"].values.tolist(), strict=True))
    assert factors["directional/E1/az000/f0/x16"] == 16.0 and factors["directional/E1/az000/f0"] == 1.0
    jobs, _ = collect_jobs(out)
    assert sorted(j.image_id.rsplit("/", 1)[-1] for j in jobs) == ["f0", "f0"]


def test_the_session_report_shows_the_bracket_without_checking_it(bracketed, tmp_path):
    with SessionStore.open_path(bracketed) as store:
        path, summary = write_session_report(store, tmp_path / "r.html", thumb_px=32)
    html = path.read_text()
    assert html.count("<figure") == 4 and html.count(" ×16 · ") == 2
    assert summary["frames"] == 2  # the QC summary counts the poses' own frames
