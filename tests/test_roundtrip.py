"""Export → import is lossless: the 16-bit mosaics and the metadata sidecars come back."""

from __future__ import annotations

import numpy as np
import pytest
from shared_sessions import write_session as make_session

from m2s2hil.store.export import export_session
from m2s2hil.store.importer import DatasetImportError, import_dataset


def test_export_then_import_gives_bit_identical_raws_and_the_same_metadata(tmp_path):
    orig, raws = make_session(tmp_path / "cap", "hubble", "B2")
    out = tmp_path / "release"
    export_session(orig, out, "m2s2")
    (imp,) = import_dataset(out, tmp_path / "imported")
    assert imp.rig.camera.model.bit_depth == 10
    assert imp.rig.camera.model.bands_nm == orig.rig.camera.model.bands_nm
    assert imp.rig.camera.model.layout == orig.rig.camera.model.layout
    assert imp.sweep.azimuth_step_deg == 90  # from the exported sweep, not the default 10°
    assert imp.completed_event_ids() >= {fr.event_id for fr in orig.frames()}
    assert max(int(r.max()) for r in raws.values()) > 255
    for fr in orig.frames():
        got, meta = imp.read_raw(fr.event_id)
        assert got.dtype == np.uint16 and np.array_equal(got, raws[fr.event_id])  # all 10 bits
        assert meta["source_format"] == "png16" and meta["source_file"].startswith("HIL16/")
        for key in ("exposure_s", "gain", "temperature_c", "dark_id", "pose"):
            assert meta[key] == fr.meta[key], key
        assert meta["exposure_known"] is True and meta["source_event_id"] == fr.event_id
    assert {d.dark_id for d in imp.darks()} == {d.dark_id for d in orig.darks()}
    for d in orig.darks():
        assert np.array_equal(imp.load_dark(d.dark_id), orig.load_dark(d.dark_id))
        assert d.exposure_s == next(x for x in imp.darks() if x.dark_id == d.dark_id).exposure_s
    assert imp.verify() == [] and imp.state == "completed"
    # the imported session computes the same cubes as the original
    ev = orig.frames()[0].event_id
    assert orig.read_cube(ev).tobytes() == imp.read_cube(ev).tobytes()
    imp.close()
    orig.close()


def test_a_tampered_dark_is_named(tmp_path):
    orig, _ = make_session(tmp_path / "cap", "hubble", "B2")
    out = tmp_path / "release"
    export_session(orig, out, "m2s2")
    dark = next((out / "metadata" / orig.session_id).glob("*.tiff"))
    data = dark.read_bytes()
    dark.write_bytes(data[:-1] + bytes([data[-1] ^ 0xFF]))  # a changed byte, whatever it was
    with pytest.raises(DatasetImportError, match="sha256"):
        import_dataset(out, tmp_path / "imported")
    orig.close()
