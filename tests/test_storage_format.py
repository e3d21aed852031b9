"""The compressed storage format: lossless raw and darks other readers open, cubes computed
when read bit-identical to the cubes stored before, legacy sessions still read, metadata
built and encoded once."""

from __future__ import annotations

import io
import json
from datetime import UTC, datetime
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile
from engine_helpers import session, small_rig_config, small_sweep
from PIL import Image

from m2s2hil.config import RigConfig, StorageConfig, default_rig
from m2s2hil.plan import Sweep
from m2s2hil.processing.chain import FrameProcessor
from m2s2hil.processing.dark import build_master_dark
from m2s2hil.store.cubes import CubeComputer
from m2s2hil.store.session import SessionStore

N = 64


def rig_with(fmt: str = "compressed", cubes: bool = False, n: int = N) -> RigConfig:
    data = default_rig().model_dump(mode="json")
    data["camera"]["model"].update(width=n, height=n)
    data["storage"] = {"format": fmt, "cubes": cubes}
    return RigConfig.model_validate(data)


def sweep() -> Sweep:
    return Sweep(satellite="hubble", build="B2", lighting=["weak"], tilts=["E1"], azimuth_step_deg=90,
                 dark={"frames": 4})


def dark_frames(seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.poisson(12.0, (N, N)).astype(np.uint16) for _ in range(4)]


def scene_raw(i: int) -> np.ndarray:
    """A 10-bit frame with light, dark current and a few saturated pixels."""
    rng = np.random.default_rng(100 + i)
    y, x = np.mgrid[0:N, 0:N]
    signal = 300 + 250 * np.sin(x / 7.0 + i) * np.cos(y / 5.0)
    raw = rng.poisson(np.clip(signal, 0, None) + 12.0).clip(0, 1023).astype(np.uint16)
    raw[3, 5] = 1023
    return raw


def capture_like_the_engine(st: SessionStore, *, cube_to_store: bool = True) -> dict[str, np.ndarray]:
    """What the engine does per session: a master dark, then frames processed with it."""
    evs = st.sweep.expand(st.rig)
    dark_ev = next(e for e in evs if e.kind == "dark")
    master = build_master_dark(dark_frames(), exposure_s=dark_ev.exposure_s, gain=dark_ev.gain,
                               temperature_c=30.0, created=datetime(2026, 12, 1, tzinfo=UTC))
    st.write_dark(dark_ev, master.data, meta=master.provenance())
    proc = FrameProcessor(st.sweep.processing, st.rig.camera.model, dark=master)
    cubes = {}
    for i, ev in enumerate(e for e in evs if e.kind == "frame"):
        cube = np.array(proc.process(scene_raw(i)).cube, copy=True)
        cubes[ev.event_id] = cube
        st.write_frame(ev, scene_raw(i), cube if cube_to_store else None, np.zeros((4, 4, 3), np.uint8),
                       meta={"dark_id": dark_ev.event_id, "temperature_c": 30.0})
    return cubes


def write_the_old_way(folder: Path, cube: np.ndarray, raw: np.ndarray, dark: np.ndarray) -> dict[str, Path]:
    """Files exactly as the store wrote them before the compressed format (0.1): uncompressed
    uint16 raw, float32 master dark, float32 cube, JSON descriptions."""
    folder.mkdir(parents=True, exist_ok=True)
    out = {"raw": folder / "raw.tiff", "dark": folder / "dark.tiff", "cube": folder / "cube.tiff"}
    for key, arr in (("raw", raw), ("dark", dark.astype(np.float32)), ("cube", cube.astype(np.float32))):
        desc = json.dumps({"shape": list(arr.shape)})
        tifffile.imwrite(out[key], arr, description=desc, metadata=None, photometric="minisblack")
    return out


def test_computed_cube_equals_the_cube_stored_the_old_way_bit_for_bit(tmp_path):
    st = SessionStore.create(tmp_path / "new", sweep(), rig_with(), session_id="new")
    cubes = capture_like_the_engine(st)
    dark_rec = st.darks()[0]
    for i, (event_id, cube) in enumerate(cubes.items()):
        old = write_the_old_way(tmp_path / "old" / str(i), cube, scene_raw(i), st.load_dark(dark_rec.dark_id))
        assert "cube" not in st.frame(event_id).files  # not stored by default
        computed = st.read_cube(event_id)
        stored_before = tifffile.imread(old["cube"])
        assert computed.dtype == stored_before.dtype == np.float32
        assert computed.tobytes() == stored_before.tobytes()  # bit for bit, NaN-safe
        # the old session's float32 dark gives the same processing as today's uint16 one
        old_dark = tifffile.imread(old["dark"])
        assert old_dark.dtype == np.float32 and np.array_equal(old_dark, st.load_dark(dark_rec.dark_id))
    recipe = st.frame(next(iter(cubes))).meta["cube"]
    assert recipe["method"] == "superpixel" and recipe["stored"] is False and recipe["recipe"].endswith("/1")
    st.close()


