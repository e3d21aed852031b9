"""Crash and resume: a session killed with SIGKILL mid-way continues from its journal."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from engine_helpers import assert_rig_safe, small_rig_config, small_sweep

from m2s2hil.engine.build import build_run
from m2s2hil.engine.runner import interrupted_sessions
from m2s2hil.engine.state import RunState
from m2s2hil.rig.factory import open_simulated_rig
from m2s2hil.store.session import SessionStore

TESTS = Path(__file__).parent

# The child runs a real session and prints one line per stored frame; each stored frame
# is followed by a short real-time pause so the parent can kill it mid-session.
CHILD = textwrap.dedent("""
    import sys, time
    sys.path.insert(0, {tests!r})
    from engine_helpers import small_rig_config, small_sweep
    from m2s2hil.engine.build import build_run
    from m2s2hil.engine.options import EngineOptions
    from m2s2hil.engine.state import FrameStored
    from m2s2hil.rig.factory import open_simulated_rig

    cfg = small_rig_config()
    sweep = small_sweep(azimuth_step_deg=45)
    rig = open_simulated_rig(cfg)

    def on_event(e):
        if isinstance(e, FrameStored):
            print("stored", e.event_id, flush=True)
            time.sleep(0.3)

    options = EngineOptions(process_depth=1, store_depth=1)
    build_run(rig, {root!r}, sweep=sweep, session_id="crashy", options=options,
              on_event=on_event).run()
    print("finished", flush=True)
""")


@pytest.mark.slow  # a child process killed mid-session: ~2 s
def test_kill_9_mid_session_then_resume_loses_and_duplicates_nothing(tmp_path) -> None:
    root = tmp_path / "data"
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD.format(tests=str(TESTS), root=str(root))],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    stored: list[str] = []
    try:
        deadline = time.monotonic() + 60
        while len(stored) < 3:
            line = child.stdout.readline()
            assert line, f"child ended early: {child.stderr.read()[-2000:]}"
            assert time.monotonic() < deadline, "child too slow"
            if line.startswith("stored"):
                stored.append(line.split()[1])
        os.kill(child.pid, signal.SIGKILL)
    finally:
        child.wait(timeout=30)
        child.stdout.close()
        child.stderr.close()
    assert child.returncode == -signal.SIGKILL

    cfg = small_rig_config()
    planned = small_sweep(azimuth_step_deg=45).expand(cfg)
    with SessionStore.open(root, "crashy") as crashed:
        before = crashed.completed_event_ids()
        assert set(stored) <= before < {e.event_id for e in planned}  # mid-way, journal intact
        assert crashed.state == "running"  # it never got to say otherwise

    assert interrupted_sessions(root) == ["crashy"]  # what a restarted daemon picks up
    rig = open_simulated_rig(cfg)
    try:
        engine = build_run(rig, root, resume="crashy")
        assert engine.status().done == len(before)
        final = engine.run()
        assert final.state is RunState.COMPLETED and final.done == final.total == len(planned)
        store = engine.store
        frame_ids = [f.event_id for f in store.frames()]
        assert sorted(frame_ids) == sorted(e.event_id for e in planned if e.kind == "frame")
        assert len(frame_ids) == len(set(frame_ids))  # none twice
        assert [d.dark_id for d in store.darks()] == [e.event_id for e in planned if e.kind == "dark"]
        assert store.verify() == []  # checksums valid, no orphans left by the killed writer
        # frames corrected after the resume record the same dark provenance as those before it
        # (the dark reloaded from the journal, read noise and all)
        by_dark: dict[str, list[dict]] = {}
        for f in store.frames():
            by_dark.setdefault(f.dark_id, []).append(f.meta["dark"])
        assert all(p == ps[0] for ps in by_dark.values() for p in ps)
        assert any(p["read_noise_dn"] is not None for ps in by_dark.values() for p in ps)
        assert store.state == "completed" and interrupted_sessions(root) == []
        # the resumed run captured exactly what was missing
        resumed = [e["payload"] for e in store.events() if e["kind"] == "run_started"]
        assert [r["done_before"] for r in resumed] == [0, len(before)]
        assert_rig_safe(rig)
        store.close()
    finally:
        rig.close()


def test_resume_refuses_a_different_rig(tmp_path) -> None:
    import pytest

    from m2s2hil.engine.build import RigChanged

    cfg = small_rig_config()
    SessionStore.create(tmp_path, small_sweep(), cfg, session_id="s").close()
    other = small_rig_config(size=512)
    rig = open_simulated_rig(other)
    try:
        with pytest.raises(RigChanged, match="different rig configuration"):
            build_run(rig, tmp_path, resume="s")
    finally:
        rig.close()


def test_a_session_another_process_writes_cannot_be_resumed_here(tmp_path) -> None:
    """The owner lock is a real inter-process lock: while a second process holds the session
    open for writing, a resume here is refused with one line naming that process."""
    import pytest

    from m2s2hil.store.owner_lock import SessionLocked

    cfg = small_rig_config()
    SessionStore.create(tmp_path, small_sweep(), cfg, session_id="busy").close()
    holder = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(f"""
            import sys
            from m2s2hil.store.session import SessionStore
            st = SessionStore.open({str(tmp_path)!r}, "busy", mode="write")
            print("holding", flush=True)
            sys.stdin.readline()
            st.close()
        """)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "holding"
        rig = open_simulated_rig(cfg)
        try:
            with pytest.raises(SessionLocked, match=f"process {holder.pid}"):
                build_run(rig, tmp_path, resume="busy")
            assert rig.world.lamps_on() == frozenset()
        finally:
            rig.close()
    finally:
        holder.communicate("\n", timeout=30)
    # once the holder has gone, the session is ours
    SessionStore.open(tmp_path, "busy", mode="write").close()
