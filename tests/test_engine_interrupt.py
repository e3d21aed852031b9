"""Ctrl-C in `capture`, as the operator presses it: real SIGINTs to the command in a subprocess.

The first asks for a pause at the next safe boundary; a second one does not wait for it. The
rig here is stuck (every snap after the first lit frame times out after a minute, in real
time), so no boundary comes soon: only a stop that does not wait for one ends the command.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from m2s2hil.commands.capture import EXIT_INTERRUPTED
from m2s2hil.store.catalogue import list_sessions
from m2s2hil.store.session import SessionStore
from tests.test_capture_cli import capture, small_rig

DARKS = 8  # the sweep's dark frames (its default), snapped before the first lit frame


def stuck_rig(tmp_path: Path) -> Path:
    """The small rig whose camera answers the darks and one lit frame, then never again
    within its (longest allowed) timeout of 60 s."""
    path = small_rig(tmp_path)
    text = path.read_text()
    assert 'port = "sim://toucan"\n' in text
    text = text.replace('port = "sim://toucan"\n', 'port = "sim://toucan"\ntimeout_s = 60\n', 1)
    text += f'\n[[simulation.faults.toucan]]\nkind = "frame_timeout"\nafter = {DARKS + 1}\ncount = -1\n'
    path.write_text(text)
    return path


def stored_frames(root: Path) -> int:
    sessions = list_sessions(root) if root.exists() else []
    if not sessions:
        return 0
    store = SessionStore.open(root, sessions[0].session_id)
    try:
        return len(store.frames())
    finally:
        store.close()


# Ctrl-C as from an operator's terminal: SIGINT at its default. A test run started in the
# background by a shell (``pytest … &``, ``nohup``) ignores SIGINT, and an ignored signal stays
# ignored across exec, so the command would never see the key press.
OPERATOR_SHELL = "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "


def until(pred: Callable[[], object], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.2)


@pytest.mark.slow
def test_second_ctrl_c_stops_at_once_with_the_rig_safe_and_the_frames_kept(tmp_path):
    rig, out, err_path = stuck_rig(tmp_path), tmp_path / "data", tmp_path / "stderr.txt"
    code = OPERATOR_SHELL + "from m2s2hil.cli import capture_main; sys.argv[0] = 'capture'; capture_main()"
    args = ["--sat", "voyager", "--build", "B2", "--light", "weak", "--tilt", "E1", "--azimuth-step", "90",
            "--rig", str(rig), "--out", str(out), "--realtime"]
    with err_path.open("w") as err:
        proc = subprocess.Popen([sys.executable, "-c", code, *args], stdout=subprocess.DEVNULL, stderr=err)
    try:
        until(lambda: stored_frames(out) >= 1, 120, "the first frame")  # the next snap hangs
        time.sleep(1.0)  # into the hanging snap
        os.kill(proc.pid, signal.SIGINT)
        until(lambda: "pausing at the next safe boundary" in err_path.read_text(), 30, "the first Ctrl-C")
        os.kill(proc.pid, signal.SIGINT)
        # Before the fix the run waited out the stuck snap (60 s), its retries and the pipeline.
        rc = proc.wait(timeout=40)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text = err_path.read_text()
    assert rc == EXIT_INTERRUPTED, text[-2000:]
    assert "stopping now (lamps off, motion stopped)" in text
    assert "rig safe: lamps off, motion stopped" in text and "NOT confirmed safe" not in text
    assert "resume with: capture --resume" in text
    (info,) = list_sessions(out)
    store = SessionStore.open(out, info.session_id)
    try:
        kept = {f.event_id for f in store.frames()}
        assert kept and store.verify() == []  # what was stored is kept, intact
    finally:
        store.close()
    # Resumable: on the rig without the stuck camera (hence --allow-rig-change: its timeout).
    text = rig.read_text()
    rig.write_text(text[:text.index("[[simulation.faults.toucan]]")])
    res = capture("--resume", info.session_id, "--out", str(out), "--rig", str(rig), "--allow-rig-change")
    assert res.exit_code == 0, res.stderr[-2000:]
    store = SessionStore.open(out, info.session_id)
    try:
        assert store.state == "completed" and kept < {f.event_id for f in store.frames()}
    finally:
        store.close()


@pytest.mark.slow
def test_first_ctrl_c_pauses_at_the_next_boundary_and_exits_130(tmp_path):
    """One Ctrl-C on a rig that is not stuck: paused at a boundary, saved, resumable (130)."""
    rig, out, err_path = small_rig(tmp_path), tmp_path / "data", tmp_path / "stderr.txt"
    code = OPERATOR_SHELL + "from m2s2hil.cli import capture_main; sys.argv[0] = 'capture'; capture_main()"
    args = ["--sat", "voyager", "--build", "B2", "--light", "weak", "--tilt", "E1", "--azimuth-step", "30",
            "--rig", str(rig), "--out", str(out), "--realtime"]
    with err_path.open("w") as err:
        proc = subprocess.Popen([sys.executable, "-c", code, *args], stdout=subprocess.DEVNULL, stderr=err)
    try:
        until(lambda: stored_frames(out) >= 1, 120, "the first frame")
        os.kill(proc.pid, signal.SIGINT)
        rc = proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text = err_path.read_text()
    assert rc == EXIT_INTERRUPTED, text[-2000:]
    assert "paused and saved; resume with: capture --resume" in text
    (info,) = list_sessions(out)
    assert info.state == "paused"