def test_raw_and_dark_are_deflate_tiffs_that_pillow_and_opencv_read(tmp_path):
    st = SessionStore.create(tmp_path / "d", sweep(), rig_with(), session_id="s")
    capture_like_the_engine(st)
    fr = st.frames()[0]
    raw_path = st.path / fr.files["raw"].path
    dark_path = st.path / st.darks()[0].files["master"].path
    for path in (raw_path, dark_path):
        with tifffile.TiffFile(path) as tf:
            assert tf.pages[0].compression == tifffile.COMPRESSION.ADOBE_DEFLATE
            assert tf.pages[0].predictor == 1  # no predictor: it enlarged these frames (benchmarks)
            arr = tf.asarray()
            assert sum(tf.pages[0].databytecounts) < 0.8 * arr.nbytes
        assert arr.dtype == np.uint16
        assert np.array_equal(np.asarray(Image.open(path)), arr)  # Pillow: mode I;16
        assert np.array_equal(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), arr)
    assert np.array_equal(tifffile.imread(raw_path), scene_raw(0))
    st.close()


def test_a_dark_that_is_not_whole_numbers_stays_float32(tmp_path):
    st = SessionStore.create(tmp_path / "d", sweep(), rig_with(), session_id="s")
    ev = next(e for e in st.sweep.expand(st.rig) if e.kind == "dark")
    master = np.full((N, N), 2.5, np.float32)
    st.write_dark(ev, master)
    got = st.load_dark(ev.event_id)
    assert got.dtype == np.float32 and np.array_equal(got, master)
    st.close()


def test_legacy_sessions_read_raw_darks_and_stored_cubes(tmp_path):
    st = SessionStore.create(tmp_path / "d", sweep(), rig_with("legacy"), session_id="old")
    cubes = capture_like_the_engine(st)
    fr = st.frames()[0]
    assert set(fr.files) == {"raw", "cube", "preview"}
    with tifffile.TiffFile(st.path / fr.files["raw"].path) as tf:
        assert tf.pages[0].compression == tifffile.COMPRESSION.NONE
    assert st.load_dark(st.darks()[0].dark_id).dtype == np.float32
    raw, meta = st.read_raw(fr.event_id)
    assert np.array_equal(raw, scene_raw(0)) and meta["storage_format"] == "legacy"
    assert np.array_equal(st.read_cube(fr.event_id), cubes[fr.event_id])
    st.close()


def test_cube_cache_option_stores_compressed_cubes(tmp_path):
    st = SessionStore.create(tmp_path / "d", sweep(), rig_with(cubes=True), session_id="c")
    cubes = capture_like_the_engine(st)
    fr = st.frames()[0]
    with tifffile.TiffFile(st.path / fr.files["cube"].path) as tf:
        assert tf.pages[0].compression == tifffile.COMPRESSION.ADOBE_DEFLATE
    assert fr.meta["cube"]["stored"] is True
    assert np.array_equal(st.read_cube(fr.event_id), cubes[fr.event_id])
    st.close()


def test_frame_metadata_is_encoded_once_the_same_in_the_tiff_and_the_journal(tmp_path):
    st = SessionStore.create(tmp_path / "d", sweep(), rig_with(), session_id="m")
    capture_like_the_engine(st)
    fr = st.frames()[0]
    row = st.journal.query("SELECT meta FROM frames WHERE event_id = ?", (fr.event_id,))[0]["meta"]
    with tifffile.TiffFile(st.path / fr.files["raw"].path) as tf:
        desc = tf.pages[0].description
    assert desc == f'{{"shape": [{N}, {N}], ' + row[1:]  # the journal's text, shape first for tifffile
    meta = json.loads(row)
    assert meta["session_id"] == "m" and meta["storage_format"] == "compressed"
    assert meta["temperature_c"] == 30.0 and meta["exposure_s"] == fr.meta["event"]["exposure_s"]
    st.close()


def test_engine_frames_recompute_to_the_cube_the_engine_computed(tmp_path):
    """End to end on the simulated rig: with the cube cache on, the stored cube is exactly what
    the engine's processing stage computed; recomputing from raw + stored dark matches it."""
    cfg = small_rig_config(128).model_copy(update={"storage": StorageConfig(cubes=True)})
    with session(tmp_path, small_sweep(), config=cfg) as (_rig, store, engine, _events):
        engine.run()
        frames = store.frames()
        assert len(frames) == 4
        computer = CubeComputer()
        for fr in frames:
            stored = tifffile.imread(io.BytesIO(store.read_file(fr.files["cube"])))
            recomputed = computer.read(_without_cube(store), fr.event_id)
            assert recomputed.tobytes() == stored.tobytes()


class _without_cube:
    """A read view of a store whose frames hide their stored cube (forces recomputation)."""

    def __init__(self, store: SessionStore) -> None:
        self._s = store

    def __getattr__(self, name: str):
        return getattr(self._s, name)

    def frame(self, event_id: str):
        fr = self._s.frame(event_id)
        return fr.model_copy(update={"files": {k: v for k, v in fr.files.items() if k != "cube"}})


