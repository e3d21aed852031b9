"""The soak, reduced (issue 21.5): the daemon as a real ``serve`` process on the virtual clock for a
few minutes of simulated time, with small and full sweeps, e-stops, operator holds and releases,
two kill -9s (one while held) and ``serve --resume``, live-view viewers, event subscribers and
concurrent exports, then every invariant of benchmarks/soak/checks.py. The full soak (an hour of
simulated time) is ``python -m benchmarks.soak``; its table is in docs/reliability.md.

The last tests show that the checks can fail: a session folder with a changed file, a stray file
and a frame journalled during a hold are each reported."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/ as a namespace package
from benchmarks.soak.checks import Counts, HoldWindow, check_session, flatness
from benchmarks.soak.daemon import Sample
from benchmarks.soak.report import markdown
from benchmarks.soak.run import Result, run_soak
from benchmarks.soak.schedule import SoakConfig

pytestmark = pytest.mark.slow

REDUCED = SoakConfig(sim_s=150.0, kills=2, seed=7, size=64, full_step_deg=90.0, tick_s=0.3,
                     p_estop=0.04, p_hold=0.05, p_viewer=0.15, p_export=0.1, probe_s=1.5,
                     hold_s=(0.5, 1.5), drain_wall_s=120.0, idle_samples=6, max_wall_s=360.0)


@pytest.fixture(scope="module")
def soak(tmp_path_factory: pytest.TempPathFactory) -> tuple[Result, Path]:
    work = tmp_path_factory.mktemp("soak")
    return run_soak(REDUCED, work), work


@pytest.mark.timeout(600)
def test_the_reduced_soak_keeps_every_invariant(soak: tuple[Result, Path]) -> None:
    result, _ = soak
    broken = {inv: bad for inv, bad in result.violations.items() if bad}
    assert not broken, "invariants broken in the soak:\n" + "\n".join(
        f"- {inv}: {len(bad)}, e.g. {bad[0]}" for inv, bad in broken.items()) + "\n\n" + markdown(result)


@pytest.mark.timeout(600)
def test_the_reduced_soak_did_what_it_says(soak: tuple[Result, Path]) -> None:
    result, _ = soak
    ran = result.ran
    for action in ("e-stops", "operator holds", "releases", "live-view viewers", "event subscribers",
                   "sessions submitted (small)", "sessions submitted (full)", "kill -9 while held"):
        assert ran[action] >= 1, f"the soak never did {action!r}: {dict(ran)}"
    assert ran["kill -9"] + ran["kill -9 while held"] == REDUCED.kills
    assert any(k.startswith("exports") for k in ran), dict(ran)
    assert sum(c.sim_s for c in result.sessions) >= REDUCED.sim_s
    assert all(w.held_after_restart for w in result.windows if w.kills), "a held restart was not probed"
    assert result.acked > 0 and result.flat, "nothing acknowledged, or no daemon judged for leaks"


@pytest.mark.timeout(600)
def test_the_session_check_finds_a_changed_and_a_stray_file(soak: tuple[Result, Path],
                                                            tmp_path: Path) -> None:
    result, work = soak
    done = next(c for c in result.sessions if c.state == "completed")
    root = tmp_path / "data"
    shutil.copytree(work / "data" / done.sid, root / done.sid)
    assert check_session(root, done.sid, set()).problems == []
    raw = sorted((root / done.sid / "frames").glob("*.raw.tiff"))[0]
    data = raw.read_bytes()
    raw.write_bytes(data[:-1] + bytes([data[-1] ^ 0xFF]))  # a changed byte (setting it could be a no-op)
    (root / done.sid / "frames" / "stray.raw.tiff").write_bytes(b"x")
    problems = check_session(root, done.sid, {"weak/E9/az999/f0"}).problems
    text = "\n".join(problems)
    assert "sha256" in text and "stray.raw.tiff" in text and "acknowledged frame(s) lost" in text, text


def test_a_frame_stored_while_held_is_a_violation(tmp_path: Path) -> None:
    (tmp_path / "data").mkdir()
    w = HoldWindow("estop", 0.0, {"a": Counts(frozenset({"x"}), 1, "estopped")}, None)
    w.compare({"a": Counts(frozenset({"x", "y"}), 2, "running")}, "at the release")
    assert len(w.violations) == 2 and "started 1 run(s)" in w.violations[0] and "y" in w.violations[1]
    op = HoldWindow("operator", 0.0, {"a": Counts(frozenset(), 1, "running")}, "a")
    op.compare({"a": Counts(frozenset({"y"}), 1, "running")}, "at the release")
    assert op.violations == []  # the session running at an operator's hold may finish its run


def test_what_the_first_run_loads_is_warm_up_not_growth() -> None:
    """Idle before its first session a daemon has not loaded QC's libraries yet: the baseline is
    the idle time after its first run. Growth after that still fails."""
    mib = 1024
    cold = [Sample(0, float(i), 306 * mib, 20, 20, 0, 8, idle=True) for i in range(8)]
    run = [Sample(0, 8.0 + i, 430 * mib, 22, 22, 1, 12, idle=False) for i in range(3)]
    warm = [Sample(0, 11.0 + i, 419 * mib, 20, 20, 1, 8, idle=True) for i in range(12)]
    (f,) = flatness(cold + run + warm)
    assert f.ok and f.rss_first_kib == f.rss_last_kib == 419 * mib
    grows = [Sample(0, 11.0 + i, (419 + 20 * i) * mib, 20, 20, 1, 8, idle=True) for i in range(12)]
    (g,) = flatness(cold + run + grows)
    assert not g.ok and g.rss_last_kib > g.rss_first_kib


def test_growing_descriptors_are_not_flat() -> None:
    leaking = [Sample(0, float(i), 400_000, 20 + i, 20 + i, 0, 8, idle=True) for i in range(20)]
    (f,) = flatness(leaking)
    assert not f.ok and f.fds_last > f.fds_first
    kept = [Sample(0, float(i), 400_000, 20 + 4 * i, 20, i, 8, idle=True) for i in range(20)]
    assert flatness(kept)[0].ok  # finished sessions' journals the daemon keeps open, within its bound
    too_many = [Sample(0, float(i), 400_000, 20 + 4 * i, 20, 2 * i, 8, idle=True) for i in range(20)]
    assert not flatness(too_many)[0].ok
