"""``m2s2hil export --format envi``: ENVI pairs that Spectral Python opens as the session's cubes."""

from __future__ import annotations

import numpy as np
import pytest
from cli_support import run_cli
from shared_sessions import export_session_of

from m2s2hil.integrations.envi import EnviExportError, export_envi
from m2s2hil.store.layout import safe_name

spectral = pytest.importorskip("spectral", reason="the envi extra (Spectral Python) is not installed")


@pytest.fixture
def hubble(shared_sessions):
    return export_session_of(shared_sessions)


def test_cli_exports_every_cube_and_spectral_reads_it_back_exactly(tmp_path, hubble):
    out = tmp_path / "envi"
    res = run_cli("export", hubble.path, "--format", "envi", "--out", out)
    assert res.exit_code == 0, res.output
    with hubble.open() as st:
        model = st.rig.camera.model
        frames = st.frames()
        assert len(frames) == 16
        for fr in frames:
            stem = out / st.session_id / safe_name(fr.event_id)
            img = spectral.envi.open(f"{stem}.hdr", f"{stem}.img")
            cube = st.read_cube(fr.event_id)  # (band, y, x)
            got = np.asarray(img.load())  # (y, x, band)
            assert got.shape == (*cube.shape[1:], model.n_bands)
            assert np.array_equal(np.moveaxis(got, -1, 0), cube)
            assert img.bands.centers == list(model.bands_nm)
            assert img.bands.bandwidths == list(model.fwhm_nm)
            assert img.bands.band_unit == "Nanometers"
            assert img.metadata["band names"] == [f"{nm:g} nm" for nm in model.bands_nm]
            assert img.metadata["m2s2 event id"] == fr.event_id
            assert img.metadata["m2s2 lighting"] == fr.meta["event"]["lighting"]


def test_existing_files_are_kept_unless_overwrite(tmp_path, hubble):
    out = tmp_path / "envi"
    with hubble.open() as st:
        first = export_envi(st, out)
        assert first.images == 16 and len(first.files) == 32
        hdr = first.files[0]
        hdr.write_text("not an ENVI header")
        with pytest.raises(EnviExportError, match="--overwrite"):
            export_envi(st, out)
        assert hdr.read_text() == "not an ENVI header"
        export_envi(st, out, overwrite=True)
        assert hdr.read_text().startswith("ENVI\n")
    res = run_cli("export", hubble.path, "--format", "envi", "--out", out)
    assert res.exit_code != 0 and "--overwrite" in res.output
