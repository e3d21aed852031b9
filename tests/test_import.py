"""Import of the published layout (8-bit PNG mosaics) and of camera raws through rawpy."""

from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest
import tifffile
from cli_support import run_cli

from m2s2hil.config import RigConfig, default_rig
from m2s2hil.plan import Sweep
from m2s2hil.store.catalogue import list_sessions
from m2s2hil.store.export import export_session
from m2s2hil.store.frame_files import encode_png
from m2s2hil.store.importer import DatasetImportError, import_dataset
from m2s2hil.store.session import SessionStore

N = 64


def small_rig() -> RigConfig:
    data = default_rig().model_dump(mode="json")
    data["camera"]["model"].update(width=N, height=N)
    return RigConfig.model_validate(data)


def captured_session(root, satellite: str, build: str) -> SessionStore:
    sweep = Sweep(satellite=satellite, build=build, lighting=["strong", "weak"], tilts=["E1"],
                  azimuth_step_deg=30, dark={"frames": 0})
    st = SessionStore.create(root, sweep, small_rig())
    rng = np.random.default_rng(7)
    for ev in sweep.expand(st.rig):
        st.write_frame(ev, rng.integers(0, 1024, (N, N), dtype=np.uint16))
    return st


def png8(value: int | np.ndarray, channels: int = 3) -> bytes:
    g = np.full((N, N), value, np.uint8) if np.isscalar(value) else value
    return encode_png(np.dstack([g] * channels) if channels == 3 else g)


def write_dng(path, mosaic: np.ndarray, white: int = 1023) -> None:
    """A minimal valid DNG (uncompressed CFA) written with tifffile; LibRaw reads it."""
    tags = [
        (50706, "B", 4, (1, 4, 0, 0), True),  # DNGVersion
        (50708, "s", 0, "m2s2hil test camera", True),  # UniqueCameraModel
        (33421, "H", 2, (2, 2), True),  # CFARepeatPatternDim
        (33422, "B", 4, (0, 1, 1, 2), True),  # CFAPattern
        (50717, "I", 1, white, True),  # WhiteLevel
    ]
    tifffile.imwrite(path, mosaic, photometric=32803, extratags=tags, subfiletype=0, metadata=None)


def test_round_trip_export_import_gives_the_same_8bit_mosaics(tmp_path):
    a = captured_session(tmp_path / "cap", "voyager", "B3")
    b = captured_session(tmp_path / "cap", "hubble", "B1")
    out = tmp_path / "release"
    export_session(a, out, "m2s2")
    export_session(b, out, "m2s2")
    shutil.rmtree(out / "HIL16")  # as released: 8-bit only, no sidecars (the lossless path:
    shutil.rmtree(out / "metadata")  # test_roundtrip.py)
    stores = import_dataset(out, tmp_path / "imported", azimuth_step_deg=30)
    assert [(s.sweep.satellite, s.sweep.build) for s in stores] == [("hubble", "B1"), ("voyager", "B3")]
    for orig, imp in zip((b, a), stores, strict=True):
        assert imp.rig.camera.model.bit_depth == 8 and imp.rig.camera.model.width == N
        assert imp.sweep.lighting == ["weak", "strong"] and imp.sweep.tilts == ["E1"]
        assert imp.completed_event_ids() == orig.completed_event_ids()  # same ids: same poses
        assert imp.state == "completed" and imp.verify() == []
        for fr in orig.frames():
            raw, _ = orig.read_raw(fr.event_id)
            got, meta = imp.read_raw(fr.event_id)
            assert got.dtype == np.uint16 and np.array_equal(got, raw >> 2)
            assert meta["source_format"] == "png8" and meta["exposure_known"] is False
            assert meta["source_file"].startswith("HIL/")
        # exporting the imported session again reproduces the release byte for byte in pixels
        again = tmp_path / f"again-{imp.session_id}"
        export_session(imp, again, "m2s2")
        for p in (again / "HIL").rglob("*.png"):
            rel = p.relative_to(again)
            assert np.array_equal(read_png(p), read_png(out / rel))
        imp.close()
    a.close()
    b.close()


def read_png(path) -> np.ndarray:
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)


def _release(root, files: dict[str, bytes]):
    for rel, data in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)
    return root


