"""The simulated camera's frame source: World state → raw mosaic + ground truth."""

from __future__ import annotations

import types
from importlib import resources

import numpy as np
import pytest
from m2s2hil.simulators.frames import SimFrameSource
from m2s2hil.simulators.scene import SceneError
from m2s2hil.simulators.snapshot import colour_of, superpixel
from m2s2hil.simulators.world import LampInfo, World
from PIL import Image
from typer.testing import CliRunner

from m2s2hil.catalog import load_catalog
from m2s2hil.cli import app
from m2s2hil.config import CameraModel

N = 256
LAMPS = {i: LampInfo(f"bar{i + 1}", "led_bar", 1.0) for i in range(5)}
LAMPS[5] = LampInfo("spot", "spotlight", 2.0)
MODEL = CameraModel(width=N, height=N)


def catalog_materials(sat: str, build: str) -> tuple[str, ...]:
    return load_catalog().build(sat, build).materials


def make_world(vclock, az: float = 30.0, tilt: float = 0.0, lamps=(0, 1, 2, 3, 4)) -> World:
    world = World(vclock, lamp_info=LAMPS)
    pose = {"az": az, "tilt": tilt}
    world.attach_axis("turntable", lambda: pose["az"])
    world.attach_axis("tilt", lambda: pose["tilt"])
    world.pose_state = pose  # test handle to move the stage
    for ch in lamps:
        world.set_lamp(ch, True)
    vclock.advance(5.0)
    return world


@pytest.fixture
def world(vclock):
    return make_world(vclock)


@pytest.fixture
def source(world):
    return SimFrameSource(world, MODEL, catalog_materials, seed=1)


def test_capture_gives_a_raw_mosaic(source):
    frame = source.capture(0.005, 1.0)
    assert frame.shape == (N, N) and frame.dtype == np.uint16
    assert frame.max() <= MODEL.full_scale
    truth = source.truth()
    assert truth.class_names == ["background", *catalog_materials("voyager", "B3")]
    assert truth.labels.shape == (N, N)
    assert truth.azimuth_deg == 30.0 and truth.exposure_s == 0.005
    # A well-lit mockup uses a good part of the range at a few ms without saturating much.
    fg = truth.labels > 0
    assert np.percentile(frame[fg], 95) > 0.3 * MODEL.full_scale
    assert (frame[fg] >= MODEL.full_scale).mean() < 0.02


