"""The hf export: a ``datasets`` dataset whose ``raw`` column keeps the 10-bit values exactly."""

from __future__ import annotations

import numpy as np
import pytest
from shared_sessions import N, export_session_of

from m2s2hil.store.export import export_session


@pytest.fixture
def datasets(tmp_path, monkeypatch):
    monkeypatch.setenv("HF_DATASETS_OFFLINE", "1")
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf-home"))
    ds = pytest.importorskip("datasets")
    monkeypatch.setattr(ds.config, "HF_DATASETS_OFFLINE", True, raising=False)
    return ds


def test_hf_export_loads_offline_and_gives_the_exact_raw_values(tmp_path, datasets, shared_sessions):
    written_a, written_b = export_session_of(shared_sessions), export_session_of(shared_sessions, "iss", "B1")
    (a, raws_a), (b, raws_b) = (written_a.open(), written_a.arrays), (written_b.open(), written_b.arrays)
    out = tmp_path / "hf"
    export_session(a, out, "hf")
    export_session(b, out, "hf")  # a second session merges into the same dataset
    train = datasets.load_dataset(str(out), split="train", cache_dir=str(tmp_path / "cache"))
    assert train.num_rows == 32
    assert {"raw", "image", "bands_nm", "fwhm_nm", "mosaic_layout", "satellite", "lighting", "azimuth_deg",
            "exposure_s", "turntable_readback_deg", "dark_id"} <= set(train.column_names)
    assert train.features["raw"].dtype == "uint16" and train.features["raw"].shape == (N, N)
    raws = {**raws_a, **raws_b}
    assert max(int(r.max()) for r in raws.values()) > 255  # values an 8-bit conversion would clip
    for i in (0, 17, 31):
        row = train[i]
        raw = np.asarray(row["raw"])
        assert np.array_equal(raw, raws[row["event_id"]]) and raw.dtype.kind in "ui"
        rgb = np.asarray(row["image"].convert("RGB"))  # what most pipelines do: the 8-bit view
        assert np.array_equal(rgb[..., 0], raws[row["event_id"]] >> 2)
        assert row["bands_nm"][0] == 431 and len(row["fwhm_nm"]) == 10
        assert np.asarray(row["mosaic_layout"]).tolist() == [list(r) for r in a.rig.camera.model.layout]
    assert sorted(set(train["satellite"])) == ["Hubble", "ISS"]
    assert "mosaic_layout" in (out / "README.md").read_text()
    a.close()
    b.close()
