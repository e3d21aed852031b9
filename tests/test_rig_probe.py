"""`m2s2hil rig probe`: a GRBL whose maximum rate ($110) is below the rig file's speed is flagged
with what it causes, and `--apply` writes the rig file's value; in-process and over a pty."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from m2s2hil.simulators.clock import VirtualClock
from rig_files import rig_text

from m2s2hil.config import load_rig
from m2s2hil.rig.factory import build_simulators
from m2s2hil.rig.probe import EXIT_MISMATCH, probe_rig
from m2s2hil.rig.pty_serve import SimServer

LOW = 600.0  # units/min: 10 deg/s where the rig file asks the turntable for 60


def _low_rate_rig(tmp_path: Path) -> Path:
    text = rig_text(homing="switches", fast=False)
    text = text.replace("homing_switches = true", 'homing_switches = true\nsettings = { "$110" = 600.0 }')
    path = tmp_path / "low.toml"
    path.write_text(text)
    return path


def _finding(report, item_prefix: str):
    return next(f for f in report.findings if f.item.startswith(item_prefix))


def test_low_max_rate_is_flagged_and_apply_fixes_it_in_process(tmp_path):
    config = load_rig(_low_rate_rig(tmp_path))
    want = config.axes["turntable"].max_speed_dps * config.axes["turntable"].units_per_degree * 60.0
    clock = VirtualClock()
    _world, sims, _frames = build_simulators(config, clock)
    assert sims["stage"].settings[110] == LOW

    report = probe_rig(config, clock=clock, sims=sims)
    f = _finding(report, "$110")
    assert f.ok is False and f.actual == "600" and float(f.expected) == want
    assert "slower than planned" in f.effect and f.fix == ("$110", want)
    assert [m.item for m in report.mismatches] == [f.item]  # everything else agrees
    assert _finding(report, "$111").ok and _finding(report, "$22").ok
    assert _finding(report, "model").ok and _finding(report, "bit depth").ok

    fixed = probe_rig(config, clock=clock, sims=sims, apply=True)
    assert fixed.ok, [(m.item, m.actual) for m in fixed.mismatches]
    assert sims["stage"].settings[110] == pytest.approx(want)


def test_homing_setting_against_the_axis_policy(tmp_path):
    path = tmp_path / "none.toml"
    path.write_text(rig_text(homing="none", switches_in_sim=True, fast=False))
    config = load_rig(path)
    clock = VirtualClock()
    _world, sims, _frames = build_simulators(config, clock)
    report = probe_rig(config, clock=clock, sims=sims)
    f = _finding(report, "$22")
    assert f.ok is False and "locked in alarm" in f.effect and f.fix == ("$22", 0.0)
    assert probe_rig(config, clock=clock, sims=sims, apply=True).ok
    assert sims["stage"].settings[22] == 0


def _cli(*args: str, answer: str | None = None) -> subprocess.CompletedProcess:
    """``m2s2hil ARGS`` in a child interpreter; ``answer`` is typed at its prompt."""
    code = "import sys; from m2s2hil.cli import main; sys.argv[0] = 'm2s2hil'; main()"
    env = {**os.environ, "COLUMNS": "300"}  # rich would wrap the table at 80 columns
    return subprocess.run([sys.executable, "-c", code, *args], input=answer, capture_output=True, text=True,
                          timeout=120, env=env)


def _served(tmp_path: Path, srv: SimServer) -> Path:
    served = tmp_path / "served.toml"
    served.write_text(srv.rig_toml())
    return served


@pytest.mark.slow
def test_low_max_rate_is_flagged_and_apply_fixes_it_over_a_pty(tmp_path):
    config = load_rig(_low_rate_rig(tmp_path))
    with SimServer(config) as srv:
        served = _served(tmp_path, srv)
        res = _cli("rig", "probe", str(served))
        assert res.returncode == EXIT_MISMATCH, res.stderr
        line = next(ln for ln in res.stdout.splitlines() if "$110" in ln)
        assert "MISMATCH" in line and "600" in line and "slower than planned" in line
        assert "Traceback" not in res.stderr

        res = _cli("rig", "probe", str(served), "--apply", "--yes")
        assert res.returncode == 0, res.stdout + res.stderr
        assert srv.sims["stage"].settings[110] == pytest.approx(3600.0)
        assert _cli("rig", "probe", str(served)).returncode == 0


@pytest.mark.slow
def test_apply_asks_first_and_no_answer_writes_nothing(tmp_path):
    config = load_rig(_low_rate_rig(tmp_path))
    with SimServer(config) as srv:
        res = _cli("rig", "probe", str(_served(tmp_path, srv)), "--apply", answer="n\n")
        assert "write stage $110=3600" in res.stdout
        assert res.returncode == EXIT_MISMATCH
        assert srv.sims["stage"].settings[110] == LOW


def test_zaber_settings_against_the_rig_file(tmp_path):
    from rig_files import zaber_rig_text

    path = tmp_path / "z.toml"
    path.write_text(zaber_rig_text())
    config = load_rig(path)
    clock = VirtualClock()
    _world, sims, _frames = build_simulators(config, clock)
    report = probe_rig(config, clock=clock, sims=sims)
    f = _finding(report, "axis 1 limit.max")
    assert f.ok is False and f.expected == str(round(370 * 100.0)) and f.actual == "10000000"
    assert _finding(report, "device id").actual == "50000" and not report.errors
    assert probe_rig(config, clock=clock, sims=sims, apply=True).ok


def test_relay_board_channel_count_against_the_lamps(tmp_path):
    """The board's coil count, found from its exception replies, against the lamps' channels."""
    path = tmp_path / "r.toml"
    path.write_text(rig_text(homing="switches", fast=False))
    config = load_rig(path)
    clock = VirtualClock()
    _world, sims, _frames = build_simulators(config, clock)
    f = _finding(probe_rig(config, clock=clock, sims=sims), "channels")
    assert f.ok and f.actual == str(sims["relays"].channels) == "8"

    text = rig_text(homing="switches", fast=False)
    text = text.replace("[lamps.spot]\nchannel = 5", "[lamps.spot]\nchannel = 11")  # beyond 8 coils
    path.write_text(text)
    config = load_rig(path)
    _world, sims, _frames = build_simulators(config, clock)
    f = _finding(probe_rig(config, clock=clock, sims=sims), "channels")
    assert f.ok is False and f.actual == "8" and "never lights" in f.effect
