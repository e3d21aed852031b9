"""Projected labels for HIL frames: the registered twin's label map at each frame's pose,
against the simulator's truth on a rig with the mockup misplaced."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import twin_support

from m2s2hil.twin.labels import label_iou, projected_labels
from m2s2hil.twin.projection import NOMINAL, TwinCamera
from m2s2hil.twin.registration import Registration
from m2s2hil.twin.simulated import SimBench, rig_with


def test_projected_labels_match_the_truth_once_registered() -> None:
    reg = twin_support.registered()
    twin = TwinCamera(rig_with(256).camera.model, 64)
    unregistered = Registration(NOMINAL, 0.5, (), 0, 0.0, 0, 0.0)
    fg, nominal_fg, miou = [], [], []
    for az, f in zip(twin_support.AZIMUTHS, twin_support.misplaced_frames(), strict=True):
        truth = f.truth.labels
        pose = (twin_support.SAT, twin_support.BUILD, az, twin_support.TILT)
        pl = projected_labels(twin, *pose, reg, truth.shape)
        assert pl.labels.shape == truth.shape and pl.class_names == tuple(f.truth.class_names)
        assert pl.confidence == pytest.approx(1 - reg.residual) and pl.meta()["source"] == "twin"
        fg.append(label_iou((pl.labels > 0).astype(np.uint8), (truth > 0).astype(np.uint8)))
        miou.append(label_iou(pl.labels, truth))
        off = projected_labels(twin, *pose, unregistered, truth.shape)
        nominal_fg.append(label_iou((off.labels > 0).astype(np.uint8), (truth > 0).astype(np.uint8)))
    # A 64² cube places the parts to about a millimetre: thin parts lose IoU (docs/benchmarks.md has 512²).
    assert min(fg) > 0.8 and np.median(miou) > 0.55
    assert np.mean(fg) > np.mean(nominal_fg) + 0.02  # the placement the registration found is what helps


def test_label_iou_refuses_maps_of_different_shapes() -> None:
    a = np.zeros((4, 4), np.uint8)
    assert label_iou(a, a) == 1.0
    with pytest.raises(ValueError, match="differ in shape"):
        label_iou(a, np.zeros((4, 5), np.uint8))


def test_the_capture_qc_stores_projected_labels_once_registered() -> None:
    """The QC hook with the twin's checks hands the engine each frame's projected labels
    (``frame_files``) once the sweep's registration has a placement (3 frames over 180°)."""
    from types import SimpleNamespace

    from engine_helpers import small_sweep

    from m2s2hil.analysis.qc import capture_qc_hook

    qc = capture_qc_hook(twin=True)
    qc.bind(small_sweep(satellite=twin_support.SAT, build=twin_support.BUILD), rig_with(256))
    stored = []
    for i, f in enumerate(twin_support.misplaced_frames()):
        ev = SimpleNamespace(event_id=f"e{i}", lighting="weak", elevation="E0")
        out = qc(SimpleNamespace(cube=f.cube, saturated_mask=None), ev, f.meta)
        files = qc.frame_files(ev)
        stored.append("projected_labels" in files)
        if files:
            assert files["projected_labels"].shape == f.cube.shape[1:]
            meta = out["projected_labels"]
            assert meta["source"] == "twin" and 0 < meta["confidence"] <= 1
    assert stored == [False, False, True, True]


