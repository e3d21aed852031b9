"""The session store: atomic checksummed files, the SQLite journal, resume, full disks."""

from __future__ import annotations

import errno
import hashlib
import io
import json
import sqlite3
import threading

import cv2
import numpy as np
import pytest
import tifffile

import m2s2hil.atomic as atomic
from m2s2hil.atomic import DiskFull, check_free_space
from m2s2hil.config import RigConfig, StorageConfig, default_rig
from m2s2hil.errors import M2S2Error, UsageError
from m2s2hil.plan import Sweep
from m2s2hil.store.catalogue import default_data_root, list_sessions
from m2s2hil.store.errors import SessionCorrupt, SessionExists, SessionNotFound
from m2s2hil.store.estimates import estimate_frame_bytes
from m2s2hil.store.frame_files import InvalidImage
from m2s2hil.store.frame_meta import MetadataConflict
from m2s2hil.store.journal import DuplicateEvent
from m2s2hil.store.session import SessionStore

N = 64


def small_rig() -> RigConfig:
    data = default_rig().model_dump(mode="json")
    data["camera"]["model"].update(width=N, height=N)
    return RigConfig.model_validate(data)


@pytest.fixture
def rig() -> RigConfig:
    return small_rig()


@pytest.fixture
def sweep() -> Sweep:
    return Sweep(satellite="hubble", build="B2", lighting=["weak"], tilts=["E1"], azimuth_step_deg=90,
                 dark={"frames": 2})


@pytest.fixture
def store(tmp_path, sweep, rig):
    st = SessionStore.create(tmp_path / "data", sweep, rig, session_id="s1")
    yield st
    st.close()


def raw_of(i: int) -> np.ndarray:
    return ((np.arange(N * N, dtype=np.uint32).reshape(N, N) * 7 + i) % 1024).astype(np.uint16)


def frame_events(st: SessionStore):
    return [e for e in st.sweep.expand(st.rig) if e.kind == "frame"]


