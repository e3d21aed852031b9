"""`sessions register` rewrites every stored frame's projected labels at the refined placement
(m2s2hil.store.relabel), atomically per frame, with the registration that made them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cli_support import run_cli
from engine_helpers import session, small_sweep

from m2s2hil.analysis.qc import capture_qc_hook
from m2s2hil.store.frame_files import decode_image
from m2s2hil.store.session import SessionStore
from m2s2hil.twin.labels import label_iou, projected_labels
from m2s2hil.twin.projection import Placement, TwinCamera
from m2s2hil.twin.registration import Registration, rig_meshes
from m2s2hil.twin.simulated import rig_with

MOUNT = {"offset_mm": [5.0, -4.0], "yaw_deg": 6.0, "tilt_bias_deg": 2.0}  # the perturbed placement


def _captured(tmp_path: Path) -> Path:
    """A finished 128² session (4 azimuths, E1) on a misplaced mount, labelled at capture."""
    rig = rig_with(128, mount=MOUNT)
    with session(tmp_path, small_sweep(), config=rig, qc=capture_qc_hook(twin=True)) as s:
        s.engine.start()
        s.engine.wait(timeout=120)
    return tmp_path / "data"


def _labels(store: SessionStore) -> dict[str, tuple[np.ndarray, dict, np.ndarray | None]]:
    out = {}
    for fr in store.frames():
        if "projected_labels" in fr.files:
            lab = np.asarray(decode_image(store.read_file(fr.files["projected_labels"])))
            truth = (np.asarray(decode_image(store.read_file(fr.files["truth_labels"])))
                     if "truth_labels" in fr.files else None)
            out[fr.event_id] = (lab, fr.meta["qc"]["projected_labels"], truth)
    return out


def _at(truth: np.ndarray, lab: np.ndarray) -> np.ndarray:
    """The truth (full sensor) at the labels' size (the superpixel cube's), nearest pixel."""
    step = truth.shape[0] // lab.shape[0]
    return truth[step // 2::step, step // 2::step]


@pytest.mark.slow  # a 4-frame capture and a refit: about 3.5 s CPU
def test_register_rewrites_the_projected_labels_at_the_refined_placement(tmp_path: Path) -> None:
    root = _captured(tmp_path)
    with SessionStore.open(root, "s1") as store:
        before = _labels(store)
        raw_before = {fr.event_id: fr.files["raw"].sha256 for fr in store.frames()}
        truth_before = {fr.event_id: fr.files["truth_labels"].sha256 for fr in store.frames()}
    res = run_cli("sessions", "register", "s1", "--root", root)
    assert res.exit_code == 0, res.stderr
    assert "projected labels rewritten for 4 frame(s)" in res.stdout
    with SessionStore.open(root, "s1") as store:
        after = _labels(store)
        assert set(after) == {fr.event_id for fr in store.frames()}  # every frame, not only the late ones
        ev = [e for e in store.events() if e["kind"] == "twin_registration"][-1]
        reg = Registration(Placement.from_dict(ev["payload"]["placement"]), float(ev["payload"]["residual"]),
                           (), 0, 0.0, 0, 0.0)
        twin = TwinCamera(store.rig.camera.model, 64, meshes=rig_meshes(store.rig))
        for fr in store.frames():
            lab, meta, _ = after[fr.event_id]
            az, tilt = fr.meta["pose"]["turntable_deg"], fr.meta["pose"]["tilt_deg"]
            fresh = projected_labels(twin, "voyager", "B3", az, tilt, reg, lab.shape)
            assert np.array_equal(lab, fresh.labels)
            assert meta["registration"]["event"] == ev["seq"] and meta["registration"]["time"] == ev["time"]
            assert meta["confidence"] == round(1 - reg.residual, 4)
            assert fr.files["raw"].sha256 == raw_before[fr.event_id]
            assert fr.files["truth_labels"].sha256 == truth_before[fr.event_id]
        assert store.verify() == []  # the old files are gone, the new ones checksummed
        old_iou = [label_iou(lab, _at(truth, lab)) for lab, _, truth in before.values() if truth is not None]
        new_iou = [label_iou(lab, _at(truth, lab)) for lab, _, truth in after.values() if truth is not None]
    assert old_iou and np.mean(new_iou) > np.mean(old_iou) + 0.05  # 0.46 -> 0.64 at 32² labels
    assert all("registration" not in m for _, m, _ in before.values())


def test_a_damaged_label_file_is_a_one_line_error_and_nothing_is_rewritten(tmp_path: Path) -> None:
    root = _captured(tmp_path)
    with SessionStore.open(root, "s1") as store:
        fr = next(f for f in store.frames() if "projected_labels" in f.files)
        path = store.path / fr.files["projected_labels"].path
        files = {f.event_id: f.files for f in store.frames()}
    path.write_bytes(b"not a png")
    res = run_cli("sessions", "register", "s1", "--root", root)
    assert res.exit_code != 0
    err = res.stderr.strip()
    assert len(err.splitlines()) == 1 and "projected_labels" in err and "sha256" in err
    with SessionStore.open(root, "s1") as store:
        assert {f.event_id: f.files for f in store.frames()} == files


def test_an_interrupted_swap_leaves_the_frame_its_old_labels(tmp_path: Path, monkeypatch) -> None:
    """The new file is written, the journal commit fails: the frame still points at its old,
    intact labels (the new file is an orphan `verify` names, as after any interrupted write)."""
    from contextlib import contextmanager

    from m2s2hil.store.relabel import replace_frame_labels

    root = _captured(tmp_path)
    with SessionStore.open(root, "s1", mode="write") as store:
        fr = next(f for f in store.frames() if "projected_labels" in f.files)

        @contextmanager
        def dies():  # the power goes between the file and the journal row
            raise KeyboardInterrupt
            yield

        monkeypatch.setattr(store.journal, "transaction", dies)
        with pytest.raises(KeyboardInterrupt):
            replace_frame_labels(store, fr.event_id, np.zeros((32, 32), np.uint8), {"source": "twin"},
                                 tag="r9")
        monkeypatch.undo()
        kept = store.frame(fr.event_id)
        assert kept.files["projected_labels"] == fr.files["projected_labels"]
        assert kept.meta["qc"]["projected_labels"] == fr.meta["qc"]["projected_labels"]
        store.read_file(kept.files["projected_labels"])  # intact: its checksum holds
        assert [p.kind for p in store.verify()] == ["orphan"]
