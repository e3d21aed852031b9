"""Export: the published M2S2 layout (8-bit and lossless 16-bit) and a Hugging Face image folder."""

from __future__ import annotations

import csv
import json

import cv2
import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from m2s2hil.commands import export as export_cmd
from m2s2hil.config import RigConfig, default_rig
from m2s2hil.plan import Sweep
from m2s2hil.store.export import ExportError, export_session, to_8bit
from m2s2hil.store.session import SessionStore

N = 64


def small_rig() -> RigConfig:
    data = default_rig().model_dump(mode="json")
    data["camera"]["model"].update(width=N, height=N)
    return RigConfig.model_validate(data)


def raw_for(ev) -> np.ndarray:
    seed = abs(hash(ev.event_id)) % 2**32
    return np.random.default_rng(seed).integers(0, 1024, (N, N), dtype=np.uint16)


def make_session(root, satellite="hubble", build="B2", frames_per_pose=1, session_id=None, **kw):
    sweep = Sweep(satellite=satellite, build=build, lighting=["weak", "directional"], tilts=["E0", "E2"],
                  azimuth_step_deg=90, frames_per_pose=frames_per_pose, dark={"frames": 2}, **kw)
    st = SessionStore.create(root, sweep, small_rig(), session_id=session_id)
    raws = {}
    for ev in sweep.expand(st.rig):
        if ev.kind == "dark":
            st.write_dark(ev, np.full((N, N), 3.0, np.float32))
            continue
        raws[ev.event_id] = raw_for(ev)
        st.write_frame(ev, raws[ev.event_id], meta={
            "temperature_c": 30.5, "pose": {"turntable_deg": ev.azimuth_deg + 0.01, "tilt_deg": ev.tilt_deg}})
    return st, raws