@pytest.mark.parametrize(
    ("bad_rel", "data", "words"),
    [
        ("HIL/Hubble/b1/e0/notes.txt", b"hello", "unexpected file name"),
        ("HIL/Hubble/b1/e0/solo_1.jpg", b"jpeg", "unsupported file type"),
        ("HIL/Hubble/b1/e9/solo_1.png", None, "unknown elevation"),
        ("HIL/Hubble/b4/e0/solo_1.png", None, "unknown build"),
        ("HIL/Hubbel/b1/e0/solo_1.png", None, "did you mean"),
        ("HIL/Hubble/b1/e0/bright_1.png", None, "lighting 'bright'"),
        ("HIL/Hubble/b1/solo_1.png", None, "unexpected file"),
        ("HIL/Voyager/b2/e1/all_3.png", b"\x89PNG\r\n\x1a\n garbage", "not a readable PNG"),
        ("HIL/Voyager/b2/e1/all_3.png", "colour", "channels differ"),
        ("HIL/Voyager/b2/e1/all_3.png", "small", "mosaic is 32x32"),
        ("HIL/Voyager/b2/e1/all_3.dng", b"II*\x00 broken raw", "LibRaw cannot read"),
    ],
)
def test_a_bad_file_is_named_and_nothing_is_imported(tmp_path, bad_rel, data, words):
    good = {f"HIL/Hubble/b1/e0/{light}_{k}.png": png8(10 * k + 1)
            for light in ("solo", "dir") for k in range(3)}
    good.update({f"HIL/Voyager/b2/e1/all_{k}.png": png8(k) for k in range(3)})
    if data is None:
        data = png8(5)
    elif data == "colour":
        data = encode_png(np.dstack([np.zeros((N, N), np.uint8), np.ones((N, N), np.uint8),
                                     np.zeros((N, N), np.uint8)]))
    elif data == "small":
        data = encode_png(np.zeros((32, 32), np.uint8))
    src = _release(tmp_path / "src", {**good, bad_rel: data})
    root = tmp_path / "root"
    with pytest.raises(DatasetImportError) as info:
        import_dataset(src, root)
    assert info.value.path == str(src / bad_rel)
    assert words in str(info.value)
    assert not root.exists() or list(root.iterdir()) == []  # no session, no staging folder
    assert list_sessions(root) == []


def test_files_outside_hil_and_dotfiles_are_ignored(tmp_path):
    src = _release(tmp_path / "src", {
        "README.md": b"# M2S2", "HIL/.DS_Store": b"x", "HIL/ISS/b2/e2/dir_0.png": png8(9, channels=1),
        "metadata/x.csv": b"a,b",
    })
    (st,) = import_dataset(src / "HIL", tmp_path / "root")
    raw, _ = st.read_raw("directional/E2/az000/f0")
    assert np.array_equal(raw, np.full((N, N), 9, np.uint16))
    st.close()


def test_dng_through_rawpy(tmp_path):
    rng = np.random.default_rng(3)
    mosaics = {k: rng.integers(0, 1024, (N, N), dtype=np.uint16) for k in (0, 1, 36)}
    src = tmp_path / "src" / "HIL" / "ISS" / "b3" / "e0"
    src.mkdir(parents=True)
    for k, m in mosaics.items():
        write_dng(src / f"all_{k}.dng", m)
    (st,) = import_dataset(tmp_path / "src", tmp_path / "root")
    assert st.rig.camera.model.bit_depth == 10
    assert st.sweep.frames_per_pose == 2  # k = 36 is a second frame at azimuth 0
    for k, m in mosaics.items():
        eid = f"strong/E0/az{(k % 36) * 10:03d}/f{k // 36}"
        raw, meta = st.read_raw(eid)
        assert np.array_equal(raw, m) and meta["source_format"] == "raw:dng"
    st.close()


def test_mixed_bit_depths_in_one_build_are_refused(tmp_path):
    src = tmp_path / "src" / "HIL" / "ISS" / "b3" / "e0"
    src.mkdir(parents=True)
    write_dng(src / "all_0.dng", np.zeros((N, N), np.uint16))
    (src / "all_1.png").write_bytes(png8(3))
    with pytest.raises(DatasetImportError, match="8-bit data among 10-bit files"):
        import_dataset(tmp_path / "src", tmp_path / "root")
    assert list_sessions(tmp_path / "root") == []


def test_missing_hil_folder_and_unknown_layout(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetImportError, match="no HIL folder"):
        import_dataset(tmp_path / "empty", tmp_path / "root")
    with pytest.raises(DatasetImportError, match="not a folder"):
        import_dataset(tmp_path / "nothing", tmp_path / "root")
    with pytest.raises(Exception, match="unknown import layout"):
        import_dataset(tmp_path / "empty", tmp_path / "root", layout="coco")


def test_cli_import(tmp_path):
    src = _release(tmp_path / "src", {f"HIL/Hubble/b2/e1/solo_{k}.png": png8(k) for k in range(4)})
    res = run_cli("import", src, "--layout", "m2s2", "--root", tmp_path / "r")
    assert res.exit_code == 0, res.output
    assert ": 4 frame(s)" in res.output
    (info,) = list_sessions(tmp_path / "r")
    assert (info.satellite, info.build, info.frames) == ("hubble", "B2", 4)
