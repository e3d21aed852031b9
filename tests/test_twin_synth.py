"""The synthetic domain (m2s2hil.twin.synth): renders by the paper's protocol, its own session kind."""

from __future__ import annotations

import numpy as np
import pytest
from cli_support import run_cli
from m2s2hil.simulators.clock import VirtualClock
from m2s2hil.simulators.scene import Scene
from shared_sessions import small_rig, synthetic_session_of

from m2s2hil.analysis.segmenters.rgb import band_colours, wavelength_to_rgb
from m2s2hil.catalog import load_catalog
from m2s2hil.errors import UsageError
from m2s2hil.plan import Sweep
from m2s2hil.sim_config import build_world
from m2s2hil.store.session import SessionStore
from m2s2hil.twin.synth import band_images, pose_key


@pytest.fixture()
def synth(shared_sessions):
    return synthetic_session_of(shared_sessions)


def test_every_pose_has_rgb_ten_bands_and_a_mask(synth):
    with synth.open() as st:
        assert st.kind == "synthetic" and st.state == "completed" and st.verify() == []
        frames = st.frames()
        assert sorted({pose_key(f.meta, f.event_id) for f in frames}) == sorted(
            (e, a) for e in ("E0", "E3") for a in (0, 180))
        e3 = next(f for f in frames if f.meta["elevation"] == "E3")
        assert e3.meta["pose"]["tilt_deg"] == 30.0 and e3.meta["domain"] == "synthetic"
        assert "raw" not in e3.files
        rgb, bands, mask = band_images(st, e3.event_id)
    assert rgb.shape == (32, 32, 3) and bands.shape == (10, 32, 32, 3) and mask.shape == (32, 32)
    names = e3.meta["class_names"]
    assert set(np.unique(mask)) <= set(range(len(names))) and (mask > 0).any()


def test_band_renders_are_lit_with_the_bands_colour(synth):
    with synth.open() as st:
        fr = next(f for f in st.frames() if f.meta["elevation"] == "E0")
        rgb, bands, mask = band_images(st, fr.event_id)
        lights = np.array(fr.meta["synthetic"]["band_light_rgb"])
    bands_nm = fr.meta["synthetic"]["bands_nm"]
    assert np.allclose(lights, band_colours(bands_nm, gamma=0.8), atol=1e-6)
    assert lights[5].tolist() == pytest.approx(list(wavelength_to_rgb(666.0, 0.8)), abs=1e-6)
    red = bands[5][mask > 0].astype(float)  # 666 nm: pure red light, nothing in green or blue
    assert red[:, 0].mean() > 10 and red[:, 1].max() == 0 and red[:, 2].max() == 0
    blue = bands[0][mask > 0].astype(float)  # 431 nm: blue with a little red (Bruton's violet)
    assert blue[:, 2].mean() > blue[:, 0].mean() and blue[:, 1].max() == 0
    assert rgb[mask > 0].mean() > red.mean()  # white light is brighter than one band's


def test_mask_is_the_scenes_label_map_at_the_pose(synth):
    rig = small_rig()
    m = rig.camera.model
    with synth.open() as st:
        fr = next(f for f in st.frames() if pose_key(f.meta) == ("E0", 180))
        _, _, mask = band_images(st, fr.event_id)
    scene = Scene(32, 32, m.bands_nm, m.fwhm_nm, m.layout)
    b = load_catalog().build("hubble", "B2")
    lamps = {ch: 1.0 for ch in rig.lamp_channels("strong")}
    world = build_world(rig, VirtualClock())
    sh = scene.render("hubble", b.materials, 180.0, rig.elevations["E0"], lamps, world.lamp_info, build="B2")
    assert np.array_equal(mask, sh.label)


def test_a_hil_session_needs_its_raw_mosaic(tmp_path):
    sweep = Sweep(satellite="hubble", build="B2", lighting=["weak"], tilts=["E1"], azimuth_step_deg=180)
    with SessionStore.create(tmp_path, sweep, small_rig()) as st:
        assert st.kind == "hil"
        ev = next(e for e in sweep.expand(st.rig) if e.kind == "frame")
        with pytest.raises(UsageError, match="raw mosaic is required in a hil session"):
            st.write_frame(ev, None)


def test_synth_command_refuses_bad_input_in_one_line(tmp_path):
    r = run_cli("synth", "--sat", "hubble", "--build", "B2", "--tilts", "E9", "--root", tmp_path)
    assert r.exit_code == 2 and "unknown elevation 'E9'" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    r = run_cli("synth", "--sat", "hubble", "--build", "B2", "--size", "4", "--root", tmp_path)
    assert r.exit_code == 2 and "outside 16" in r.stderr


class Threshold:
    """A stand-in segmenter: foreground where the brightest channel passes half its maximum."""

    name = "threshold"

    def segment(self, cube: np.ndarray) -> np.ndarray:
        top = cube.max(axis=0)
        return (top > 0.5 * top.max()).astype(np.int64)


def test_fused_bands_is_the_majority_of_bands_5_9_10(synth):
    from m2s2hil.analysis.evaluation.synthetic import _cube, fused_bands

    with synth.open() as st:
        _, bands, _ = band_images(st, st.frames()[0].event_id)
    seg = Threshold()
    maps = [seg.segment(_cube(bands[b - 1])) for b in (5, 9, 10)]
    expected = (np.sum(maps, axis=0) >= 2).astype(np.int64)
    assert np.array_equal(fused_bands(seg, bands) > 0, expected > 0)
    with pytest.raises(Exception, match="outside 1..10"):
        fused_bands(seg, bands, (0, 5))


def test_synthetic_columns_and_sim_to_real(tmp_path, synth):
    from shared_sessions import hil_with_labels

    from m2s2hil.analysis.evaluation.synthetic import evaluate_synthetic

    sid, _ = hil_with_labels(tmp_path / "root")
    out = tmp_path / "eval"
    with synth.open() as st, SessionStore.open(tmp_path / "root", sid) as hil:
        files = evaluate_synthetic(st, Threshold(), out, hil=hil)
    rows = files["synthetic_table2.csv"].read_text().splitlines()
    assert rows[0].startswith("satellite,build,classes,elevation,n,precision_rgb")
    assert [row.split(",")[:5] for row in rows[1:]] == [["hubble", "B2", "5", e, "2"] for e in ("E0", "E3")]
    for row in rows[1:]:
        vals = [float(x) for x in row.split(",")[5:] if x != "nan"]
        assert all(0.0 <= v <= 1.0 for v in vals) and len(vals) >= 6
    pairs = files["sim_to_real.csv"].read_text().splitlines()
    assert len(pairs) == 3 and {p.split(",")[1] for p in pairs[1:]} == {"0", "180"}
    assert all(p.split(",")[4] == "truth_labels" for p in pairs[1:])
    assert "| hubble | B2 | 5 | E3 | 2 |" in files["synthetic_table2.md"].read_text()


@pytest.mark.slow
def test_evaluate_command_gives_a_synthetic_session_its_columns(tmp_path, synth):
    r = run_cli("evaluate", synth.path, "--out", tmp_path, "--limit", "1")
    assert r.exit_code == 0, r.stderr
    assert "| hubble | B2 | 5 | E0 | 1 |" in r.stdout and (tmp_path / "synthetic_table2.csv").is_file()