def write(st: SessionStore, ev, i: int = 0, **kw):
    cube = np.random.default_rng(i).random((N // 4, N // 4, 10)).astype(np.float32)
    preview = np.zeros((N // 4, N // 4, 3), np.uint8)
    meta = {"temperature_c": 31.5, "pose": {"turntable_deg": ev.azimuth_deg, "tilt_deg": ev.tilt_deg}}
    return st.write_frame(ev, raw_of(i), cube, preview, meta, **kw)


def test_create_makes_a_wal_journal_and_copies_of_the_plan(store, tmp_path, sweep, rig):
    path = tmp_path / "data" / "s1"
    assert store.path == path and (path / "journal.sqlite").is_file()
    assert Sweep.from_json((path / "sweep.json").read_text()) == sweep
    assert json.loads((path / "rig.json").read_text()) == rig.model_dump(mode="json")
    assert store.journal.pragma("journal_mode") == "wal"
    assert store.journal.pragma("synchronous") == 2  # FULL
    with sqlite3.connect(path / "journal.sqlite") as db:  # persisted in the file, not per connection
        assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        row = db.execute("SELECT state, rig_digest, software_version FROM session").fetchone()
    assert row[0] == "created" and row[1] == rig.digest and row[2]
    assert not list((tmp_path / "data").glob(".*"))  # no staging folder left behind
    with pytest.raises(SessionExists):
        SessionStore.create(tmp_path / "data", sweep, rig, session_id="s1")


def test_generated_session_id_names_the_sweep(tmp_path, sweep, rig):
    with SessionStore.create(tmp_path, sweep, rig) as st:
        assert st.session_id.split("-")[1:4] == ["hubble", "B2", "weak"]
        assert len(st.session_id.split("-")[0]) == len("20261124T213000")


def test_frame_files_checksums_and_tiff_metadata(store):
    ev = frame_events(store)[1]
    rec = write(store, ev, 3)
    assert set(rec.files) == {"raw", "preview"}  # the cube is computed when read (test_storage_format.py)
    for f in rec.files.values():
        data = (store.path / f.path).read_bytes()
        assert hashlib.sha256(data).hexdigest() == f.sha256 and len(data) == f.bytes
    with tifffile.TiffFile(store.path / rec.files["raw"].path) as tf:
        arr = tf.asarray()
        desc = json.loads(tf.pages[0].description)
    assert desc.pop("shape") == list(arr.shape)  # for tifffile's shaped-series reader
    assert arr.dtype == np.uint16 and np.array_equal(arr, raw_of(3))
    assert desc["event"]["event_id"] == ev.event_id
    assert desc["exposure_s"] == ev.exposure_s and desc["gain"] == ev.gain
    assert desc["temperature_c"] == 31.5 and desc["pose"]["turntable_deg"] == ev.azimuth_deg
    assert desc["rig_digest"] == store.rig.digest and desc["software_version"]
    assert desc["dark_id"] == ev.dark_id and desc["processing_method"] == "superpixel"
    assert desc["cube"]["stored"] is False and desc["cube"]["method"] == "superpixel"
    assert store.frames()[0].meta == desc  # the journal holds the same metadata
    assert store.verify() == []


def test_verify_reports_a_corrupted_and_a_missing_file(store):
    evs = frame_events(store)
    a, b = write(store, evs[0], 0), write(store, evs[1], 1)
    p = store.path / a.files["raw"].path
    data = bytearray(p.read_bytes())
    data[-1] ^= 0xFF
    p.write_bytes(bytes(data))
    (store.path / b.files["preview"].path).unlink()
    problems = {(pr.path, pr.kind) for pr in store.verify()}
    assert problems == {(a.files["raw"].path, "checksum"), (b.files["preview"].path, "missing")}
    with pytest.raises(SessionCorrupt, match="sha256"):
        store.read_raw(evs[0].event_id)


def test_duplicate_event_is_refused_and_not_recorded_twice(store):
    ev = frame_events(store)[0]
    write(store, ev, 0)
    before = (store.path / store.frames()[0].files["raw"].path).read_bytes()
    with pytest.raises(DuplicateEvent):
        write(store, ev, 9)
    assert len(store.frames()) == 1
    assert (store.path / store.frames()[0].files["raw"].path).read_bytes() == before
    dark = store.sweep.expand(store.rig)[0]
    store.write_dark(dark, np.full((N, N), 2.5, np.float32))
    with pytest.raises(DuplicateEvent):
        store.write_dark(dark, np.zeros((N, N), np.float32))


def test_the_same_event_from_two_threads_is_written_once(store):
    ev = frame_events(store)[0]
    outcomes: list[object] = []
    barrier = threading.Barrier(2)

    def go(i: int) -> None:
        barrier.wait()
        try:
            outcomes.append(write(store, ev, i))
        except DuplicateEvent as exc:
            outcomes.append(exc)

    threads = [threading.Thread(target=go, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert sorted(type(o).__name__ for o in outcomes) == ["DuplicateEvent", "FrameRecord"]
    assert len(store.frames()) == 1 and store.verify() == []


def test_reopen_for_resume_knows_what_is_done(tmp_path, sweep, rig):
    st = SessionStore.create(tmp_path, sweep, rig, session_id="r1")
    events = st.sweep.expand(rig)
    st.write_dark(events[0], np.full((N, N), 1.25, np.float32), {"temperature_c": 30.0})
    write(st, events[1], 1)
    st.record_skip(events[2], "camera timeout after 3 attempts", "timeout")
    st.set_state("paused")
    st.record_event("note", {"text": "lamp 4 replaced"})
    st.close()

    st = SessionStore.open(tmp_path, "r1", mode="write")
    assert st.state == "paused"
    assert st.completed_event_ids() == {events[0].event_id, events[1].event_id}
    assert st.skipped_event_ids() == {events[2].event_id}
    assert st.skips()[0].fault_class == "timeout"
    kinds = [e["kind"] for e in st.events()]
    assert kinds == ["created", "dark", "frame", "skip", "state", "note"]
    assert np.array_equal(st.load_dark(events[0].event_id), np.full((N, N), 1.25, np.float32))
    assert st.dark_for(events[0].exposure_s, events[0].gain).dark_id == events[0].event_id
    write(st, events[2], 2)  # the resumed run fills the gap
    assert st.skipped_event_ids() == set()
    s = st.summary()
    assert (s["frames"], s["darks"], s["missing"], s["planned_frames"]) == (2, 1, 2, 4)
    st.close()


def test_a_failing_write_leaves_no_file_under_the_final_name(store, monkeypatch):
    ev = frame_events(store)[0]
    calls = {"n": 0}
    real = atomic._write_fd

    def flaky(fd, data):  # the raw file goes through, the cube dies half-way
        calls["n"] += 1
        if calls["n"] == 2:
            real(fd, bytes(data)[: len(data) // 2])
            raise OSError(errno.EIO, "I/O error")
        real(fd, data)

    monkeypatch.setattr(atomic, "_write_fd", flaky)
    with pytest.raises(OSError, match="I/O error"):
        write(store, ev, 0)
    assert list((store.path / "frames").iterdir()) == []  # neither final files nor temporaries
    assert store.completed_event_ids() == set()
    monkeypatch.setattr(atomic, "_write_fd", real)
    write(store, ev, 0)
    assert store.verify() == []


def test_enospc_is_disk_full_and_the_journal_stays_consistent(store, monkeypatch):
    evs = frame_events(store)
    write(store, evs[0], 0)

    def full(fd, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(atomic, "_write_fd", full)
    with pytest.raises(DiskFull) as info:
        write(store, evs[1], 1)
    assert info.value.fault_class == "disk_full" and isinstance(info.value, M2S2Error)
    assert store.completed_event_ids() == {evs[0].event_id}
    assert store.verify() == []  # no orphan, no temp file, journal intact
    assert store.journal.pragma("integrity_check") == "ok"
    monkeypatch.undo()
    write(store, evs[1], 1)  # after freeing space the same event goes through
    assert store.completed_event_ids() == {evs[0].event_id, evs[1].event_id}


def test_crash_between_files_and_commit_leaves_only_an_orphan_that_resume_overwrites(
        tmp_path, sweep, rig, monkeypatch):
    st = SessionStore.create(tmp_path, sweep, rig, session_id="c1")
    ev = frame_events(st)[0]

    def crash(**kw):
        raise KeyboardInterrupt  # the process dies after the renames, before the commit

    monkeypatch.setattr(st.journal, "add_frame", crash)
    with pytest.raises(KeyboardInterrupt):
        write(st, ev, 0)
    st.close()
    st = SessionStore.open(tmp_path, "c1", mode="write")
    assert ev.event_id not in st.completed_event_ids()
    assert {p.kind for p in st.verify()} == {"orphan"}
    write(st, ev, 5)
    assert st.verify() == []
    raw, _ = st.read_raw(ev.event_id)
    assert np.array_equal(raw, raw_of(5))
    st.close()


def test_check_free_space_and_frame_size_estimate(tmp_path):
    assert check_free_space(tmp_path, 1024) > 0
    with pytest.raises(DiskFull, match="disk full") as info:
        check_free_space(tmp_path / "not" / "yet", 10**18)
    assert info.value.needed > info.value.free
    m = default_rig().camera.model
    # deflate-compressed 10-bit raw (at most 10 bits a pixel + 5 %), no stored cube, RGB preview
    assert estimate_frame_bytes(default_rig()) == int(2048 * 2048 * 10 / 8 * 1.05) + 512 * 512 * 3 + 65536
    cached = default_rig().model_copy(update={"storage": StorageConfig(cubes=True)})
    assert estimate_frame_bytes(cached, "ppid") > 10 * m.width * m.height * 4


def test_disk_full_before_writing_when_space_is_short(store, monkeypatch):
    import shutil

    usage = shutil.disk_usage(store.path)
    monkeypatch.setattr(atomic.shutil, "disk_usage", lambda p: usage._replace(free=1000))
    with pytest.raises(DiskFull):
        write(store, frame_events(store)[0], 0)
    assert list((store.path / "frames").iterdir()) == [] and store.completed_event_ids() == set()


def test_bad_arrays_are_refused_before_anything_is_written(store):
    ev = frame_events(store)[0]
    with pytest.raises(InvalidImage, match="uint16"):
        store.write_frame(ev, raw_of(0).astype(np.float32))
    with pytest.raises(InvalidImage, match="camera gives"):
        store.write_frame(ev, np.zeros((N, N + 4), np.uint16))
    with pytest.raises(InvalidImage, match="bands"):
        store.write_frame(ev, raw_of(0), np.zeros((16, 16, 3), np.float32))
    with pytest.raises(UsageError, match="write_dark"):
        store.write_frame(store.sweep.expand(store.rig)[0], raw_of(0))
    assert store.completed_event_ids() == set() and list((store.path / "frames").iterdir()) == []
    write(store, ev, 0)  # a refused write does not block the event


def test_manifest_and_completion(store):
    events = store.sweep.expand(store.rig)
    store.write_dark(events[0], np.zeros((N, N), np.float32))
    for i, ev in enumerate(events[1:]):
        write(store, ev, i)
    man = store.complete()
    on_disk = json.loads((store.path / "manifest.json").read_text())
    assert on_disk == man and store.state == "completed" and man["state"] == "completed"
    assert len(man["files"]) == 4 * 2 + 1  # raw + preview per frame (cubes are computed), the dark
    for f in man["files"]:
        assert hashlib.sha256((store.path / f["path"]).read_bytes()).hexdigest() == f["sha256"]


def test_open_errors_and_listing(tmp_path, sweep, rig):
    with pytest.raises(SessionNotFound):
        SessionStore.open(tmp_path, "nope")
    with pytest.raises(UsageError, match="invalid session id"):
        SessionStore.open(tmp_path, "../etc")
    SessionStore.create(tmp_path, sweep, rig, session_id="good").close()
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "journal.sqlite").write_bytes(b"this is not a database" * 100)
    with pytest.raises(SessionCorrupt, match="journal damaged .*sessions repair bad"):
        SessionStore.open(tmp_path, "bad")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SessionCorrupt, match="no journal"):
        SessionStore.open(tmp_path, "empty")
    listed = {s.session_id: s for s in list_sessions(tmp_path)}
    assert set(listed) == {"good", "bad"}
    assert listed["good"].state == "created" and listed["good"].satellite == "hubble"
    assert listed["bad"].state == "damaged" and listed["bad"].error


def test_default_data_root(monkeypatch, tmp_path):
    monkeypatch.delenv("M2S2HIL_DATA", raising=False)
    assert str(default_data_root()) == "sessions"
    monkeypatch.setenv("M2S2HIL_DATA", str(tmp_path))
    assert default_data_root() == tmp_path


def test_dark_tiff_is_float32_with_provenance(store):
    dark = store.sweep.expand(store.rig)[0]
    master = np.random.default_rng(1).random((N, N)).astype(np.float32) * 40
    rec = store.write_dark(dark, master, {"temperature_c": 29.0, "frames_used": [1, 2]})
    with tifffile.TiffFile(io.BytesIO((store.path / rec.files["master"].path).read_bytes())) as tf:
        arr, desc = tf.asarray(), json.loads(tf.pages[0].description)
    assert arr.dtype == np.float32 and np.array_equal(arr, master)
    assert desc["n_frames"] == 2 and desc["reduce"] == "mean" and desc["exposure_s"] == dark.exposure_s
    assert rec.n_frames == 2 and rec.meta["temperature_c"] == 29.0


def test_sqlite_full_is_disk_full_and_rolls_back(store):
    evs = frame_events(store)
    write(store, evs[0], 0)
    pages = store.journal.pragma("page_count")
    store.journal.query(f"PRAGMA max_page_count = {pages}")  # SQLite may not grow: SQLITE_FULL
    big = {"notes": "x" * 200_000}
    with pytest.raises(DiskFull):
        store.write_frame(evs[1], raw_of(1), meta=big)
    assert store.completed_event_ids() == {evs[0].event_id}
    assert store.journal.pragma("integrity_check") == "ok"
    store.journal.query("PRAGMA max_page_count = 1073741823")
    store.write_frame(evs[1], raw_of(1), meta=big)  # resume overwrites the orphaned files
    assert store.verify() == []


def test_meta_cannot_forge_provenance_and_nan_becomes_null(store):
    ev = frame_events(store)[0]
    with pytest.raises(MetadataConflict, match="rig_digest, session_id"):
        store.write_frame(ev, raw_of(0), meta={"rig_digest": "forged", "session_id": "other"})
    rec = store.write_frame(ev, raw_of(0), meta={
        "exposure_s": 0.0123, "temperature_c": float("nan"), "pose": {"turntable_deg": np.float64(1.5)}})
    _, desc = store.read_raw(ev.event_id)
    assert desc["rig_digest"] == store.rig.digest and desc["session_id"] == "s1"
    assert desc["exposure_s"] == 0.0123  # the actual exposure overrides the planned one
    assert desc["temperature_c"] is None and desc["pose"]["turntable_deg"] == 1.5
    assert rec.meta == desc


def test_extra_arrays_are_written_checksummed_and_committed_with_the_frame(store):
    evs = frame_events(store)
    labels = (np.arange(N * N).reshape(N, N) % 5).astype(np.int64)
    depth = np.linspace(0, 1, N * N, dtype=np.float32).reshape(N, N)
    rec = store.write_frame(evs[0], raw_of(0), extra={"truth_labels": labels, "depth": depth})
    assert rec.files["truth_labels"].path.endswith(".truth_labels.png")
    assert rec.files["depth"].path.endswith(".depth.tiff")
    got = cv2.imread(str(store.path / rec.files["truth_labels"].path), cv2.IMREAD_UNCHANGED)
    assert got.dtype == np.uint8 and np.array_equal(got, labels)
    assert np.array_equal(tifffile.imread(store.path / rec.files["depth"].path), depth)
    assert store.verify() == []
    with pytest.raises(UsageError, match="invalid extra file role"):
        store.write_frame(evs[1], raw_of(1), extra={"raw": labels})
    assert evs[1].event_id not in store.completed_event_ids()


def test_metadata_with_a_nested_shape_key_reads_back(tmp_path):
    """tifffile must not mistake our JSON description for its shaped-series metadata."""
    from m2s2hil.store.frame_files import decode_tiff, encode_tiff

    raw = np.arange(64, dtype=np.uint16).reshape(8, 8)
    data = encode_tiff(raw, {"dark": {"shape": [8, 8], "n": 4}, "exposure_s": 0.008})
    arr, meta = decode_tiff(data)
    assert np.array_equal(arr, raw)
    assert meta["dark"]["shape"] == [8, 8]
    # ... and plain tifffile, as a user who downloaded the file would call it.
    import io

    import tifffile

    assert np.array_equal(tifffile.imread(io.BytesIO(data)), raw)
    cube = np.zeros((3, 4, 5), np.float32)
    assert tifffile.imread(io.BytesIO(encode_tiff(cube, {"dark": {"shape": [1]}}))).shape == (3, 4, 5)


def test_a_stored_dark_is_rebuilt_with_its_provenance_by_the_store_and_the_analysis_loader(store):
    """One rebuild (store.cubes.master_dark_from): the evaluation loader's copy used to drop the
    read noise, the camera serial and the reduction of the dark it reads from the session."""
    from m2s2hil.analysis.evaluation.jobs import session_jobs
    from m2s2hil.analysis.evaluation.loading import load_dark
    from m2s2hil.processing.dark import build_master_dark
    from m2s2hil.store.cubes import master_dark_of

    dark = store.sweep.expand(store.rig)[0]
    assert dark.kind == "dark"
    rng = np.random.default_rng(3)
    snaps = [rng.normal(40.0, 2.0, (N, N)).clip(0, 1023).astype(np.uint16) for _ in range(2)]
    master = build_master_dark(snaps, reduce="median", exposure_s=dark.exposure_s, gain=dark.gain,
                               temperature_c=[30.0, 30.5], camera="TOUCAN-SN-42")
    assert master.read_noise_dn is not None
    rec = store.write_dark(dark, master.data, master.provenance())
    write(store, frame_events(store)[0])
    (job,) = [j for j in session_jobs(store) if j.dark is not None][:1]
    loaded, rebuilt = load_dark(job), master_dark_of(store, rec)
    assert loaded is not None
    assert (loaded.read_noise_dn, loaded.camera_serial, loaded.reduce) == (master.read_noise_dn,
                                                                          "TOUCAN-SN-42", "median")
    assert loaded.provenance() == rebuilt.provenance() == master.provenance()


def test_a_reader_holding_the_journal_keeps_reading_when_the_owner_lets_go(store):
    # CI caught it: the console read a frame while the daemon gave the finished session's owner
    # lock back, and the journal object the read held had been swapped out and closed.
    held = store.journal
    before = held.query("SELECT COUNT(*) AS n FROM frames")[0]["n"]
    store.release_ownership()
    assert store.journal is held and held.read_only
    assert held.query("SELECT COUNT(*) AS n FROM frames")[0]["n"] == before
    # read-only now: the owner lock is gone
    with pytest.raises(sqlite3.OperationalError), held.transaction() as db:
        db.execute("DELETE FROM frames")


def test_a_closed_journal_says_so(store):
    from m2s2hil.store.journal import JournalClosed, JournalError

    store.close()
    with pytest.raises(JournalClosed, match="journal closed") as exc:
        store.journal.query("SELECT 1")
    assert isinstance(exc.value, JournalError)
    with pytest.raises(JournalClosed), store.journal.transaction():
        pass
    store.close()  # twice is harmless
