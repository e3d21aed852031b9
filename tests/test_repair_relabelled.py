"""`sessions repair` after `sessions register` rewrote a frame's projected labels: the rewritten
file (``<frame>.projected_labels.r<event>.png``) is kept as the frame's labels, not quarantined as
a file without a frame, and the metadata says it is a rewrite whose provenance was in the journal."""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from engine_helpers import session, small_sweep

from m2s2hil.analysis.qc import capture_qc_hook
from m2s2hil.store.frame_files import decode_image
from m2s2hil.store.relabel import replace_frame_labels
from m2s2hil.store.repair import RECOVERED, repair_session
from m2s2hil.store.session import SessionStore
from m2s2hil.twin.simulated import rig_with

pytestmark = pytest.mark.slow  # a 4-frame twin capture each: about 2 s CPU


def _captured(tmp_path: Path) -> Path:
    with session(tmp_path, small_sweep(), config=rig_with(64), qc=capture_qc_hook(twin=True)) as s:
        s.engine.start()
        s.engine.wait(timeout=120)
    return tmp_path / "data"


def _first_labelled(store: SessionStore):
    return next(f for f in store.frames() if "projected_labels" in f.files)


def test_repair_keeps_the_rewritten_labels(tmp_path: Path) -> None:
    root = _captured(tmp_path)
    with SessionStore.open(root, "s1", mode="write") as store:
        fr = _first_labelled(store)
        capture_meta = fr.meta["qc"]["projected_labels"]
        shape = np.asarray(decode_image(store.read_file(fr.files["projected_labels"]))).shape
        new = np.full(shape, 3, np.uint8)
        rel = replace_frame_labels(store, fr.event_id, new, {"source": "twin", "registration": {"event": 7}},
                                   tag="r7")
    report = repair_session(root, "s1", force=True)
    assert report.quarantined == [] and report.frames == 4
    with SessionStore.open(root, "s1") as store:
        assert store.verify() == []
        kept = store.frame(fr.event_id)
        assert kept.files["projected_labels"].path == rel
        assert np.array_equal(np.asarray(decode_image(store.read_file(kept.files["projected_labels"]))), new)
        qc = kept.meta["qc"]
        assert qc["projected_labels"][RECOVERED] is True and qc["projected_labels"]["tag"] == "r7"
        assert qc["projected_labels"]["registration"] == {"event": 7}
        assert report.kept_journal in qc["projected_labels"]["provenance"]
        assert qc["projected_labels_superseded"] == capture_meta
        others = [f for f in store.frames() if f.event_id != fr.event_id and "projected_labels" in f.files]
        assert others and all(RECOVERED not in f.meta["qc"]["projected_labels"] for f in others)


def test_repair_after_an_interrupted_rewrite_keeps_the_newest_and_quarantines_the_rest(
        tmp_path: Path, monkeypatch) -> None:
    root = _captured(tmp_path)
    with SessionStore.open(root, "s1", mode="write") as store:
        fr = _first_labelled(store)
        old_path = fr.files["projected_labels"].path
        shape = np.asarray(decode_image(store.read_file(fr.files["projected_labels"]))).shape
        replace_frame_labels(store, fr.event_id, np.full(shape, 1, np.uint8), {"source": "twin"}, tag="r5")

        @contextmanager
        def dies():  # the second rewrite's file lands, its journal row does not
            raise KeyboardInterrupt
            yield

        monkeypatch.setattr(store.journal, "transaction", dies)
        with pytest.raises(KeyboardInterrupt):
            replace_frame_labels(store, fr.event_id, np.full(shape, 2, np.uint8), {"source": "twin"},
                                 tag="r12")
        monkeypatch.undo()
    assert not (root / "s1" / old_path).exists()  # the first rewrite removed the capture-time file
    report = repair_session(root, "s1", force=True)
    assert len(report.quarantined) == 1 and report.quarantined[0].endswith(".projected_labels.r5.png")
    assert (root / "s1" / report.quarantined[0]).is_file()  # set aside, not deleted
    with SessionStore.open(root, "s1") as store:
        assert store.verify() == []
        kept = store.frame(fr.event_id)
        assert kept.files["projected_labels"].path.endswith(".projected_labels.r12.png")
        assert int(np.asarray(decode_image(store.read_file(kept.files["projected_labels"]))).max()) == 2
        assert kept.meta["qc"]["projected_labels"]["tag"] == "r12"
