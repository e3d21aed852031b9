"""The catalog (Table 1 of the paper) and where the simulator's mockups put each filament."""

import numpy as np
import pytest
from m2s2hil.simulators.mockups import HUBBLE_BUILDS, assign_materials, mockup, part_materials
from m2s2hil.simulators.scene import Scene
from m2s2hil.simulators.world import LampInfo
from scipy import ndimage

from m2s2hil.catalog import load_catalog
from m2s2hil.config import DEFAULT_LAYOUT, CameraModel
from m2s2hil.errors import CatalogError

# Table 1 of the M2S2 paper, transcribed independently of catalog.toml's order.
TABLE1 = {
    ("voyager", "B1"): {"pro_silver"},
    ("voyager", "B2"): {"pro_silver", "dark_grey", "pro_gold", "cold_white"},
    ("voyager", "B3"): {
        "pro_silver", "dark_grey", "pro_metallic_blue", "pro_gold", "cold_white",
        "pro_metallic_magenta", "red", "azure_blue", "olive_brown", "lime_green",
    },
    ("iss", "B1"): {"pro_silver"},
    ("iss", "B2"): {"pro_silver", "dark_grey", "pro_metallic_blue", "pro_gold", "cold_white"},
    ("iss", "B3"): {
        "pro_silver", "dark_grey", "pro_metallic_blue", "pro_gold", "cold_white",
        "red", "azure_blue", "olive_brown", "lime_green", "wood",
    },
    ("hubble", "B1"): {"pro_silver"},
    ("hubble", "B2"): {"pro_silver", "dark_grey", "pro_metallic_blue", "pro_metallic_magenta"},
    ("hubble", "B3"): {"pro_silver", "dark_grey", "pro_metallic_blue", "pro_metallic_magenta"},
}


def test_builds_match_table1():
    cat = load_catalog()
    for (sat, build), mats in TABLE1.items():
        assert set(cat.build(sat, build).materials) == mats, (sat, build)
    assert len(cat.materials) == 11
    assert sum(len(s.builds) for s in cat.satellites.values()) == 9


def test_lighting_and_dataset_names():
    cat = load_catalog()
    assert {k: v.dataset for k, v in cat.lighting.items()} == {
        "weak": "solo", "strong": "all", "directional": "dir"
    }
    assert cat.light("solo").key == "weak"
    assert cat.light("Directional").key == "directional"
    assert sorted(cat.elevations) == ["E0", "E1", "E2"]


def test_lookup_is_case_insensitive_and_errors_are_clear():
    cat = load_catalog()
    assert cat.satellite("Hubble").key == "hubble"
    assert cat.build("hubble", "b2").key == "B2"
    with pytest.raises(CatalogError, match="unknown satellite 'hubbel'.*did you mean 'hubble'"):
        cat.satellite("hubbel")
    with pytest.raises(CatalogError, match="unknown build of Hubble 'B4'"):
        cat.build("hubble", "B4")


def test_class_names_start_with_background():
    assert load_catalog().class_names("hubble", "B2")[0] == "background"


# -- where the filaments sit (simulators/mockups.py) ------------------------------------------
N = 128
LAMPS = {i: LampInfo(f"bar{i + 1}", "led_bar", 1.0) for i in range(5)}
STRONG = dict.fromkeys(range(5), 1.0)
VIEWS = ((0.0, 15.0), (90.0, 15.0), (180.0, -15.0), (270.0, 0.0))


@pytest.fixture(scope="module")
def scene() -> Scene:
    cam = CameraModel()
    return Scene(N, N, cam.bands_nm, cam.fwhm_nm, DEFAULT_LAYOUT)


def test_every_build_shows_exactly_its_catalog_materials(scene):
    cat = load_catalog()
    for sat in cat.satellites.values():
        for build in sat.builds.values():
            mats = build.materials
            seen: set[int] = set()
            for az, tilt in VIEWS:
                shaded = scene.render(sat.key, mats, az, tilt, STRONG, LAMPS, build=build.key)
                seen |= set(np.unique(shaded.label).tolist())
            assert shaded.mount.class_names == ("background", *mats)
            assert seen == set(range(len(mats) + 1)), (sat.key, build.key, sorted(seen))


def test_hubble_part_maps_use_the_catalog_filaments():
    cat = load_catalog()
    m = mockup("hubble")
    assert set(m.builds) == set(cat.satellite("hubble").builds)
    for key, table in HUBBLE_BUILDS.items():
        assert set(table) == {p.name for p in m.parts}, key
        assert set(table.values()) == set(cat.build("hubble", key).materials), key
    # B2 is what the parts' preferences give; a custom material list falls back to them.
    b2 = cat.build("hubble", "B2").materials
    assert part_materials(m, b2, "B2") == assign_materials(m.parts, b2)
    assert set(part_materials(m, ["pro_silver", "wood"], "B3")) == {"pro_silver", "wood"}


def _regions(label: np.ndarray) -> int:
    """Connected regions of one material, summed over the materials (background left out)."""
    return sum(ndimage.label(label == k)[1] for k in range(1, int(label.max()) + 1))


def test_hubble_b3_places_its_filaments_differently_from_b2(scene):
    mats = load_catalog().build("hubble", "B3").materials
    assert set(mats) == set(load_catalog().build("hubble", "B2").materials)  # Table 1
    regions = {"B2": 0, "B3": 0}
    share = {"B2": np.zeros(len(mats) + 1), "B3": np.zeros(len(mats) + 1)}
    for az, tilt in VIEWS:
        labels = {b: scene.render("hubble", mats, az, tilt, STRONG, LAMPS, build=b).label.copy()
                  for b in ("B2", "B3")}
        fg = labels["B2"] > 0
        assert np.array_equal(fg, labels["B3"] > 0)  # the same print geometry
        assert (labels["B2"][fg] != labels["B3"][fg]).mean() > 0.3, (az, tilt)
        for b, lab in labels.items():
            regions[b] += _regions(lab)
            share[b] += np.bincount(lab.ravel(), minlength=len(mats) + 1)
    # "The most complex case": more separate material regions, and no filament dominating.
    assert regions["B3"] > 1.2 * regions["B2"], regions
    top = {b: v[1:].max() / v[1:].sum() for b, v in share.items()}
    assert top["B3"] < 0.4 < top["B2"], top
