"""The fault matrix, reduced for CI: every device × fault kind once and persistent, a seeded
few-percent rate on one kind per device, every SIGKILL point and both disk cells, each checked
against the session invariants (tests/fault_harness.py has the cells and the invariants;
benchmarks/fault_matrix.py runs the full matrix whose table is in docs/reliability.md).

Small sensor (256×256), one lighting, one tilt, four azimuths: a cell costs well under a
second in-process; a kill cell pays for a child interpreter."""

from __future__ import annotations

from pathlib import Path

import fault_harness as fm
import pytest

FEW = {"stage": "late_reply", "relays": "garble", "toucan": "frame_timeout"}
CELLS = (
    fm.fault_cells(rates=("once", "persistent"))
    + [c for c in fm.fault_cells(rates=("few",)) if FEW[c.device] == c.kind]
    + fm.kill_cells()
    + fm.disk_cells()
)


# A kill cell starts a child interpreter that captures until it kills itself: seconds each
# (the child's own limit is 300 s).
KILL_MARKS = [pytest.mark.slow, pytest.mark.timeout(600)]
PARAMS = [pytest.param(c, id=c.name, marks=KILL_MARKS if c.group == "kill" else []) for c in CELLS]


@pytest.mark.parametrize("cell", PARAMS)
def test_cell_keeps_every_invariant(cell: fm.Cell, tmp_path: Path) -> None:
    obs = fm.run_cell(cell, tmp_path, size=256, step=90)
    assert obs.violations == [], f"{cell.name}: {obs.state} exit {obs.code}"
    if cell.group == "fault" and cell.rate == "persistent":
        assert obs.faults > 0  # the fault really was met (and journalled)


def test_the_invariants_catch_a_lying_session(tmp_path: Path) -> None:
    """The checker itself: a completed session with a file gone, a stray file and a wrong
    exit code is reported on each count."""
    cell = fm.Cell("fault", "toucan", "frame_timeout", "once")
    obs = fm.run_cell(cell, tmp_path, size=256, step=90)
    assert obs.ok
    root = tmp_path / cell.name.replace("/", "_")
    (session,) = [p for p in root.iterdir() if p.is_dir()]
    next((session / "frames").glob("*.raw.tiff")).unlink()
    (session / "frames" / "stray.raw.tiff").write_bytes(b"x")
    bad = fm.check_invariants(root, session.name, state="completed", code=5, expected=cell.expected)
    text = "\n".join(bad)
    assert "exit 5 for state completed" in text
    assert "verify:" in text and "files on disk != journal" in text and "manifest != journal" not in text