def test_a_cube_that_cannot_be_computed_is_a_typed_error_naming_the_frame(tmp_path):
    from m2s2hil.store.cubes import CubeUnavailable

    st = SessionStore.create(tmp_path / "d", sweep(), rig_with(), session_id="x")
    ev = next(e for e in st.sweep.expand(st.rig) if e.kind == "frame")
    st.write_frame(ev, scene_raw(0), meta={"dark_id": "dark/none"})  # a dark the session lacks
    with pytest.raises(CubeUnavailable, match="no dark 'dark/none'"):
        st.read_cube(ev.event_id)
    ev2 = [e for e in st.sweep.expand(st.rig) if e.kind == "frame"][1]
    st.write_frame(ev2, scene_raw(1), meta={"dark_id": None, "calibration": {"source": "cal.json"}})
    with pytest.raises(CubeUnavailable, match="calibrated frame without its stored cube"):
        st.read_cube(ev2.event_id)
    st.close()


@pytest.mark.parametrize("isal", [True, False], ids=["isal", "libdeflate"])
def test_strip_compressed_tiffs_decode_exactly_with_either_compressor(monkeypatch, isal):
    """Raw frames and darks are cut into row strips compressed by ISA-L (or libdeflate without
    it): every reader gets the exact pixels back, uint16 and float32 alike."""
    from m2s2hil.store import frame_files

    if not isal:
        monkeypatch.setattr(frame_files, "_isal_zlib", None)
    elif frame_files._isal_zlib is None:
        pytest.skip("isal is not installed")
    rng = np.random.default_rng(7)
    raw = rng.integers(0, 1024, (300, 2048), dtype=np.uint16)  # not a multiple of the strip height
    data = frame_files.encode_raw(raw, {"event": "x"})
    with tifffile.TiffFile(io.BytesIO(data)) as tf:
        page = tf.pages[0]
        assert page.compression == tifffile.COMPRESSION.ADOBE_DEFLATE
        assert page.rowsperstrip == 64 and len(page.dataoffsets) == 5  # 256 KiB strips, the last short
        assert np.array_equal(page.asarray(), raw)
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(data))), raw)
    assert np.array_equal(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED), raw)
    big_endian = raw.astype(">u2")  # written little-endian whatever the array's byte order
    assert np.array_equal(frame_files.decode_tiff(frame_files.encode_dark(big_endian, {}))[0], raw)
    dark = rng.normal(40, 3, (64, 64)).astype(np.float32)
    assert np.array_equal(frame_files.decode_tiff(frame_files.encode_dark(dark, {}))[0], dark)


def test_previews_are_jpeg_in_the_compressed_format_and_png_in_the_legacy_one(tmp_path):
    y, x = np.mgrid[0:N, 0:N]
    rgb = np.stack([4 * x, 4 * y, np.full_like(x, 40)], axis=-1).astype(np.uint8)  # red right, green down
    rgb[20:40, 20:40] = (30, 60, 220)  # a blue panel
    for fmt, suffix in (("compressed", ".preview.jpg"), ("legacy", ".preview.png")):
        st = SessionStore.create(tmp_path / fmt, sweep(), rig_with(fmt), session_id=fmt)
        ev = next(e for e in st.sweep.expand(st.rig) if e.kind == "frame")
        fr = st.write_frame(ev, scene_raw(0), None, rgb)
        assert fr.files["preview"].path.endswith(suffix)
        from m2s2hil.store.frame_files import decode_image

        back = decode_image(st.read_file(fr.files["preview"]))
        assert back.shape == rgb.shape and back.dtype == np.uint8
        err = np.abs(back.astype(int) - rgb)
        if fmt == "legacy":
            assert not err.any()
        else:  # a quick-look: close to what the engine rendered, RGB order kept
            assert err.mean() < 3.0 and err.max() < 40
        st.close()


def test_a_stored_dark_comes_back_with_the_provenance_it_was_stored_with(tmp_path):
    """A resumed run (engine.darks.SessionDarks.load) and computed cubes rebuild the master dark
    from the journal: same pixels, same provenance, read noise included (its low-light check)."""
    from m2s2hil.store.cubes import master_dark

    st = SessionStore.create(tmp_path / "d", sweep(), rig_with(), session_id="r")
    ev = next(e for e in st.sweep.expand(st.rig) if e.kind == "dark")
    master = build_master_dark(dark_frames(), exposure_s=ev.exposure_s, gain=ev.gain,
                               temperature_c=30.0, created=datetime(2026, 12, 1, tzinfo=UTC))
    assert master.read_noise_dn is not None
    st.write_dark(ev, master.data, meta=master.provenance())
    back = master_dark(st, ev.event_id)
    assert np.array_equal(back.data, master.data) and back.provenance() == master.provenance()
    """A resumed run (engine.darks.SessionDarks.load) and computed cubes rebuild the master dark
    from the journal: same pixels, same provenance, read noise included (its low-light check)."""
    from m2s2hil.store.cubes import master_dark
    st.close()