def read_png(path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, path
    return img


def test_to_8bit_drops_the_two_low_bits():
    raw = np.array([0, 3, 4, 511, 1020, 1023], np.uint16)
    assert to_8bit(raw, 10).tolist() == [0, 0, 1, 127, 255, 255]
    assert to_8bit(np.array([200], np.uint16), 8).tolist() == [200]


def test_m2s2_layout_paths_bit_depths_and_metadata(tmp_path):
    st, raws = make_session(tmp_path / "data")
    out = tmp_path / "out"
    res = export_session(st, out, "m2s2")
    assert res.images == 16
    # azimuth index k: 0, 90, 180, 270 deg -> 0..3; weak = "solo", directional = "dir"
    expected = {f"HIL/Hubble/b2/e{e}/{light}_{k}.png" for e in (0, 2) for light in ("solo", "dir")
                for k in range(4)}
    got = {p.relative_to(out).as_posix() for p in (out / "HIL").rglob("*.png")}
    assert got == expected
    rows = list(csv.DictReader((out / "metadata" / f"{st.session_id}.csv").open()))
    assert len(rows) == 16
    for r in rows:
        raw = raws[r["event_id"]]
        img8 = read_png(out / r["file"])
        assert img8.dtype == np.uint8 and img8.shape == (N, N, 3)
        assert np.array_equal(img8[..., 0], img8[..., 1]) and np.array_equal(img8[..., 0], img8[..., 2])
        assert np.array_equal(img8[..., 0], (raw >> 2).astype(np.uint8))
        img16 = read_png(out / r["file16"])
        assert img16.dtype == np.uint16 and img16.shape == (N, N) and np.array_equal(img16, raw)
        ev_az = float(r["nominal_azimuth_deg"])
        assert int(r["k"]) == int(ev_az // 90)
        assert r["file"].endswith(f"_{r['k']}.png")
        assert float(r["turntable_readback_deg"]) == pytest.approx(float(r["azimuth_deg"]) + 0.01)
        assert float(r["exposure_s"]) in (0.008, 0.003) and r["dark_id"].startswith("dark/")
        assert r["lighting_dataset"] == {"weak": "solo", "directional": "dir"}[r["lighting"]]
    info = json.loads((out / "metadata" / f"{st.session_id}.json").read_text())
    assert info["bands_nm"] == [431, 479, 515, 567, 611, 666, 719, 775, 820, 877]
    assert info["fwhm_nm"][0] == 65 and len(info["fwhm_nm"]) == 10
    assert len(info["mosaic_layout"]) == 4 and all(len(r) == 4 for r in info["mosaic_layout"])
    assert info["bit_depth"] == 10 and ">> 2" in info["png8_mapping"]
    assert info["elevations_deg"] == {"E0": 15.0, "E1": 0.0, "E2": -15.0}
    assert len(info["darks"]) == 2
    for d in info["darks"]:
        assert (out / "metadata" / d["file"]).is_file()
    st.close()


def test_extra_frames_per_pose_get_indices_after_the_azimuths(tmp_path):
    st, _ = make_session(tmp_path / "data", frames_per_pose=2)
    export_session(st, tmp_path / "out", "m2s2")
    names = sorted(p.name for p in (tmp_path / "out" / "HIL" / "Hubble" / "b2" / "e0").glob("solo_*.png"))
    assert names == sorted(f"solo_{k}.png" for k in range(8))
    rows = list(csv.DictReader((tmp_path / "out" / "metadata" / f"{st.session_id}.csv").open()))
    for r in rows:
        assert int(r["k"]) == int(r["azimuth_index"]) + 4 * int(r["frame"])
    st.close()


def test_existing_files_are_not_overwritten_unless_asked(tmp_path):
    st, _ = make_session(tmp_path / "data")
    export_session(st, tmp_path / "out", "m2s2")
    with pytest.raises(ExportError, match="already exists"):
        export_session(st, tmp_path / "out", "m2s2")
    assert export_session(st, tmp_path / "out", "m2s2", overwrite=True).images == 16
    with pytest.raises(ExportError, match="unknown export layout"):
        export_session(st, tmp_path / "x", "zip")
    st.close()


def test_hf_image_folder_loads_offline_with_datasets(tmp_path, monkeypatch):
    monkeypatch.setenv("HF_DATASETS_OFFLINE", "1")
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf-home"))
    datasets = pytest.importorskip("datasets")
    monkeypatch.setattr(datasets.config, "HF_DATASETS_OFFLINE", True, raising=False)
    a, raws_a = make_session(tmp_path / "data", "hubble", "B2")
    b, raws_b = make_session(tmp_path / "data", "iss", "B1")
    out = tmp_path / "hf"
    export_session(a, out, "hf")
    export_session(b, out, "hf")  # a second session merges into the same folder
    ds = datasets.load_dataset("imagefolder", data_dir=str(out), cache_dir=str(tmp_path / "cache"))
    train = ds["train"]
    assert train.num_rows == 32
    assert {"image", "satellite", "build", "lighting", "azimuth_deg", "exposure_s"} <= set(train.column_names)
    raws = {**raws_a, **raws_b}
    for i in (0, 17, 31):
        row = train[i]
        arr = np.array(row["image"])
        assert arr.dtype == np.uint16 and np.array_equal(arr, raws[row["event_id"]])
    assert sorted(set(train["satellite"])) == ["Hubble", "ISS"]
    a.close()
    b.close()


def test_cli_export_by_id_and_by_folder(tmp_path):
    st, _ = make_session(tmp_path / "data", session_id="cli1")
    st.close()
    umbrella = typer.Typer()
    umbrella.add_typer(export_cmd.app, name="export")
    runner = CliRunner()
    res = runner.invoke(umbrella, ["export", "cli1", "--layout", "m2s2", "--out", str(tmp_path / "o1"),
                                   "--root", str(tmp_path / "data")])
    assert res.exit_code == 0, res.output
    assert "exported 16 image(s)" in res.output
    assert (tmp_path / "o1" / "HIL" / "Hubble" / "b2" / "e2" / "dir_3.png").is_file()
    res = runner.invoke(umbrella, ["export", str(tmp_path / "data" / "cli1"), "--layout", "hf",
                                   "--out", str(tmp_path / "o2")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "o2" / "train" / "metadata.csv").is_file()
    res = runner.invoke(umbrella, ["export", "cli1", "--layout", "tar", "--out", str(tmp_path / "o3"),
                                   "--root", str(tmp_path / "data")])
    assert res.exit_code != 0 and "--layout must be one of" in str(res.exception)
    res = runner.invoke(umbrella, ["export", "missing", "--out", str(tmp_path / "o4"),
                                   "--root", str(tmp_path / "data")])
    assert res.exit_code != 0 and "no session 'missing'" in str(res.exception)