def test_radiance_cube_sampled_through_the_msfa_is_the_noise_free_mosaic(source):
    source.capture(0.004, 1.5)
    truth = source.truth()
    cube = truth.radiance()
    assert cube.shape == (10, N, N) and cube.dtype == np.float32
    assert truth.radiance() is cube  # computed once
    layout = np.asarray(MODEL.layout)
    n = layout.shape[0]
    band = np.tile(layout, (N // n, N // n))
    sampled = np.take_along_axis(cube, band[None], axis=0)[0]
    assert np.allclose(sampled, truth.signal(), rtol=1e-5, atol=1e-4)
    assert truth.signal().max() > 100


def test_truth_is_in_the_units_of_the_frame(source):
    """Averaged frames minus the expected dark level recover the noise-free signal."""
    frames = np.mean([source.capture(0.003, 1.0).astype(np.float64) for _ in range(24)], axis=0)
    truth = source.truth()
    dark = source.sensor.expected_dark_dn(0.003, 1.0, truth.temperature_c)
    signal = truth.signal()
    ok = (signal + dark) < 0.9 * MODEL.full_scale
    err = (frames - dark - signal)[ok]
    assert abs(err.mean()) < 0.1
    assert err.std() < 2.0  # a single frame's noise is ~5 DN at these levels


def test_lens_cap_gives_no_scene_signal(world, source):
    lit = source.capture(0.005).astype(np.float64)
    world.set_lens_cap(True)
    capped = source.capture(0.005).astype(np.float64)
    truth = source.truth()
    assert truth.lens_cap and not truth.labels.any() and not truth.radiance().any()
    dark = source.sensor.expected_dark_dn(0.005, 1.0, world.sensor_temperature_c)
    assert abs((capped - dark).mean()) < 0.1
    mockup = source.scene.render("voyager", catalog_materials("voyager", "B3"), 30.0, 0.0,
                                 world.lamp_output(), LAMPS).label > 0
    assert abs(capped[mockup].mean() - capped[~mockup].mean()) < 0.2
    assert lit[mockup].mean() > capped[mockup].mean() + 100


def test_white_panel_fills_the_view_falls_off_to_the_corners_and_follows_the_lamps(world, source):
    with pytest.raises(ValueError, match="unknown target"):
        world.set_target("grey_card")
    world.set_target("white_panel")
    dark = source.sensor.expected_dark_dn(0.004, 1.0, world.sensor_temperature_c)

    def signal() -> np.ndarray:
        return source.capture(0.004).astype(np.float64) - dark

    bright = signal()
    assert not source.truth().labels.any()  # no mockup in view
    assert bright.min() > 50 and bright.max() < 0.9 * MODEL.full_scale  # lit everywhere, unsaturated
    # 1 - 0.06 (x² + y²) over x, y in [-1, -0.75] (a 32-pixel corner of 256) against the centre
    assert bright[:32, :32].mean() / bright[112:144, 112:144].mean() == pytest.approx(0.909, abs=0.015)
    world.set_lamp(3, False)
    world.set_lamp(4, False)
    assert signal().mean() < 0.85 * bright.mean()  # the second frame reuses the panel's pattern
    world.set_target("mockup")
    source.capture(0.004)
    assert source.truth().labels.any()


def test_sensor_temperature_raises_the_dark_level(world, source):
    world.set_lens_cap(True)
    world.sensor_temperature_c = 25.0
    cool = source.capture(2.0).mean()
    world.sensor_temperature_c = 45.0
    warm = source.capture(2.0).mean()
    black = source.sensor.params.black_level_dn
    assert (warm - black) > 5 * (cool - black) > 0


def test_frames_follow_the_stage_the_lamps_and_the_mount(world, source, vclock):
    source.capture(0.005)
    a = source.truth()
    world.pose_state["az"] = 100.0
    source.capture(0.005)
    b = source.truth()
    assert (a.labels != b.labels).mean() > 0.05
    world.mount("hubble", "B2")
    source.capture(0.005)
    c = source.truth()
    assert c.satellite == "hubble" and c.class_names == ["background", *catalog_materials("hubble", "B2")]
    # Lamps just switched on are still warming up: dimmer than a moment later.
    for ch in (0, 1, 2, 3, 4):
        world.set_lamp(ch, False)
    world.set_lamp(5, True)
    warming = source.capture(0.005).astype(np.float64)
    assert source.truth().lamps == {5: 0.5}
    vclock.advance(3.0)
    warm = source.capture(0.005).astype(np.float64)
    fg = source.truth().labels > 0
    assert warm[fg].mean() > warming[fg].mean() + 20


def test_same_pose_reuses_the_render(source):
    source.capture(0.005)
    first = source.truth()
    source.capture(0.005)
    assert source.truth().labels is first.labels


def test_materials_of_build_as_a_mapping(vclock):
    world = make_world(vclock)
    world.mount("iss", "B2")
    nested = {"iss": {"B2": ["pro_silver", "cold_white"]}}
    src = SimFrameSource(world, MODEL, nested)
    src.capture(0.005)
    assert src.truth().class_names == ["background", "pro_silver", "cold_white"]
    flat = SimFrameSource(world, MODEL, {("iss", "B2"): ["pro_silver"]})
    flat.capture(0.005)
    assert set(np.unique(flat.truth().labels).tolist()) == {0, 1}
    world.mount("hubble", "B1")
    with pytest.raises(SceneError, match="no material list for satellite 'hubble' build 'B1'"):
        flat.capture(0.005)


def test_odd_layout_and_duck_typed_camera_model(vclock):
    world = make_world(vclock)
    layout = ((0, 1, 2), (3, 4, 5), (6, 7, 8))
    model = types.SimpleNamespace(width=240, height=240, bit_depth=12, layout=layout,
                                  bands_nm=(431, 479, 515, 567, 611, 666, 719, 775, 820),
                                  fwhm_nm=(65, 47, 42, 37, 36, 34, 33, 31, 31))
    src = SimFrameSource(world, model, catalog_materials)
    frame = src.capture(0.005)
    assert frame.shape == (240, 240) and frame.max() <= 4095
    truth = src.truth()
    cube = truth.radiance()
    assert cube.shape == (9, 240, 240)
    sampled = np.take_along_axis(cube, np.tile(np.asarray(layout), (80, 80))[None], axis=0)[0]
    assert np.allclose(sampled, truth.signal(), rtol=1e-5, atol=1e-4)
    assert superpixel(frame, layout).shape == (9, 80, 80)


def test_bad_capture_arguments(source):
    with pytest.raises(ValueError, match="exposure"):
        source.capture(-1.0)
    with pytest.raises(ValueError, match="gain"):
        source.capture(0.01, 0.0)
    with pytest.raises(SceneError, match="camera model lacks"):
        SimFrameSource(source.world, object(), catalog_materials)


def test_snapshot_command_writes_pictures(tmp_path):
    rig_text = resources.files("m2s2hil").joinpath("data/default_rig.toml").read_text()
    rig_text = rig_text.replace("width = 2048", f"width = {N}").replace("height = 2048", f"height = {N}")
    rig = tmp_path / "small_rig.toml"
    rig.write_text(rig_text)
    out = tmp_path / "snap"
    result = CliRunner().invoke(app, ["sim", "snapshot", "--sat", "iss", "--build", "B2", "--az", "40",
                                      "--tilt", "E0", "--light", "directional", "--out", str(out),
                                      "--rig", str(rig)])
    assert result.exit_code == 0, result.output
    rgb = Image.open(out / "iss_B2_E0_directional_az40_rgb.png")
    assert rgb.size == (N // 4, N // 4) and rgb.mode == "RGB"
    px = np.asarray(rgb)
    assert px.max() > 200 and np.median(px) < 40  # a lit mockup on a dark backdrop
    labels = np.asarray(Image.open(out / "iss_B2_E0_directional_az40_labels.png").convert("RGB"))
    assert labels.shape[1] > N // 4  # the map plus a legend strip
    used = {tuple(c) for c in labels[: N // 4, : N // 4].reshape(-1, 3).tolist()}
    assert used == {colour_of(m) for m in ["background", *catalog_materials("iss", "B2")]}
    bad = CliRunner().invoke(app, ["sim", "snapshot", "--sat", "mir", "--out", str(out), "--rig", str(rig)])
    assert bad.exit_code != 0


def test_irradiance_is_the_light_on_each_surface_and_the_spotlight_casts_shadows(vclock):
    """``FrameTruth.irradiance``: the renderer's diffuse factor. Under the spotlight at 80° a
    share of the mockup gets the room bounce alone (``spot_ambient`` of the lamp's output); under
    the five shadowless bars no pixel is that dark; with the cap on there is no light."""
    from m2s2hil.simulators.shading import LightingParams

    spot_world = make_world(vclock, lamps=(5,))
    spot_world.spot_angle_deg = 80.0
    spot = SimFrameSource(spot_world, MODEL, catalog_materials, seed=1)
    spot.capture(0.005)
    truth = spot.truth()
    light = truth.irradiance()
    assert light.shape == (N, N) and light.dtype == np.float32
    obj = light[truth.labels > 0]
    ambient = LightingParams().spot_ambient * truth.lamps[5]
    in_shadow = np.isclose(obj, ambient, rtol=1e-4)
    assert 0.02 < in_shadow.mean() < 0.9  # some faces behind the mockup's own parts
    assert np.median(obj) > 20 * ambient  # a lit face gets tens of times the bounce
    bars = SimFrameSource(make_world(vclock), MODEL, catalog_materials, seed=1)
    bars.capture(0.005)
    lit = bars.truth().irradiance()[bars.truth().labels > 0]
    assert lit.min() > 0.1 * np.median(lit)
    spot_world.set_lens_cap(True)
    spot.capture(0.005)
    assert not spot.truth().irradiance().any()
