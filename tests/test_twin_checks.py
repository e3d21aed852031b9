"""The simulated rig's perturbations (``[simulation.mount]``, ``[simulation.lamps]``) and the
twin's checks during the sweep: flags in the frame's QC, and the fault policy pausing on them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cli_support import run_cli
from engine_helpers import session, small_sweep, wait_for_state

from m2s2hil.analysis.qc import capture_qc_hook
from m2s2hil.config import load_rig
from m2s2hil.engine.fault_policy import FaultPolicy
from m2s2hil.engine.state import RunState
from m2s2hil.errors import ConfigError
from m2s2hil.twin.checks import CheckConfig, sweep_checks
from m2s2hil.twin.registration import Registrar, register_session, stored_registration
from m2s2hil.twin.simulated import BenchFrame, SimBench, rig_with

DEFAULT_RIG = Path(__file__).resolve().parents[1] / "m2s2hil" / "data" / "default_rig.toml"


@pytest.mark.parametrize(("section", "key"), [
    ("[simulation.lamps]\nbarX = 0.5\n", "simulation.lamps.barX"),
    ("[simulation.lamps]\nbar1 = 1.5\n", "simulation.lamps.bar1"),
    ("[simulation.mount]\nbuild = \"B7\"\n", "simulation.mount.build"),
    ("[simulation.mount]\nyaw_deg = 400\n", "simulation.mount.yaw_deg"),
    ("[simulation.mount]\nsatellite = \"hubble\"\nbuild = \"B4\"\n", "simulation.mount.build"),
    ("[simulation.mount]\noffset_mm = [1.0]\n", "simulation.mount.offset_mm"),
])
def test_bad_perturbation_is_one_typed_error_naming_the_key(tmp_path: Path, section: str, key: str) -> None:
    rig = tmp_path / "rig.toml"
    rig.write_text(DEFAULT_RIG.read_text() + "\n" + section)
    with pytest.raises(ConfigError) as exc:
        load_rig(rig)
    assert exc.value.key.startswith(key) and str(rig) in str(exc.value)


def _frame(size: int = 128, az: float = 0.0, tilt: float = 0.0, **sim: object) -> BenchFrame:
    bench = SimBench(rig_with(size, **sim))
    return bench.frame("voyager", "B3", "weak", az, tilt, exposure_s=0.02, process=False)


def _centroid(labels: np.ndarray) -> np.ndarray:
    ys, xs = np.nonzero(labels)
    return np.array([xs.mean(), ys.mean()])


def test_perturbations_change_the_simulated_frames() -> None:
    size = 128
    nominal = SimBench(rig_with(size))
    base = nominal.frame("voyager", "B3", "weak", 0.0, 0.0, exposure_s=0.02, process=False)
    # Off the axis by 8 mm along x: the silhouette moves right by 8 mm in pixels at azimuth 0.
    moved = SimBench(rig_with(size, mount={"offset_mm": [8.0, 0.0]})).frame("voyager", "B3", "weak", 0, 0,
                                                                           exposure_s=0.02, process=False)
    px_per_mm = 2 * 0.45 * size / 160.0
    dx, dy = _centroid(moved.truth.labels) - _centroid(base.truth.labels)
    assert dx == pytest.approx(8.0 * px_per_mm, abs=0.6) and abs(dy) < 0.6
    # Yawed 20 deg at azimuth 0 looks like the nominal mockup turned to 20 deg; a tilt bias likewise.
    yawed = _frame(mount={"yaw_deg": 20.0})
    turned = nominal.frame("voyager", "B3", "weak", 20.0, 0.0, exposure_s=0.02, process=False)
    assert np.array_equal(yawed.truth.labels, turned.truth.labels)
    assert not np.array_equal(yawed.truth.labels, base.truth.labels)
    biased = SimBench(rig_with(size, mount={"tilt_bias_deg": 5.0})).frame("voyager", "B3", "weak", 0, 0,
                                                                        exposure_s=0.02, process=False)
    assert np.array_equal(biased.truth.labels, nominal.frame("voyager", "B3", "weak", 0, 5.0,
                                                             exposure_s=0.02, process=False).truth.labels)
    assert biased.truth.tilt_deg == 0.0  # the truth keeps the stage's read-back
    # The wrong build: another build is on the turntable, whatever the session mounted.
    wrong = _frame(mount={"build": "B1"})
    assert wrong.truth.build == "B1" and wrong.truth.class_names == ["background", "pro_silver"]
    # A dead lamp, a dim one: less light on the same scene.
    dead = _frame(lamps={"bar1": 0.0})
    dim = _frame(lamps={"bar1": 0.5})
    total = [float(f.truth.signal().sum()) for f in (base, dim, dead)]
    assert total[0] > total[1] > total[2] > 0.3 * total[0]
    assert np.array_equal(dead.truth.labels, base.truth.labels)


@pytest.fixture(scope="module")
def checked() -> dict[str, list[str]]:
    """Flags of one frame per case on a 384² sensor (96² cube), voyager B3 in weak light."""
    out = {}
    cases = {"nominal": {}, "off_axis": {"mount": {"offset_mm": [3.0, 0.0]}},
             "tilt": {"mount": {"tilt_bias_deg": 3.0}}, "wrong_build": {"mount": {"build": "B1"}},
             "dead_lamp": {"lamps": {"bar2": 0.0}}}
    for name, sim in cases.items():
        rig = rig_with(384, **sim)
        f = SimBench(rig).frame("voyager", "B3", "weak", 60.0, 0.0)
        chk = sweep_checks(small_sweep(), rig, CheckConfig(size=96))
        res = chk.checks.check(f.cube, "voyager", "B3", 60.0, 0.0, f.meta["lamps_on"], f.meta["exposure_s"])
        out[name] = res["flags"]
    return out


def test_checks_flag_what_the_rig_perturbs(checked: dict[str, list[str]]) -> None:
    assert checked["nominal"] == []
    assert "off_axis" in checked["off_axis"]
    assert "tilt_off" in checked["tilt"]
    assert "wrong_build" in checked["wrong_build"]
    assert "lamp_out" in checked["dead_lamp"]


def test_the_mask_bias_of_a_shadowed_view_is_debiased_by_the_twin() -> None:
    # Hubble in directional light at azimuth 0: its shadowed side is lost to the mask, so the
    # raw alignment turns the silhouette (a 2 deg "yaw"); against the twin's own prediction of
    # the mask, it does not.
    rig = rig_with(256)
    f = SimBench(rig).frame("hubble", "B2", "directional", 0.0, 0.0)
    yaws, shifts = {}, {}
    for debias in (False, True):
        chk = sweep_checks(small_sweep(), rig, CheckConfig(debias=debias)).checks
        res = chk.check(f.cube, "hubble", "B2", 0.0, 0.0, f.meta["lamps_on"], f.meta["exposure_s"])
        yaws[debias], shifts[debias] = abs(res["yaw_deg"]), abs(res["shift_mm"][0])
    assert yaws[True] < 0.6 < 1.5 < yaws[False]
    assert shifts[True] < 0.5 < 0.7 < shifts[False]


def test_the_joint_estimate_over_a_lighting_sees_an_offset_along_the_line_of_sight() -> None:
    chk = sweep_checks(small_sweep(), rig_with(256), CheckConfig(size=32))
    res = {"shift_mm": [0.0, 0.0]}
    # 4 mm along the line of sight at azimuth 0: lateral shifts -4 sin(az) as the turntable turns.
    along = [(az, -4.0 * np.sin(np.radians(az)), 0.2, 0.5) for az in (0.0, 10.0, 20.0)]
    assert chk._joint_flags(along[:1], dict(res), None) is None  # one frame: no joint estimate
    assert chk._joint_flags(along, res, None) == ["off_axis"]
    assert res["joint"]["offset_mm"][1] == pytest.approx(4.0, abs=0.8)
    # A yaw and a tilt seen in every frame, against one frame's odd estimate.
    steady = [(az, 0.0, 2.0, 1.6) for az in (0.0, 10.0)]
    assert chk._joint_flags(steady, dict(res), None) == ["yawed", "tilt_off"]
    assert chk._joint_flags([(0.0, 0.0, 2.2, 1.5), (10.0, 0.0, 0.1, 0.3), (20.0, 0.0, 0.2, 0.4)],
                            dict(res), None) == []


def test_checks_run_on_the_first_frames_of_a_lighting_then_every_nth() -> None:
    chk = sweep_checks(small_sweep(), rig_with(256), CheckConfig(size=32, first_frames=2, every=3))
    due = [chk.due(("weak", "E1")) for _ in range(8)] + [chk.due(("strong", "E1")) for _ in range(3)]
    assert due == [True, True, False, False, True, False, False, True, True, True, False]


def test_the_fault_policy_pauses_on_a_twin_flag_and_the_registration_is_stored(tmp_path: Path) -> None:
    # The session says B3, B1 stands there, 6 mm off the axis (same silhouette: voyager's
    # builds differ in filaments only).
    rig = rig_with(256, mount={"build": "B1", "offset_mm": [6.0, 0.0]})
    qc = capture_qc_hook(twin=CheckConfig(confirm=1))
    policy = FaultPolicy(qc_pause=("wrong_build",))
    with session(tmp_path, small_sweep(), config=rig, qc=qc, policy=policy) as s:
        s.engine.start()
        wait_for_state(s.engine, RunState.PAUSED, timeout=120)
        flagged = [f for f in s.store.frames() if "wrong_build" in f.meta["qc"]["flags"]]
        assert flagged and "twin" in flagged[0].meta["qc"]
        assert "wrong_build" in flagged[0].meta["qc"]["twin"]["flags"]
        assert qc.summary()["flag_counts"]["wrong_build"] >= 1
        s.engine.abort()
        s.engine.wait(timeout=60)
        assert stored_registration(s.store) is None or stored_registration(s.store)["source"] == "capture"
        reg = register_session(s.store, Registrar(rig.camera.model, levels=((48, 1.0),)))
        stored = stored_registration(s.store)
    assert stored is not None and stored["source"] == "session"
    assert stored["placement"]["dx_mm"] == pytest.approx(reg.placement.dx_mm, abs=1e-3)
    assert reg.placement.dx_mm > 3.0  # towards the 6 mm it stands off (from the few frames taken)
    shown = run_cli("sessions", "show", "s1", "--root", tmp_path / "data", "--json")
    assert shown.exit_code == 0, shown.stderr
    assert json.loads(shown.stdout)["registration"]["placement"] == stored["placement"]


@pytest.mark.slow
def test_the_joint_fit_flags_an_offset_along_the_line_of_sight_within_three_frames() -> None:
    """Azimuths 0, 10, 20 (the first frames of a lighting): 2 mm away from the camera moves the
    silhouette by 0.7 mm at most, under one view's noise; the placement fitted to the three
    frames together, against their predicted masks, finds it, and nothing on a nominal mount
    (the yaw's cells: benchmarks/bench_twin_checks.py)."""
    flags = {}
    for name, sim in {"nominal": {}, "along": {"mount": {"offset_mm": [0.0, 2.0]}}}.items():
        rig = rig_with(512, **sim)
        bench = SimBench(rig)
        chk = sweep_checks(small_sweep(satellite="voyager", build="B3"), rig, CheckConfig())
        seen: set[str] = set()
        for az in (0.0, 10.0, 20.0):
            f = bench.frame("voyager", "B3", "strong", az, 0.0)
            res = chk(f.cube, f.meta, key=("strong", "E1"))
            assert res is not None
            seen |= set(res["flags"])
        assert "fit" in res["joint"] and res["joint"]["fit"]["frames"] == 3
        flags[name] = seen
    assert flags["nominal"] == set()
    assert "off_axis" in flags["along"]
