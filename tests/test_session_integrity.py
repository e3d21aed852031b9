"""A session never lies (issue 12): readers change nothing, resume verifies, a damaged journal
is found before it is written, gaps are not success, disk and folder problems are one line.

Each test here failed on the code before issue 12 (F1-F4, F6, F7 of the issue)."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from collections import namedtuple
from pathlib import Path

import pytest
from engine_helpers import assert_rig_safe, session, small_rig_config, small_sweep

from m2s2hil.commands.capture import EXIT_FAILED, EXIT_GAPS, EXIT_PAUSED, _run_engine
from m2s2hil.engine.build import build_run
from m2s2hil.engine.runner import SessionFailed
from m2s2hil.engine.state import RunState
from m2s2hil.rig.factory import open_simulated_rig
from m2s2hil.store.catalogue import list_sessions
from m2s2hil.store.errors import ReadOnlySession, SessionDamaged
from m2s2hil.store.owner_lock import SessionLocked
from m2s2hil.store.repair import repair_session
from m2s2hil.store.session import SessionStore

S = RunState
FRAME_IDS = ["weak/E1/az000/f0", "weak/E1/az090/f0", "weak/E1/az180/f0", "weak/E1/az270/f0"]


def _cli(*args: str) -> subprocess.CompletedProcess:
    code = "import sys; from m2s2hil.cli import main; sys.argv[0] = 'm2s2hil'; main()"
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=60)


def _completed(tmp_path: Path, sid: str = "s1") -> Path:
    """A completed 4-frame session; returns the data root."""
    with session(tmp_path, session_id=sid) as (_rig, _store, engine, _events):
        assert engine.run().state is S.COMPLETED
    return tmp_path / "data"


def _digest(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _m2s2hil(monkeypatch, capsys, *args: str) -> tuple[int, str, str]:
    """``m2s2hil ARGS`` in this process: (exit code, stdout, stderr)."""
    from m2s2hil.cli import main

    monkeypatch.setattr(sys, "argv", ["m2s2hil", *args])
    with pytest.raises(SystemExit) as info:
        main()
    out = capsys.readouterr()
    return int(info.value.code or 0), out.out, out.err


# -- F1: reading never changes a session; only the lock holder cleans --------------------------

@pytest.mark.slow  # a writer process: ~4 s
def test_readers_leave_a_live_writers_temporary_files_alone(tmp_path) -> None:
    root = _completed(tmp_path)
    writer = SessionStore.open(root, "s1", mode="write")
    try:
        tmp = writer.path / "frames" / ".weak_E1_az000_f0.raw.tiff.tmp-4242-abcd"
        tmp.write_bytes(b"half a frame")  # what the writer is in the middle of
        # A second process: `sessions show --verify` while the writer holds the lock.
        res = _cli("sessions", "show", "s1", "--verify", "--root", str(root))
        assert res.returncode == 0, res.stderr
        assert "integrity: ok" in res.stdout
        assert tmp.exists(), "a reader deleted the live writer's temporary file"
        # The same in this process: a read-only store, a second would-be writer.
        with SessionStore.open(root, "s1") as reader:
            assert reader.verify() == []
            with pytest.raises(ReadOnlySession):
                reader.record_event("note", {})
        with pytest.raises(SessionLocked, match="being written by process"):
            SessionStore.open(root, "s1", mode="write")
        assert [s.session_id for s in list_sessions(root)] == ["s1"] and tmp.exists()
    finally:
        writer.close()
    # Nobody writes now: a reader reports the leftover, only the next owner removes it.
    with SessionStore.open(root, "s1") as reader:
        assert [p.kind for p in reader.verify()] == ["temporary"]
    assert tmp.exists()
    SessionStore.open(root, "s1", mode="write").close()
    assert not tmp.exists()


def test_show_verify_list_and_export_leave_the_session_folder_byte_for_byte_unchanged(
        tmp_path, monkeypatch, capsys) -> None:
    root = _completed(tmp_path)

    def snapshot() -> dict[str, tuple[int, int, str]]:
        return {p.relative_to(root).as_posix(): (p.stat().st_size, p.stat().st_mtime_ns,
                                                 _digest(p) if p.is_file() else "")
                for p in root.rglob("*")}

    before = snapshot()
    for args in (("sessions", "list", "--root", str(root)),
                 ("sessions", "show", "s1", "--verify", "--root", str(root)),
                 ("export", "s1", "--layout", "m2s2", "--out", str(tmp_path / "out"), "--root", str(root))):
        code, _out, err = _m2s2hil(monkeypatch, capsys, *args)
        assert code == 0, (args, err)
    assert snapshot() == before  # no file added (not even -wal/-shm), none changed


# -- F2: resume verifies what is stored before trusting it -------------------------------------

def test_resume_moves_a_missing_and_a_truncated_frame_aside_and_captures_them_again(tmp_path) -> None:
    root = _completed(tmp_path)
    with SessionStore.open(root, "s1") as st:
        raws = {f.event_id: st.path / f.files["raw"].path for f in st.frames()}
    raws[FRAME_IDS[1]].unlink()
    damaged = raws[FRAME_IDS[2]]
    damaged.write_bytes(damaged.read_bytes()[:1000])  # truncated
    rig = open_simulated_rig(small_rig_config())
    try:
        engine = build_run(rig, root, resume="s1")
        assert {e for e in engine.store.completed_event_ids() if "/E1/" in e} == {FRAME_IDS[0], FRAME_IDS[3]}
        final = engine.run()
        assert final.state is S.COMPLETED and final.done == final.total
        store = engine.store
        assert sorted(f.event_id for f in store.frames()) == FRAME_IDS  # each once
        assert store.verify() == []
        q = [e["payload"] for e in store.events() if e["kind"] == "quarantined"]
        assert sorted(p["event_id"] for p in q) == [FRAME_IDS[1], FRAME_IDS[2]]
        assert all(p["row"]["files"] for p in q)  # the journal row is kept in the event
        kept = list((store.path / "quarantine").rglob("*.raw.tiff"))
        assert [k.stat().st_size for k in kept] == [1000]  # the damaged file is kept, not deleted
        store.close()
        assert_rig_safe(rig)
    finally:
        rig.close()


# -- F3: a damaged journal ---------------------------------------------------------------------

def _damage(journal: Path) -> None:
    data = bytearray(journal.read_bytes())
    page = 4096
    assert len(data) >= 4 * page
    data[2 * page:3 * page] = os.urandom(page)  # random bytes over a page (not the header)
    journal.write_bytes(bytes(data))


def test_a_damaged_journal_is_found_before_anything_is_written_and_repair_rebuilds_it(
        tmp_path, monkeypatch, capsys) -> None:
    root = _completed(tmp_path / "a", "good")
    _completed(tmp_path / "b", "bad")
    os.replace(tmp_path / "b" / "data" / "bad", root / "bad")
    journal = root / "bad" / "journal.sqlite"
    _damage(journal)
    before = _digest(journal)

    listed = {s.session_id: s for s in list_sessions(root)}
    assert listed["good"].state == "completed"
    assert listed["bad"].state == "damaged" and listed["bad"].error
    code, out, err = _m2s2hil(monkeypatch, capsys, "sessions", "list", "--root", str(root))
    assert code == 0 and "good" in out and "sessions repair bad" in out
    for args in (("show", "bad"), ("show", "bad", "--verify")):
        code, out, err = _m2s2hil(monkeypatch, capsys, "sessions", *args, "--root", str(root))
        assert code == 1 and "Traceback" not in err
        assert len(err.strip().splitlines()) == 1 and "sessions repair bad" in err

    rig = open_simulated_rig(small_rig_config())
    try:
        with pytest.raises(SessionDamaged, match="sessions repair bad"):
            build_run(rig, root, resume="bad")
        assert _digest(journal) == before  # refused before writing anything
        assert rig.world.lamps_on() == frozenset()

        report = repair_session(root, "bad")
        assert (report.frames, report.darks, report.quarantined) == (4, 1, [])
        assert (root / "bad" / report.kept_journal).exists()
        with SessionStore.open(root, "bad") as st:
            assert st.verify() == [] and st.state == "completed"
            assert sorted(f.event_id for f in st.frames()) == FRAME_IDS
            assert st.frames()[0].meta["session_id"] == "bad"
        # The repaired session resumes like any other: nothing left to capture.
        engine = build_run(rig, root, resume="bad")
        assert engine.run().state is S.COMPLETED
        engine.store.close()
    finally:
        rig.close()


def test_repair_without_a_manifest_quarantines_a_damaged_frame_for_the_resume(tmp_path) -> None:
    root = _completed(tmp_path)
    folder = root / "s1"
    (folder / "manifest.json").unlink()  # e.g. killed before completion
    raw = next((folder / "frames").glob("weak_E1_az090_f0.raw.tiff"))
    raw.write_bytes(raw.read_bytes()[:2000])
    _damage(folder / "journal.sqlite")
    report = repair_session(root, "s1")
    assert report.frames == 3 and report.state == "paused"
    assert any(q.endswith("weak_E1_az090_f0.raw.tiff") for q in report.quarantined)
    rig = open_simulated_rig(small_rig_config())
    try:
        engine = build_run(rig, root, resume="s1")
        assert engine.run().state is S.COMPLETED
        assert sorted(f.event_id for f in engine.store.frames()) == FRAME_IDS
        assert engine.store.verify() == []
        engine.store.close()
    finally:
        rig.close()


def test_repair_leaves_a_sound_journal_alone_unless_forced(tmp_path) -> None:
    from m2s2hil.errors import UsageError

    root = _completed(tmp_path)
    before = _digest(root / "s1" / "journal.sqlite")
    with pytest.raises(UsageError, match="journal is sound"):
        repair_session(root, "s1")
    assert _digest(root / "s1" / "journal.sqlite") == before
    report = repair_session(root, "s1", force=True)
    assert (report.frames, report.darks, report.state) == (4, 1, "completed")
    with SessionStore.open(root, "s1") as st:
        assert st.verify() == [] and [e["kind"] for e in st.events()][-1] == "repaired"


# -- F4: gaps are not plain success; nothing stored is failure; the fault count is exact -------

def test_a_camera_that_times_out_for_good_after_two_frames_is_completed_with_gaps(tmp_path) -> None:
    # Darks take 2 camera frames each; "after" lets the dark and two light frames through.
    faults = {"toucan": [{"kind": "frame_timeout", "count": -1, "after": 4}]}
    sweep = small_sweep(azimuth_step_deg=20)  # 18 frames: 4 timeouts each, far more than 50 faults
    with session(tmp_path, sweep, faults=faults) as (rig, store, engine, _events):
        code = _run_engine(engine, virtual=True)
        st = engine.status()
        assert code == EXIT_GAPS and st.state is S.COMPLETED_WITH_GAPS
        assert store.state == "completed_with_gaps"
        assert len(store.frames()) == 2 and st.skipped == 16
        journal_faults = sum(e["kind"] == "fault" for e in store.events())
        assert journal_faults > 50 and st.fault_count == journal_faults
        finished = [e for e in store.events() if e["kind"] == "run_finished"][-1]["payload"]
        assert finished["faults"] == journal_faults and finished["state"] == "completed_with_gaps"
        assert (store.path / "manifest.json").exists()
        assert_rig_safe(rig)


def test_a_relay_stuck_off_stores_nothing_and_the_session_fails(tmp_path) -> None:
    faults = {"relays": [{"kind": "relay_stuck", "count": -1, "channel": ch} for ch in range(8)]}
    with session(tmp_path, faults=faults) as (rig, store, engine, _events):
        code = _run_engine(engine, virtual=True)
        st = engine.status()
        assert code == EXIT_FAILED and st.state is S.FAILED
        assert "no frame stored" in (st.error or "")
        assert store.state == "failed" and store.frames() == []
        assert len(store.skips()) == 4
        assert_rig_safe(rig)


def test_run_raises_session_failed_when_nothing_was_stored(tmp_path) -> None:
    faults = {"toucan": [{"kind": "frame_timeout", "count": -1, "after": 2}]}
    with session(tmp_path, faults=faults) as (_rig, _store, engine, _events), \
            pytest.raises(SessionFailed, match="no frame stored"):
        engine.run()


# -- F6 / F7: the disk and the output folder, through the `capture` command ----------------------

def _capture(monkeypatch, capsys, *args: str) -> tuple[int, str]:
    from m2s2hil.cli import capture_main

    monkeypatch.setattr(sys, "argv", ["capture", *args])
    with pytest.raises(SystemExit) as info:
        capture_main()
    out = capsys.readouterr()
    return int(info.value.code or 0), out.out + out.err


def _small_rig_file(tmp_path: Path) -> Path:
    import tomli_w

    p = tmp_path / "rig.toml"
    p.write_text(tomli_w.dumps(small_rig_config().model_dump(mode="json", exclude_none=True)))
    return p


ARGS = ("--sat", "voyager", "--build", "B3", "--light", "weak", "--tilt", "E1", "--azimuth-step", "90")


def test_too_little_disk_at_the_start_pauses_resumably_with_exit_3(tmp_path, monkeypatch, capsys) -> None:
    import shutil

    real = shutil.disk_usage
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10**9, 10**9 - 8 * 10**6, 8 * 10**6))
    rig = _small_rig_file(tmp_path)
    out = tmp_path / "data"
    code, text = _capture(monkeypatch, capsys, *ARGS, "--rig", str(rig), "--out", str(out))
    assert code == EXIT_PAUSED, text
    (info,) = list_sessions(out)
    assert info.state == "paused" and info.frames == 0
    assert f"resume with: capture --resume {info.session_id} --out {out}" in " ".join(text.split())
    monkeypatch.setattr(shutil, "disk_usage", real)  # space freed
    code, text = _capture(monkeypatch, capsys, "--resume", info.session_id, "--rig", str(rig),
                          "--out", str(out))
    assert code == 0, text
    assert list_sessions(out)[0].state == "completed"


def test_a_read_only_output_folder_is_one_line_naming_it_and_exit_2(tmp_path, monkeypatch, capsys) -> None:
    out = tmp_path / "ro"
    out.mkdir()
    real = os.statvfs

    class _ReadOnly:
        def __init__(self, st: os.statvfs_result) -> None:
            self._st = st
            self.f_flag = st.f_flag | os.ST_RDONLY
            self.f_bavail, self.f_frsize = 0, st.f_frsize  # a full-looking small read-only mount

    monkeypatch.setattr(os, "statvfs",
                        lambda p: _ReadOnly(real(p)) if str(p).startswith(str(out)) else real(p))
    rig = _small_rig_file(tmp_path)
    code, text = _capture(monkeypatch, capsys, *ARGS, "--rig", str(rig), "--out", str(out))
    assert code == 2, text
    lines = [ln for ln in text.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1 and str(out) in lines[0] and "read-only" in lines[0]
    assert "Traceback" not in text and "disk full" not in text
    assert list(out.iterdir()) == []


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes through file permissions")
def test_an_unwritable_output_folder_by_permissions(tmp_path, monkeypatch, capsys) -> None:
    out = tmp_path / "locked"
    out.mkdir(mode=0o555)
    rig = _small_rig_file(tmp_path)
    code, text = _capture(monkeypatch, capsys, *ARGS, "--rig", str(rig), "--out", str(out))
    assert code == 2 and str(out) in text and "Traceback" not in text


# -- F5: teardown reconnects a device that vanished; data and rig outcomes apart ---------------

def test_a_stage_port_vanishing_during_teardown_is_reopened_and_the_data_kept(tmp_path) -> None:
    from m2s2hil.engine.state import FrameStored

    with session(tmp_path) as (rig, store, engine, _events):
        stage = rig.sims["stage"]
        stored = []

        def vanish_after_last(e) -> None:
            if isinstance(e, FrameStored):
                stored.append(e.event_id)
                if len(stored) == len(FRAME_IDS):
                    stage.vanish(0.5)  # the USB adapter drops out as the run ends

        engine.subscribe(vanish_after_last)
        st = engine.run()
        assert st.state is S.COMPLETED and engine.rig_safe is True
        teardown = [f for f in st.faults if f.action == "teardown"]
        assert teardown and all(f.fault_class == "device_gone" and f.device == "stage" for f in teardown)
        finished = [e for e in store.events() if e["kind"] == "run_finished"][-1]["payload"]
        assert finished["state"] == "completed" and finished["rig_safe"] is True
        assert (store.path / "manifest.json").exists() and store.verify() == []
        assert_rig_safe(rig)


# -- through the daemon: an e-stopped session resumes once the operator clears the stop ---------

@pytest.mark.slow
def test_an_estopped_session_resumes_after_the_operator_clears_the_stop(tmp_path) -> None:
    from api_support import daemon, sweep

    with daemon(tmp_path / "data") as d:
        sid = d.client.post("/sessions", json=sweep(azimuth_step_deg=15)).json()["session_id"]
        d.wait(sid, lambda s: s["state"] == "running" and s["done"] >= 3)
        assert d.client.post("/rig/stop").json()["session_state"] == "aborted"
        with SessionStore.open(d.root, sid) as st:
            assert st.state == "estopped"
        r = d.client.post(f"/sessions/{sid}/resume")  # the stop is not cleared yet
        assert r.status_code == 409 and "emergency stop" in r.json()["detail"]
        assert d.client.post("/queue/release").json()["held"] is None  # the operator clears it
        r = d.client.post(f"/sessions/{sid}/resume")
        assert r.status_code == 200, r.text
        st = d.wait_done(sid, timeout=120)
        assert st["state"] == "completed" and st["done"] == st["total"]
        with SessionStore.open(d.root, sid) as store:
            ids = [f.event_id for f in store.frames()]
            assert len(ids) == len(set(ids)) == 24 and store.verify() == []
        assert d.rig.world.lamps_on() == frozenset()


# -- F8: a relay's I/O error names the relay board and is a device fault ----------------------

def test_a_relay_boards_io_error_on_a_vanished_pty_names_the_board_and_is_device_gone() -> None:
    from m2s2hil.drivers.clock import SystemClock
    from m2s2hil.drivers.errors import DeviceGone
    from m2s2hil.drivers.modbus_relay import ModbusRelayBoard
    from m2s2hil.simulators.modbus_relay import ModbusRelaySim
    from m2s2hil.simulators.pty import PtyServer

    from m2s2hil.engine.fault_policy import fault_class_of

    clock = SystemClock()
    srv = PtyServer(ModbusRelaySim("mb-gone", clock)).start()
    board = ModbusRelayBoard(srv.path, device="lamp-relays", clock=clock, timeout_s=0.3, retries=1,
                             reconnect_attempts=2, reconnect_interval_s=0.05)
    try:
        board.connect()
        board.set([1])
        srv.close()  # the USB adapter is pulled: the pty goes away under the open port (EIO)
        with pytest.raises(DeviceGone) as info:
            board.set([])
        err = info.value
        assert err.device == "lamp-relays" and str(err).startswith("lamp-relays")
        assert fault_class_of(err) == "device_gone"
    finally:
        srv.close()
        board.close()


def test_capture_resume_of_a_damaged_session_refuses_before_the_rig_opens(tmp_path, monkeypatch,
                                                                          capsys) -> None:
    root = _completed(tmp_path)
    _damage(root / "s1" / "journal.sqlite")

    def no_rig(*a, **kw):
        raise AssertionError("the rig was opened for a session that cannot be resumed")

    monkeypatch.setattr("m2s2hil.engine.build.open_capture_rig", no_rig)
    code, text = _capture(monkeypatch, capsys, "--resume", "s1", "--out", str(root))
    errors = [ln for ln in text.splitlines() if ln.startswith("error:")]
    assert code == 1 and len(errors) == 1
    assert "journal damaged" in errors[0] and "m2s2hil sessions repair s1" in " ".join(text.split())


def test_a_frame_damaged_after_it_was_stored_fails_the_run_and_the_resume_recaptures_it(tmp_path) -> None:
    from m2s2hil.engine.state import FrameStored

    with session(tmp_path) as (rig, store, engine, _events):
        def damage_first(e) -> None:
            if isinstance(e, FrameStored) and e.event_id == FRAME_IDS[0]:
                raw = store.path / e.path
                raw.write_bytes(raw.read_bytes()[:-10] + b"0123456789")  # same size, other bytes

        engine.subscribe(damage_first)
        with pytest.raises(SessionFailed, match="failed the final check"):
            engine.run()
        assert store.state == "failed" and not (store.path / "manifest.json").exists()
        assert_rig_safe(rig)
    root = tmp_path / "data"
    rig = open_simulated_rig(small_rig_config())
    try:
        engine = build_run(rig, root, resume="s1")
        assert [p.kind for p in engine.quarantined] == ["checksum"]
        assert engine.run().state is S.COMPLETED
        assert engine.store.verify() == [] and sorted(f.event_id for f in engine.store.frames()) == FRAME_IDS
        engine.store.close()
    finally:
        rig.close()
