import pytest

from m2s2hil.catalog import load_catalog
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
