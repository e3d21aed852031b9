"""Export: the published M2S2 layout (8-bit and lossless 16-bit); the hf layout is in test_export_hf.py."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pytest
from cli_support import run_cli
from shared_sessions import N, Written, export_session_of, write_session

from m2s2hil.store.export import ExportError, export_session, to_8bit
from m2s2hil.store.session import SessionStore


@pytest.fixture
def hubble(shared_sessions) -> Written:
    """Hubble B2, written once per test process; the tests here only read it."""
    return export_session_of(shared_sessions)


def read_png(path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, path
    return img


def test_to_8bit_drops_the_two_low_bits():
    raw = np.array([0, 3, 4, 511, 1020, 1023], np.uint16)
    assert to_8bit(raw, 10).tolist() == [0, 0, 1, 127, 255, 255]
    assert to_8bit(np.array([200], np.uint16), 8).tolist() == [200]


def test_m2s2_layout_paths_bit_depths_and_metadata(tmp_path, hubble):
    st, raws = hubble.open(), hubble.arrays
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
    st, _ = write_session(tmp_path / "data", frames_per_pose=2)
    export_session(st, tmp_path / "out", "m2s2")
    names = sorted(p.name for p in (tmp_path / "out" / "HIL" / "Hubble" / "b2" / "e0").glob("solo_*.png"))
    assert names == sorted(f"solo_{k}.png" for k in range(8))
    rows = list(csv.DictReader((tmp_path / "out" / "metadata" / f"{st.session_id}.csv").open()))
    for r in rows:
        assert int(r["k"]) == int(r["azimuth_index"]) + 4 * int(r["frame"])
    st.close()


def test_existing_files_are_not_overwritten_unless_asked(tmp_path, hubble):
    st = hubble.open()
    export_session(st, tmp_path / "out", "m2s2")
    with pytest.raises(ExportError, match="already exists"):
        export_session(st, tmp_path / "out", "m2s2")
    assert export_session(st, tmp_path / "out", "m2s2", overwrite=True).images == 16
    with pytest.raises(ExportError, match="unknown export layout"):
        export_session(st, tmp_path / "x", "zip")
    st.close()


def test_cli_export_by_id_and_by_folder(tmp_path, hubble):
    sid, root = hubble.session_id, hubble.root
    res = run_cli("export", sid, "--layout", "m2s2", "--out", tmp_path / "o1", "--root", root)
    assert res.exit_code == 0, res.output
    assert "exported 16 image(s)" in res.output
    assert (tmp_path / "o1" / "HIL" / "Hubble" / "b2" / "e2" / "dir_3.png").is_file()
    res = run_cli("export", hubble.path, "--layout", "hf", "--out", tmp_path / "o2")
    assert res.exit_code == 0, res.output
    assert (tmp_path / "o2" / "data" / f"train-{sid}.parquet").is_file()
    res = run_cli("export", sid, "--layout", "tar", "--out", tmp_path / "o3", "--root", root)
    assert res.exit_code == 2 and "--layout must be one of" in res.stderr
    res = run_cli("export", "missing", "--out", tmp_path / "o4", "--root", root)
    assert res.exit_code == 2 and "no session 'missing'" in res.stderr


def _snapshot(folder) -> dict[str, tuple[int, int]]:
    return {p.relative_to(folder).as_posix(): (p.stat().st_mtime_ns, p.stat().st_size)
            for p in sorted(folder.rglob("*"))}


EXPORT_AS_NOBODY = """
import sys
from m2s2hil.store.export import export_session
from m2s2hil.store.session import SessionStore
with SessionStore.open_path(sys.argv[1]) as st:
    print(export_session(st, sys.argv[2], sys.argv[3]).images)
"""


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("setpriv") is None,
                    reason="needs root to run the export as another user (setpriv)")
@pytest.mark.slow  # a subprocess: ~8 s
def test_an_archived_read_only_session_exports_and_is_left_untouched(hubble, layout="m2s2"):
    """The export runs as an unprivileged user on a session folder that user cannot write
    (root ignores permissions, so it would not prove anything)."""
    base = Path(tempfile.mkdtemp(prefix="m2s2hil-ro-", dir="/tmp"))
    try:
        base.chmod(0o755)
        folder = hubble.copy_to(base / "data").path
        with SessionStore.open_path(folder, mode="write") as st:
            st.complete()
        (base / "data").chmod(0o755)
        for p in [folder, *folder.rglob("*")]:
            p.chmod(0o555 if p.is_dir() else 0o444)
        out = base / "out"
        out.mkdir(mode=0o777)
        out.chmod(0o777)
        before = _snapshot(folder)
        env = {**os.environ, "HOME": str(out), "HF_HOME": str(out / ".hf"), "HF_DATASETS_OFFLINE": "1",
               "NUMBA_CACHE_DIR": str(out / ".numba"), "MPLCONFIGDIR": str(out / ".mpl")}
        res = subprocess.run(["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", sys.executable,
                              "-c", EXPORT_AS_NOBODY, str(folder), str(out / "x"), layout],
                             capture_output=True, text=True, env=env, cwd=str(out), timeout=120)
        assert res.returncode == 0, res.stderr[-2000:]
        assert res.stdout.strip().splitlines()[-1] == "16"
        assert _snapshot(folder) == before  # no journal event, no -shm/-wal, nothing written
    finally:
        for p in [base, *base.rglob("*")]:
            p.chmod(0o755 if p.is_dir() else 0o644)
        shutil.rmtree(base, ignore_errors=True)


@pytest.mark.parametrize("layout", ["m2s2", "hf"])
def test_exporting_records_nothing_in_the_session(tmp_path, hubble, layout):
    mine = hubble.copy_to(tmp_path / "data")
    with SessionStore.open_path(mine.path, mode="write") as st:
        st.complete()
    with SessionStore.open_path(mine.path) as ro:
        n_events = len(ro.events())
        export_session(ro, tmp_path / "out", layout)
    with SessionStore.open_path(mine.path) as ro:
        assert len(ro.events()) == n_events
        assert not [e for e in ro.events() if e["kind"] == "export"]