def test_hil_frames_are_scored_against_the_projected_labels_and_table2_shows_them() -> None:
    from m2s2hil.analysis.evaluation.evaluate import _segmenter_result
    from m2s2hil.analysis.evaluation.jobs import FrameJob
    from m2s2hil.analysis.evaluation.options import EvalOptions
    from m2s2hil.analysis.evaluation.table2 import build_rows, to_csv, to_markdown

    # A 10-band cube of two filaments on a backdrop; no truth (a HIL frame), projected labels.
    rng = np.random.default_rng(0)
    lab = np.zeros((32, 32), np.uint8)
    lab[6:26, 4:15], lab[6:26, 17:28] = 1, 2
    spectra = np.array([np.full(10, 0.2), np.linspace(0.9, 0.3, 10), np.linspace(0.2, 0.8, 10)])
    cube = (spectra[lab].transpose(2, 0, 1) + rng.normal(0, 0.01, (10, 32, 32))).astype(np.float32)
    job = FrameJob("s1/f1", "s1", "hubble", "B1", 3, "E1", "weak", 0.0, {}, "superpixel")
    opts = EvalOptions(mtc_for="none")
    right = _segmenter_result("spectral", cube, None, job, opts, (), lab)
    wrong = _segmenter_result("spectral", cube, None, job, opts, (), np.roll(lab, 8, axis=1))
    assert "precision" not in right and right["hil_dice"] > 0.9 > 0.8 > wrong["hil_dice"]
    recs = [{"satellite": "hubble", "build": "B1", "elevation": "E1", "lighting": "weak", "classes": 3,
             "has_truth": False, "error": None, "results": {"spectral": r, "rgb-kmeans": {}}}
            for r in (right, wrong)]
    (row,) = build_rows(recs, multi="spectral", rgb="rgb-kmeans")
    assert row.hil["dice"] == (pytest.approx((right["hil_dice"] + wrong["hil_dice"]) / 2), 2)
    md = to_markdown([row])
    assert "HIL Dice" in md.splitlines()[0] and "projected labels" in md
    assert "hil_recall_n" in to_csv([row]).splitlines()[0]


def test_labels_at_the_true_placement_are_the_simulators_truth() -> None:
    """The twin projects the mesh the simulated camera renders, with its geometry: at the
    placement the rig was given, the projected labels are the truth, pixel for pixel."""
    reg = Registration(twin_support.TRUE, 0.0, (), 0, 0.0, 0, 0.0)
    twin = TwinCamera(rig_with(256).camera.model, 64)
    for az, f in zip(twin_support.AZIMUTHS, twin_support.misplaced_frames(), strict=True):
        pl = projected_labels(twin, twin_support.SAT, twin_support.BUILD, az, twin_support.TILT, reg,
                              f.truth.labels.shape)
        assert np.array_equal(pl.labels, f.truth.labels)


def _box_mockup(folder: Path) -> Path:
    """An STL folder, one box per filament of Hubble B2, side by side (about 150 mm across)."""
    import trimesh

    from m2s2hil.catalog import load_catalog

    folder.mkdir()
    for i, mat in enumerate(load_catalog().build("hubble", "B2").materials):
        box = trimesh.creation.box((30.0, 30.0, 40.0 + 20.0 * i))
        box.apply_translation((30.0 * i, 0.0, 20.0 + 10.0 * i))
        box.export(folder / f"{mat}.stl")
    return folder


def test_the_twin_projects_the_lab_mesh_the_rig_file_names(tmp_path: Path) -> None:
    from m2s2hil.twin.registration import rig_meshes

    rig = rig_with(128, mockups={"hubble": {"B2": {"mesh": str(_box_mockup(tmp_path / "stl"))}}})
    f = SimBench(rig).frame("hubble", "B2", "weak", 30.0, 0.0, exposure_s=0.02, process=False)
    meshes = rig_meshes(rig)
    assert set(meshes) == {("hubble", "B2")}
    reg = Registration(NOMINAL, 0.0, (), 0, 0.0, 0, 0.0)
    lab = projected_labels(TwinCamera(rig.camera.model, 64, meshes=meshes), "hubble", "B2", 30.0, 0.0, reg,
                           f.truth.labels.shape)
    assert np.array_equal(lab.labels, f.truth.labels)
    builtin = projected_labels(TwinCamera(rig.camera.model, 64), "hubble", "B2", 30.0, 0.0, reg,
                               f.truth.labels.shape)
    assert not np.array_equal(builtin.labels, f.truth.labels)  # the built-in Hubble is another shape
