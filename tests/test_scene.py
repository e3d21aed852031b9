"""The satellite scene: materials, mockups, projection, lamps."""

from __future__ import annotations

import numpy as np
import pytest
from m2s2hil.simulators.materials import (
    MATERIAL_KEYS,
    UnknownMaterialError,
    band_average,
    reflectance,
    specular_colour,
)
from m2s2hil.simulators.mockups import assign_materials, mockup
from m2s2hil.simulators.scene import Scene, SceneError
from m2s2hil.simulators.world import LampInfo

from m2s2hil.catalog import load_catalog
from m2s2hil.config import DEFAULT_LAYOUT

BANDS = (431, 479, 515, 567, 611, 666, 719, 775, 820, 877)
FWHM = (65, 47, 42, 37, 36, 34, 33, 31, 31, 31)
N = 256
LAMPS = {i: LampInfo(f"bar{i + 1}", "led_bar", 1.0) for i in range(5)}
LAMPS[5] = LampInfo("spot", "spotlight", 2.0)
WEAK = {0: 1.0, 1: 1.0, 2: 1.0}
STRONG = {0: 1.0, 1: 1.0, 2: 1.0, 3: 1.0, 4: 1.0}
SPOT = {5: 1.0}


def mats(sat: str, build: str) -> tuple[str, ...]:
    return load_catalog().build(sat, build).materials


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene(N, N, BANDS, FWHM, DEFAULT_LAYOUT)


# -- materials -------------------------------------------------------------------------
def r(key: str) -> dict[int, float]:
    return dict(zip(BANDS, reflectance(key, BANDS, FWHM), strict=True))


def test_every_catalog_material_has_a_reflectance_model():
    cat = load_catalog()
    assert set(cat.materials) == set(MATERIAL_KEYS)
    for key in MATERIAL_KEYS:
        rho = reflectance(key, BANDS, FWHM)
        assert rho.shape == (10,) and np.all((rho > 0) & (rho < 1))
    with pytest.raises(UnknownMaterialError, match="no reflectance model for material 'gold'"):
        reflectance("gold", BANDS, FWHM)


def test_reflectances_follow_their_hue():
    red, azure, lime = r("red"), r("azure_blue"), r("lime_green")
    gold, mag = r("pro_gold"), r("pro_metallic_magenta")
    assert red[479] < 0.1 < 0.5 < red[666]
    assert max(azure[431], azure[479], azure[515], azure[567], azure[611], azure[666]) == azure[479]
    assert max(lime[431], lime[479], lime[515], lime[567], lime[611], lime[666]) == lime[567]
    assert gold[479] < gold[515] < gold[567] < gold[611]
    assert mag[431] > mag[515] < mag[666] and mag[567] < 0.5 * mag[666]
    olive = r("olive_brown")
    assert olive[479] < 0.1 and olive[479] < olive[611] < olive[719]
    for flat, lo, hi in (("cold_white", 0.8, 0.95), ("dark_grey", 0.03, 0.12), ("pro_silver", 0.4, 0.7)):
        v = reflectance(flat, BANDS, FWHM)
        assert lo < v.min() and v.max() < hi and np.ptp(v) < 0.12
    # PLA's near-infrared plateau: dyed filaments turn bright beyond ~750 nm.
    for dyed in ("red", "azure_blue", "lime_green", "pro_metallic_blue"):
        v = r(dyed)
        assert (v[820] > 0.4 and v[820] > v[611]) or v[820] > 0.7


def test_band_average_integrates_over_the_band():
    from m2s2hil.simulators.materials import GRID_NM

    flat = np.full(GRID_NM.shape, 0.37)
    assert np.allclose(band_average(flat, BANDS, FWHM), 0.37)
    ramp = GRID_NM / 1000.0  # a linear spectrum averages to its value at the band centre
    assert np.allclose(band_average(ramp, BANDS, FWHM), np.asarray(BANDS) / 1000.0, atol=1e-6)
    # A step is smoothed more by a wide band than by a narrow one.
    step = (GRID_NM > 500).astype(float)
    wide, narrow = band_average(step, [480], [65]), band_average(step, [480], [10])
    assert narrow < wide < 0.5


def test_metallic_filaments_are_specular():
    cat = load_catalog()
    for key, m in cat.materials.items():
        peak = specular_colour(key, BANDS, FWHM).max()
        assert (peak > 0.3) if m.metallic else (peak < 0.1), key


# -- mockups and materials per part -------------------------------------------------------
def test_every_build_material_lands_on_a_part():
    cat = load_catalog()
    for sat in cat.satellites.values():
        parts = mockup(sat.key).parts
        for build in sat.builds.values():
            chosen = assign_materials(parts, build.materials)
            assert set(chosen) | {"pro_silver"} == set(build.materials), (sat.key, build.key)
    assert set(assign_materials(mockup("iss").parts, ["pro_silver"])) == {"pro_silver"}
    # A build without Pro Silver still covers all its materials.
    chosen = assign_materials(mockup("hubble").parts, ["red", "wood"])
    assert set(chosen) == {"red", "wood"}


@pytest.mark.parametrize("sat", ["voyager", "iss", "hubble"])
def test_label_maps_hold_exactly_the_builds_materials(scene, sat):
    m = mats(sat, "B3")
    seen: set[int] = set()
    for az in (0, 90, 180, 270):
        shaded = scene.render(sat, m, az, 15.0, STRONG, LAMPS)
        assert shaded.label.shape == (N, N) and shaded.label.dtype == np.uint8
        seen |= set(np.unique(shaded.label).tolist())
        assert shaded.mount.class_names == ("background", *m)
    assert seen == set(range(len(m) + 1))


