"""Exports carry the synthetic domain, the simulator's masks and the projected labels, paired by pose."""

from __future__ import annotations

import csv

import cv2
import numpy as np
import pytest
from shared_sessions import hil_with_labels, synthetic_session_of

from m2s2hil.store.export import export_session
from m2s2hil.store.frame_files import decode_image
from m2s2hil.store.session import SessionStore


@pytest.fixture()
def synth(shared_sessions):
    return synthetic_session_of(shared_sessions)


def test_m2s2_layout_puts_synthetic_beside_hil_with_masks_and_pairs(tmp_path, synth):
    sid, labels = hil_with_labels(tmp_path / "root")
    out = tmp_path / "out"
    with synth.open() as st:  # the synthetic one first: the pairs are rebuilt by the HIL export
        res = export_session(st, out, "m2s2")
    assert res.images == 4
    views = {p.relative_to(out).as_posix() for p in (out / "Synthetic").rglob("*.png")}
    assert len(views) == 4 * 12 and "Synthetic/Hubble/b2/e3/band10_1.png" in views
    assert "Synthetic/Hubble/b2/e0/mask_0.png" in views and "Synthetic/Hubble/b2/e0/rgb_1.png" in views
    with SessionStore.open(tmp_path / "root", sid) as hil:
        export_session(hil, out, "m2s2")
    rows = list(csv.DictReader((out / "metadata" / f"{sid}.csv").open()))
    for r in rows:
        truth, projected = labels[r["event_id"]]
        assert np.array_equal(cv2.imread(str(out / r["mask_file"]), cv2.IMREAD_UNCHANGED), truth)
        assert np.array_equal(cv2.imread(str(out / r["labels_file"]), cv2.IMREAD_UNCHANGED), projected)
        assert r["mask_file"].replace("HILmasks", "HIL") == r["file"] and r["domain"] == "hil"
    pairs = list(csv.DictReader((out / "metadata" / "pairs.csv").open()))
    assert len(pairs) == 4  # every view; E0 with its HIL frame, E3 alone
    paired = [p for p in pairs if p["hil_file"]]
    assert len(paired) == 2 and {p["elevation"] for p in pairs if not p["hil_file"]} == {"E3"}
    for p in paired:  # the same pose: satellite, build, elevation folder and azimuth index k
        syn_k = p["synthetic_file"].rsplit("_", 1)[1]
        assert p["hil_file"].endswith(f"_{syn_k}") and p["hil_file"].split("/")[1:4] == \
            p["synthetic_file"].split("/")[1:4]
        assert (out / p["synthetic_mask_file"]).is_file() and (out / p["hil_labels_file"]).is_file()


@pytest.mark.slow
def test_zarr_holds_synthetic_group_and_projected_labels(tmp_path, synth):
    xr = pytest.importorskip("xarray")
    sid, labels = hil_with_labels(tmp_path / "root")
    out = tmp_path / "data.zarr"
    with synth.open() as st:
        assert export_session(st, out, "zarr").images == 4
    with SessionStore.open(tmp_path / "root", sid) as hil:
        export_session(hil, out, "zarr")
    root = xr.open_zarr(out, consolidated=False)
    syn = xr.open_zarr(out, group="synthetic", consolidated=False)
    assert syn["bands"].shape == (4, 10, 32, 32, 3) and syn["mask"].dtype == np.uint8
    i = [str(e) for e in root["event_id"].values].index("weak/E0/az180/f0")
    truth, projected = labels["weak/E0/az180/f0"]
    assert np.array_equal(root["labels"][i].values, truth)
    assert np.array_equal(root["projected_labels"][i].values, projected)
    j = [(str(e), float(a)) for e, a in zip(syn["elevation"].values, syn["azimuth_deg"].values, strict=True)]
    k = j.index(("E0", 180.0))  # the same pose in the synthetic group
    with synth.open() as st:
        fr = next(f for f in st.frames() if f.event_id == str(syn["event_id"].values[k]))
        assert np.array_equal(syn["mask"][k].values, decode_image(st.read_file(fr.files["truth_labels"])))


def test_hf_export_has_a_synthetic_config_and_hil_masks(tmp_path, synth):
    datasets = pytest.importorskip("datasets")
    sid, labels = hil_with_labels(tmp_path / "root")
    out = tmp_path / "hf"
    with synth.open() as st:
        export_session(st, out, "hf")
    with SessionStore.open(tmp_path / "root", sid) as hil:
        export_session(hil, out, "hf")
    syn = datasets.load_dataset(str(out), "synthetic", split="train", cache_dir=str(tmp_path / "cache"))
    assert len(syn) == 4 and len(syn[0]["bands"]) == 10 and syn[0]["rgb"].size == (32, 32)
    hil_ds = datasets.load_dataset(str(out), split="train", cache_dir=str(tmp_path / "cache"))
    row = hil_ds[0]
    truth, projected = labels[row["event_id"]]
    assert np.array_equal(np.asarray(row["mask"]), truth)
    assert np.array_equal(np.asarray(row["labels"]), projected)
