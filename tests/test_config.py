import tomllib
from importlib import resources

import pytest

from m2s2hil.config import DEMOSAIC_METHODS, check_demosaic_method, load_rig, parse_rig
from m2s2hil.errors import ConfigError, UsageError
from m2s2hil.sim_config import is_simulated, sim_name


def _default() -> dict:
    return tomllib.loads(resources.files("m2s2hil").joinpath("data/default_rig.toml").read_text())


def test_default_rig_is_fully_simulated():
    rig = load_rig()
    assert all(is_simulated(d.port) for d in rig.devices.values())
    assert is_simulated(rig.camera.port)
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


# -- the [simulation] section --------------------------------------------------------------------


def _with_simulation(**simulation) -> dict:
    d = _default()
    d["simulation"] = {**d.get("simulation", {}), **simulation}
    return d


@pytest.mark.parametrize(
    ("simulation", "key", "problem"),
    [
        ({"spot_angle_deg": "wide"}, "simulation.spot_angle_deg", "valid number"),
        ({"sensor_temprature_c": 40.0}, "simulation.sensor_temprature_c", "unknown key"),
        ({"sensor_temperature_c": 400.0}, "simulation.sensor_temperature_c", "less than or equal to 100"),
        ({"sensor": {"read_nois": 3.0}}, "simulation.sensor.read_nois", "unknown key"),
        ({"sensor": {"read_noise_e": -1.0}}, "simulation.sensor.read_noise_e", "greater than or equal to 0"),
        ({"sensor": {"qe": [0.5, 0.5]}}, "simulation.sensor", "qe and qe_nm go together"),
        ({"faults": {"stage": [{"kind": "bogus_fault"}]}}, "simulation.faults.stage.0.kind",
         "unknown fault kind 'bogus_fault'"),
        ({"faults": {"stage": [{"kind": "vanish", "duration": 2.0}]}}, "simulation.faults.stage.0.duration",
         "unknown key"),
        ({"faults": {"stage": [{"kind": "drop_reply", "rate": 2.0}]}}, "simulation.faults.stage.0.rate",
         "less than or equal to 1"),
        ({"faults": {"stage": [{"kind": "drop_reply", "delay_s": 1.0}]}}, "simulation.faults.stage.0.delay_s",
         "does not take 'delay_s'"),
        ({"faults": {"stage": [{"kind": "alarm", "flag": "FS"}]}}, "simulation.faults.stage.0.flag",
         "does not take 'flag'"),
        ({"faults": {"stage": [{"kind": "alarm", "code": 99}]}}, "simulation.faults.stage.0.code",
         "not a GRBL 1.1 alarm code"),
        ({"faults": {"relays": [{"kind": "stall"}]}}, "simulation.faults.relays.0.kind",
         "has no fault 'stall'"),
        ({"faults": {"toucan": [{"kind": "garble"}]}}, "simulation.faults.toucan.0.kind",
         "has no fault 'garble'"),
        ({"faults": {"camera9": [{"kind": "drop_reply"}]}}, "simulation.faults.camera9", "no device named"),
        ({"devices": {"relays": {"homing_switches": True}}}, "simulation.devices.relays",
         "only GRBL simulators take options"),
        ({"devices": {"nope": {}}}, "simulation.devices.nope", "no device named 'nope'"),
        ({"devices": {"stage": {"settings": {"$x": 1}}}}, "simulation.devices.stage.settings.$x", "pattern"),
    ],
)
def test_bad_simulation_section_names_key_and_problem(simulation, key, problem):
    with pytest.raises(ConfigError) as info:
        parse_rig(_with_simulation(**simulation), "rig.toml")
    assert info.value.key.startswith(key), info.value
    assert problem in info.value.problem
    assert str(info.value).startswith(f"rig.toml: {key}")
    assert info.value.exit_code == 2


