"""Exports are one at a time per output folder and all or nothing (m2s2hil.daemon.export_lock):
a second export while one runs is refused at once, in this process, from another process and
through the daemon (409); a ``kill -9`` mid-export leaves nothing that looks complete."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from api_support import daemon, small_rig_config, sweep
from cli_support import run_cli
from shared_sessions import N, export_session_of

from m2s2hil.daemon.export_lock import STAGING_MARK, ExportBusy, export_lock, export_once

LAYOUTS = ["m2s2", "hf", "zarr"]
#: What a complete export of the shared 16-frame session holds, by layout: the file written last.
COMPLETE = {"m2s2": "metadata/{sid}.json", "hf": "metadata/{sid}.json", "zarr": "raw/zarr.json"}


def _leftovers(out: Path) -> list[Path]:
    return [p for p in out.parent.iterdir() if STAGING_MARK in p.name and not p.name.endswith("-lock")]


def _tree(folder: Path) -> dict[str, int]:
    return {p.relative_to(folder).as_posix(): p.stat().st_ino
            for p in sorted(folder.rglob("*")) if p.is_file()}


_HOLDER = """
import sys, time
from pathlib import Path
from m2s2hil.daemon.export_lock import export_lock
with export_lock(Path(sys.argv[1])):
    print("held", flush=True)
    sys.stdin.read()
"""

#: An export in a child process that stops for good after reading 3 raw frames (every layout reads
#: them one by one), so the parent can kill it there.
_STALLED = """
import sys, time
from pathlib import Path
from m2s2hil.daemon.export_lock import export_once
from m2s2hil.store.session import SessionStore
reads = 0
real = SessionStore.read_raw
def read_raw(self, event_id):
    global reads
    reads += 1
    if reads > 3:
        print("stalled", flush=True)
        time.sleep(600)
    return real(self, event_id)
SessionStore.read_raw = read_raw
root, sid, out, layout, overwrite = sys.argv[1:]
with SessionStore.open(Path(root), sid) as store:
    export_once(store, Path(out), layout, overwrite=overwrite == "1", fresh=overwrite == "1")
"""


def test_a_held_export_refuses_another_in_this_process(shared_sessions, tmp_path) -> None:
    written = export_session_of(shared_sessions)
    out = tmp_path / "out"
    with written.open() as store, export_lock(out), pytest.raises(ExportBusy, match="another export"):
        export_once(store, out, "m2s2")
    assert not out.exists()
    with written.open() as store:
        assert export_once(store, out, "m2s2").images == 16  # released


def test_an_export_in_another_process_refuses_this_one(shared_sessions, tmp_path) -> None:
    written = export_session_of(shared_sessions)
    out = tmp_path / "out"
    holder = subprocess.Popen([sys.executable, "-c", _HOLDER, str(out)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        with written.open() as store, pytest.raises(ExportBusy, match=rf"pid {holder.pid}\b"):
            export_once(store, out, "m2s2")
        cli = run_cli("export", written.session_id, "--root", written.root, "--out", out)
        assert cli.exit_code == 1, cli.output
        assert "another export is writing" in cli.stderr
    finally:
        holder.communicate("", timeout=30)
    assert not out.exists()


@pytest.mark.slow  # a child interpreter per layout, killed mid-export: seconds each
@pytest.mark.parametrize("layout", LAYOUTS)
def test_a_killed_export_leaves_nothing_that_looks_complete(shared_sessions, tmp_path, layout) -> None:
    written = export_session_of(shared_sessions)
    out = tmp_path / "exports" / layout

    def stalled_export(overwrite: bool) -> None:
        child = subprocess.Popen([sys.executable, "-c", _STALLED, str(written.root), written.session_id,
                                  str(out), layout, "1" if overwrite else "0"],
                                 stdout=subprocess.PIPE, text=True)
        try:
            assert child.stdout is not None and child.stdout.readline().strip() == "stalled"
            assert _leftovers(out), "the export writes beside its folder"
        finally:
            child.kill()  # SIGKILL: no cleanup of any kind
            child.wait(timeout=30)

    stalled_export(overwrite=False)
    assert not out.exists()  # nothing under the export's name at all
    with written.open() as store:
        assert export_once(store, out, layout).images == 16  # the lock died with the process
    assert not _leftovers(out)  # the dead export's staging folder is gone
    before = _tree(out)
    assert COMPLETE[layout].format(sid=written.session_id) in before
    stalled_export(overwrite=True)
    assert _tree(out) == before  # the complete export is untouched, file for file


def test_the_cli_export_adds_to_a_folder_and_overwrites_in_place(shared_sessions, tmp_path) -> None:
    """Merging two sessions into one folder and --overwrite keep working through the staging folder."""
    a, b = export_session_of(shared_sessions), export_session_of(shared_sessions, "iss", "B1")
    out = tmp_path / "merged"
    for w in (a, b, a):
        args = ["--overwrite"] if w is a and (out / "metadata" / f"{b.session_id}.json").exists() else []
        cli = run_cli("export", w.session_id, "--root", w.root, "--out", out, *args)
        assert cli.exit_code == 0, cli.output
    csvs = {p.name for p in (out / "metadata").glob("*.csv")}
    assert csvs == {f"{a.session_id}.csv", f"{b.session_id}.csv"}
    assert len(list((out / "HIL").rglob("*.png"))) == 32
    assert not _leftovers(out)


def _export(d, sid: str, body: dict, statuses: list[int], lock: threading.Lock) -> None:
    r = d.client.post(f"/sessions/{sid}/export", json=body)
    with lock:
        statuses.append(r.status_code)


def test_the_daemon_answers_409_while_an_export_of_the_session_runs(tmp_path) -> None:
    with daemon(tmp_path / "data", rig_config=small_rig_config(N)) as d:
        sid = d.client.post("/sessions", json=sweep()).json()["session_id"]
        assert d.wait_done(sid)["state"] == "completed"
        out = d.root / "exports" / sid / "m2s2"
        with export_lock(out):
            r = d.client.post(f"/sessions/{sid}/export", json={"layout": "m2s2", "overwrite": True})
            assert r.status_code == 409, r.text
            assert "another export is writing" in r.json()["detail"]
        assert not out.exists()
        # Five at once, one of them overwriting: each is done whole or refused; never a 5xx.
        statuses: list[int] = []
        lock = threading.Lock()
        bodies = [{"layout": "m2s2"}] * 4 + [{"layout": "m2s2", "overwrite": True}]
        threads = [threading.Thread(target=_export, args=(d, sid, b, statuses, lock)) for b in bodies]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=120)
        assert sorted(set(statuses)) <= [201, 409, 422] and 201 in statuses, statuses
        meta = json.loads((out / "metadata" / f"{sid}.json").read_text())
        frames = len(d.client.get(f"/sessions/{sid}/frames").json()["items"])
        assert meta["session_id"] == sid and len(list((out / "HIL").rglob("*.png"))) == frames
        assert not _leftovers(out)
