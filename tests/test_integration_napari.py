"""The npe2 plugin: its manifest validates and is discovered; its reader opens a session and a Zarr export."""

from __future__ import annotations

from importlib.resources import files

import numpy as np
import pytest
from shared_sessions import export_session_of

from m2s2hil.integrations.napari.reader import get_reader, read_session, read_zarr, superpixel_bands

npe2 = pytest.importorskip("npe2", reason="the napari extra (npe2) is not installed")


@pytest.fixture
def hubble(shared_sessions):
    return export_session_of(shared_sessions)


def test_manifest_validates_and_names_the_reader():
    path = files("m2s2hil.integrations.napari") / "napari.yaml"
    pm = npe2.PluginManifest.from_file(str(path))
    assert pm.name == "m2s2hil"
    reader, = pm.contributions.readers
    assert reader.accepts_directories
    cmd, = pm.contributions.commands
    assert cmd.id == reader.command and cmd.python_name == "m2s2hil.integrations.napari.reader:get_reader"
    # the installed distribution's entry point leads npe2 to the same manifest
    assert npe2.PluginManifest.from_distribution("m2s2hil").name == "m2s2hil"


def test_npe2_finds_our_reader_for_a_session(hubble):
    pm = npe2.PluginManager()
    pm.discover(include_npe1=False)
    readers = [r for r in pm.iter_compatible_readers([str(hubble.path)]) if r.plugin_name == "m2s2hil"]
    assert readers, "npe2 offers no m2s2hil reader for a session folder"
    fn = pm.get_command(readers[0].command).exec  # resolves python_name
    assert fn is not None


def test_session_opens_as_cube_and_raw(hubble):
    reader = get_reader(str(hubble.path))
    assert reader is read_session
    layers = reader(str(hubble.path))
    (cube, ck, ct), (raw, _rk, rt) = layers[:2]
    with hubble.open() as st:
        m = st.rig.camera.model
        ids = [fr.event_id for fr in st.frames()]
        assert ct == "image" and cube.shape[:2] == (len(ids), m.n_bands)
        assert ck["metadata"]["wavelength_nm"] == list(m.bands_nm)
        assert ck["metadata"]["fwhm_nm"] == list(m.fwhm_nm)
        assert ck["metadata"]["event_ids"] == ids
        assert np.array_equal(cube[3], st.read_cube(ids[3]))
    assert rt == "image" and np.array_equal(raw[5], hubble.arrays[ids[5]])
    assert ck["scale"][2] * cube.shape[2] == raw.shape[1]  # the cube lies over the raw
    assert get_reader(str(hubble.path.parent)) is None and get_reader([str(hubble.path)] * 2) is None


def test_zarr_export_opens_with_labels(tmp_path, hubble):
    pytest.importorskip("xarray", reason="the analysis extra (xarray, zarr) is not installed")
    from m2s2hil.store.zarr_export import export_zarr

    labels = (np.arange(64 * 64, dtype=np.uint8).reshape(64, 64) % 7)
    copy = hubble.copy_to(tmp_path / "s")
    out = tmp_path / "data.zarr"
    with copy.open() as st:
        export_zarr(st, out)
        model = st.rig.camera.model
    assert get_reader(str(out)) is read_zarr
    layers = read_zarr(str(out))
    (bands, bk, _), (raw, _, _) = layers[:2]
    assert bk["metadata"]["wavelength_nm"] == [float(np.float32(b)) for b in model.bands_nm]
    assert raw.shape == (16, 64, 64) and bands.shape == (16, model.n_bands, 16, 16)
    ids = bk["metadata"]["event_ids"]
    assert np.array_equal(raw[0], hubble.arrays[ids[0]])
    layout = np.asarray(model.layout)
    b0 = np.argwhere(layout == 0)
    assert bands[0, 0, 2, 3] == pytest.approx(np.mean([raw[0, 8 + r, 12 + c] for r, c in b0]))
    assert len(layers) == 2  # no ground truth in this session: no labels layer
    assert np.array_equal(superpixel_bands(labels[None].astype(np.uint16), layout, model.n_bands).shape,
                          (1, model.n_bands, 16, 16))


@pytest.mark.timeout(120)
def test_a_captured_session_opens_with_its_ground_truth_labels(tmp_path):
    from engine_helpers import session, small_rig_config, small_sweep

    with session(tmp_path, small_sweep(), config=small_rig_config(64)) as (_, store, engine, _):
        engine.run()
        path = store.path
        frames = store.frames()
        truth = [store.read_file(fr.files["truth_labels"]) for fr in frames]
    layers = get_reader(str(path))(str(path))
    labels, _lk, lt = layers[-1]
    assert lt == "labels" and labels.shape == (len(frames), 64, 64)
    from m2s2hil.store.frame_files import decode_image

    for i, data in enumerate(truth):
        assert np.array_equal(labels[i], decode_image(data))
    assert labels.max() > 0  # the mockup is in view: some pixel is a material