def test_good_simulation_section_is_typed():
    rig = parse_rig(_with_simulation(
        spot_angle_deg=30, sensor_temperature_c=40.0, sensor={"read_noise_e": 9},
        faults={"stage": [{"kind": "alarm", "after": 3, "code": 1}, {"kind": "garble", "rate": 0.01}],
                "toucan": [{"kind": "frame_timeout", "rate": 0.5, "count": 2}]},
    ), "rig.toml")
    sim = rig.simulation
    assert sim.spot_angle_deg == 30.0 and sim.sensor.params().read_noise_e == 9.0
    assert sim.faults["stage"][0].params() == {"code": 1}
    assert sim.faults["toucan"][0].rate == 0.5


def test_sensor_settings_cover_every_sensor_parameter():
    from dataclasses import fields

    from m2s2hil.simulators.sensor import SensorParams

    from m2s2hil.sim_config import SensorSettings

    assert set(SensorSettings.model_fields) == {f.name for f in fields(SensorParams)}
    assert SensorSettings().params() == SensorParams()


def test_digest_ignores_written_out_simulation_defaults_but_not_changes():
    rig = load_rig()
    again = parse_rig(rig.model_dump(mode="json"), "dumped")
    assert again.digest == rig.digest
    other = parse_rig(_with_simulation(spot_angle_deg=30.0), "rig.toml")
    assert other.digest != rig.digest


def test_world_and_fault_plans_come_from_the_configuration():
    from m2s2hil.simulators.clock import VirtualClock

    from m2s2hil.sim_config import build_world, fault_plans

    rig = parse_rig(_with_simulation(
        spot_angle_deg=20.0, faults={"relays": [{"kind": "relay_stuck", "channel": 3}]},
    ), "rig.toml")
    world = build_world(rig, VirtualClock())
    assert world.spot_angle_deg == 20.0
    assert {ch: info.name for ch, info in world.lamp_info.items()} == {
        lamp.channel: name for name, lamp in rig.lamps.items()}
    plans = fault_plans(rig, {"toucan": [{"kind": "unplug", "duration_s": 2.0}]})
    assert set(plans) == {*rig.devices, "toucan"}
    assert plans["relays"].take("relay_stuck") == {"channel": 3}
    assert plans["toucan"].take("unplug") == {"duration_s": 2.0}
    assert plans["stage"].take("drop_reply") is None


def test_faults_passed_by_a_caller_are_checked_like_the_file():
    from m2s2hil.sim_config import fault_plans

    with pytest.raises(ConfigError) as info:
        fault_plans(load_rig(), {"stage": [{"kind": "unplug"}]})
    assert info.value.source == "faults" and info.value.key == "faults.stage.0.kind"
    with pytest.raises(ConfigError, match=r"faults: stage\.0\.kind: unknown fault kind"):
        fault_plans(load_rig(), {"stage": [{"kind": "nope"}]})


@pytest.mark.parametrize(("port", "simulated", "name"), [
    ("sim://stage", True, "stage"),
    ("sim:///stage", True, "stage"),  # read as the sim:// serial handler reads it
    ("/dev/ttyUSB0", False, None),
    ("usb://", False, None),
    ("/dev/serial/by-id/usb-sim://x", False, None),  # only a port that starts with the scheme
])
def test_one_predicate_says_a_port_is_simulated(port, simulated, name):
    assert is_simulated(port) is simulated
    assert sim_name(port) == name


def test_the_method_names_are_the_demosaicers_registry():
    """The rig file knows the methods without importing processing; the two lists agree."""
    from m2s2hil.processing.demosaic import METHODS, _registry

    assert tuple(_registry()) == DEMOSAIC_METHODS == METHODS
    assert all(cls.name == name for name, cls in _registry().items())


def test_one_method_check_with_the_callers_error():
    assert check_demosaic_method("wb") == "wb"
    with pytest.raises(UsageError, match=r"unknown demosaicing method 'magic'; known: superpixel, "):
        check_demosaic_method("magic")
    with pytest.raises(ValueError, match="--x: unknown demosaicing method"):
        check_demosaic_method("magic", lambda problem: ValueError(f"--x: {problem}"))
