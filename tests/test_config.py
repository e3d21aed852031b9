import tomllib
from importlib import resources

import pytest

from m2s2hil.config import load_rig, parse_rig
from m2s2hil.errors import ConfigError


def _default() -> dict:
    return tomllib.loads(resources.files("m2s2hil").joinpath("data/default_rig.toml").read_text())


def test_default_rig_is_fully_simulated():
    rig = load_rig()
    assert all(d.port.startswith("sim://") for d in rig.devices.values())
    assert rig.camera.port.startswith("sim://")
    assert rig.lamp_channels("weak") == (0, 1, 2)
    assert len(rig.lamp_channels("strong")) == 5
    assert len(rig.digest) == 64


@pytest.mark.parametrize(
    ("mutate", "key", "problem"),
    [
        (lambda d: d["lighting"].__setitem__("weak", ["bar9"]), "lighting.weak", "no lamp named 'bar9'"),
        (lambda d: d["axes"]["tilt"].__setitem__("max_speed_dps", -1), "axes.tilt.max_speed_dps",
         "greater than 0"),
        (lambda d: d["axes"]["turntable"].__setitem__("device", "nope"), "axes.turntable.device",
         "no device named 'nope'"),
        (lambda d: d["lamps"]["bar2"].__setitem__("channel", 0), "lamps.bar2.channel",
         "already used"),
        (lambda d: d["elevations"].__setitem__("E0", 80.0), "elevations.E0", "outside the tilt"),
        (lambda d: d["devices"]["stage"].__setitem__("bogus", 1), "devices.stage.bogus",
         "unknown key"),
        (lambda d: d["camera"]["model"].__setitem__("layout", [[0, 1], [2, 3]]), "camera.model",
         "no position for bands"),
        (lambda d: d["lighting"].pop("directional"), "lighting", "missing preset"),
        (lambda d: d.setdefault("processing", {}).__setitem__("method", "magic"), "processing.method",
         "unknown demosaicing method 'magic'"),
    ],
)
def test_bad_rig_names_key_and_problem(mutate, key, problem):
    d = _default()
    mutate(d)
    with pytest.raises(ConfigError) as info:
        parse_rig(d, "rig.toml")
    assert info.value.key == key
    assert problem in info.value.problem
    assert str(info.value).startswith(f"rig.toml: {key}")
    assert info.value.exit_code == 2


def test_bad_files(tmp_path):
    with pytest.raises(ConfigError, match="no such file"):
        load_rig(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[devices\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_rig(bad)
