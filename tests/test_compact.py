"""``m2s2hil sessions compact``: a legacy session converted atomically, verified before and after."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tifffile
from shared_sessions import Written
from test_storage_format import capture_like_the_engine, rig_with, scene_raw, sweep
from typer.testing import CliRunner

from m2s2hil.cli import app
from m2s2hil.store import compact as compact_mod
from m2s2hil.store.compact import CompactError, compact_session
from m2s2hil.store.session import SessionStore


@pytest.fixture
def legacy_session(shared_sessions):
    """``legacy_session(root)``: a completed legacy-format session "old" under ``root`` (a copy
    of one written once per test process: every test here changes it); its cubes, by event id."""

    def make(root) -> Written:
        st = SessionStore.create(root, sweep(), rig_with("legacy"), session_id="old")
        cubes = capture_like_the_engine(st)
        st.complete()
        st.close()
        return Written(root, "old", cubes)

    original = shared_sessions.get("legacy", make)
    return lambda root: original.copy_to(root).arrays


def test_compact_converts_a_legacy_session_and_keeps_every_value(tmp_path, legacy_session):
    cubes = legacy_session(tmp_path)
    old_files = {p.name for p in (tmp_path / "old").rglob("*.tiff")}
    res = CliRunner().invoke(app, ["sessions", "compact", "old", "--root", str(tmp_path)])
    assert res.exit_code == 0, res.output
    assert "compacted 4 frame(s) and 1 dark(s), 4 cube(s) now computed" in res.output
    with SessionStore.open(tmp_path, "old") as st:
        assert st.verify() == []
        for i, fr in enumerate(st.frames()):
            assert set(fr.files) == {"raw", "preview"} and fr.files["raw"].path.endswith("-v2.raw.tiff")
            stem = {f.path.rsplit("/", 1)[1].split(".")[0] for f in fr.files.values()}
            assert len(stem) == 1  # a frame's files share their stem (sessions repair groups them so)
            with tifffile.TiffFile(st.path / fr.files["raw"].path) as tf:
                assert tf.pages[0].compression == tifffile.COMPRESSION.ADOBE_DEFLATE
            raw, meta = st.read_raw(fr.event_id)
            assert np.array_equal(raw, scene_raw(i)) and meta["storage_format"] == "compressed"
            assert st.read_cube(fr.event_id).tobytes() == cubes[fr.event_id].tobytes()
            assert meta["temperature_c"] == 30.0 and meta == fr.meta
        assert st.load_dark(st.darks()[0].dark_id).dtype == np.uint16
        names = {p.name for p in st.path.rglob("*.tiff")}
        assert not names & old_files  # the old files are gone
        manifest = {f["path"] for f in json.loads((st.path / "manifest.json").read_text())["files"]}
        assert manifest == {r.path for fr in st.frames() for r in fr.files.values()} | {
            st.darks()[0].files["master"].path}
        assert any(e["kind"] == "compact" for e in st.events())
    again = CliRunner().invoke(app, ["sessions", "compact", "old", "--root", str(tmp_path)])
    assert again.exit_code == 0 and "already compact" in again.output


def test_a_crash_before_the_switch_leaves_the_old_session_and_a_rerun_finishes(tmp_path, monkeypatch,
                                                                              legacy_session):
    cubes = legacy_session(tmp_path)

    def crash(*a, **kw):
        raise KeyboardInterrupt("power cut")

    monkeypatch.setattr(compact_mod.SessionStore, "manifest", crash)  # after the commit
    with pytest.raises(KeyboardInterrupt):
        compact_session(tmp_path, "old")
    with SessionStore.open(tmp_path, "old") as st:  # switched, old files still there: orphans
        assert {p.kind for p in st.verify()} == {"orphan"}
        fr = st.frames()[0]
        assert st.read_cube(fr.event_id).tobytes() == cubes[fr.event_id].tobytes()
    monkeypatch.undo()
    report = compact_session(tmp_path, "old")
    assert report.frames == 0 and len(report.removed) == 4 * 3 + 1  # raws, cubes, previews; dark
    with SessionStore.open(tmp_path, "old") as st:
        assert st.verify() == []


def test_a_crash_before_the_commit_changes_nothing(tmp_path, monkeypatch, legacy_session):
    legacy_session(tmp_path)
    with SessionStore.open(tmp_path, "old") as st:
        before = [(fr.event_id, fr.files) for fr in st.frames()]

    real = compact_mod.SessionStore.open

    def open_then_break(*a, **kw):
        st = real(*a, **kw)
        st.journal.transaction = lambda: (_ for _ in ()).throw(OSError("disk gone"))
        return st

    monkeypatch.setattr(compact_mod.SessionStore, "open", open_then_break)
    with pytest.raises(OSError):
        compact_session(tmp_path, "old")
    monkeypatch.undo()
    with SessionStore.open(tmp_path, "old") as st:
        assert [(fr.event_id, fr.files) for fr in st.frames()] == before
        assert {p.kind for p in st.verify()} == {"orphan"}  # the new files, unknown to the journal
    assert compact_session(tmp_path, "old").frames == 4


def test_a_damaged_session_is_refused_before_anything_is_written(tmp_path, legacy_session):
    legacy_session(tmp_path)
    with SessionStore.open(tmp_path, "old") as st:
        victim = st.path / st.frames()[1].files["raw"].path
    victim.write_bytes(victim.read_bytes()[:-2] + b"\x00\x01")
    with pytest.raises(CompactError, match="checksum"):
        compact_session(tmp_path, "old")
    assert not list((tmp_path / "old" / "frames").glob("*-v2.*"))