def test_b1_is_all_silver(scene):
    for sat in ("voyager", "iss", "hubble"):
        shaded = scene.render(sat, mats(sat, "B1"), 30.0, 0.0, STRONG, LAMPS)
        assert shaded.mount.class_names == ("background", "pro_silver")
        assert set(np.unique(shaded.label).tolist()) == {0, 1}
        assert set(shaded.mount.part_materials.values()) == {"pro_silver"}


def test_the_stand_is_silver_and_reaches_the_bottom_of_the_frame(scene):
    shaded = scene.render("hubble", mats("hubble", "B3"), 0.0, 0.0, STRONG, LAMPS)
    bottom = shaded.label[-3:]
    assert set(np.unique(bottom).tolist()) == {0, 1}  # background and the silver pole
    assert (bottom == 1).sum() > 0


def test_rotation_and_tilt_change_the_image(scene):
    m = mats("voyager", "B3")
    a = scene.render("voyager", m, 0.0, 0.0, STRONG, LAMPS).label.copy()
    b = scene.render("voyager", m, 40.0, 0.0, STRONG, LAMPS).label.copy()
    c = scene.render("voyager", m, 40.0, 15.0, STRONG, LAMPS).label.copy()
    d = scene.render("voyager", m, 360.0, 0.0, STRONG, LAMPS).label.copy()
    assert (a != b).mean() > 0.05
    assert (b != c).mean() > 0.02
    assert (a != d).mean() < 0.001  # a full turn is the same view


def test_mockup_is_framed(scene):
    for sat in ("voyager", "iss", "hubble"):
        for az in (0.0, 45.0, 90.0):
            lab = scene.render(sat, mats(sat, "B2"), az, 15.0, STRONG, LAMPS).label
            fg = lab[: N * 3 // 4] > 0  # above the stand's pole
            assert 0.02 < fg.mean() < 0.6  # ISS edge-on at 90° is slim
            assert not lab[0].any() and not lab[:, 0].any() and not lab[:, -1].any()  # nothing cut off


def test_weak_is_darker_than_strong(scene):
    m = mats("iss", "B3")
    weak = scene.render("iss", m, 20.0, 0.0, WEAK, LAMPS)
    fg = weak.label > 0
    weak_mean = float(weak.rate[fg].mean())
    strong = scene.render("iss", m, 20.0, 0.0, STRONG, LAMPS)
    assert weak_mean < 0.85 * float(strong.rate[fg].mean())
    half = scene.render("iss", m, 20.0, 0.0, {k: 0.5 for k in STRONG}, LAMPS)  # warming up
    assert float(half.rate[fg].mean()) < float(strong.rate[fg].mean())


def test_spotlight_lights_the_side_it_comes_from(scene):
    m = mats("hubble", "B1")
    right = scene.render("hubble", m, 0.0, 0.0, SPOT, LAMPS, spot_angle_deg=60.0)
    tube = right.label[N // 3 : N // 2, N // 2 - 20 : N // 2 + 20]
    assert (tube == 1).all()
    d_right = right.diffuse[N // 3 : N // 2].copy()
    left = scene.render("hubble", m, 0.0, 0.0, SPOT, LAMPS, spot_angle_deg=-60.0)
    d_left = left.diffuse[N // 3 : N // 2]
    c = N // 2
    assert d_right[:, c + 5 : c + 15].mean() > 1.5 * d_right[:, c - 15 : c - 5].mean()
    assert d_left[:, c - 15 : c - 5].mean() > 1.5 * d_left[:, c + 5 : c + 15].mean()


def test_spotlight_casts_shadows(scene):
    m = mats("iss", "B1")
    lit = scene.render("iss", m, 0.0, 0.0, SPOT, LAMPS, spot_angle_deg=45.0)
    fg = lit.label > 0
    # Surfaces turned towards the spotlight but receiving only the ambient term are in shadow.
    ambient = 0.02
    assert ((lit.diffuse <= ambient + 1e-6) & fg).sum() > 50
    bars = scene.render("iss", m, 0.0, 0.0, STRONG, LAMPS)
    assert ((bars.diffuse <= 0.2 + 1e-6) & fg).sum() < ((lit.diffuse <= ambient + 1e-6) & fg).sum()


def test_no_lamps_gives_no_light_on_the_mockup(scene):
    dark = scene.render("voyager", mats("voyager", "B2"), 0.0, 0.0, {}, LAMPS)
    assert float(np.abs(dark.rate).max()) == 0.0
    assert (dark.label > 0).any()


def test_same_pose_and_lamps_are_cached(scene):
    m = mats("voyager", "B2")
    first = scene.render("voyager", m, 12.0, 0.0, WEAK, LAMPS)
    assert scene.render("voyager", m, 12.0, 0.0, WEAK, LAMPS) is first
    assert scene.render("voyager", m, 12.0, 0.0, STRONG, LAMPS) is not first


def test_bad_scene_inputs_are_rejected(scene):
    with pytest.raises(SceneError, match="no mockup model for satellite 'mir'"):
        scene.render("mir", ["pro_silver"], 0, 0, WEAK, LAMPS)
    with pytest.raises(SceneError, match="no reflectance model for material 'chrome'"):
        scene.render("iss", ["pro_silver", "chrome"], 0, 0, WEAK, LAMPS)
    with pytest.raises(SceneError, match="no materials"):
        scene.render("iss", [], 0, 0, WEAK, LAMPS)
    with pytest.raises(SceneError, match="pose must be finite"):
        scene.render("iss", ["pro_silver"], float("nan"), 0, WEAK, LAMPS)
    with pytest.raises(SceneError, match="square"):
        Scene(N, N, BANDS, FWHM, [[0, 1, 2]])
