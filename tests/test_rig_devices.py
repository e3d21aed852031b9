"""The device registry (m2s2hil/rig/devices/): one entry per kind the rig file accepts, agreeing
with the rig file's rules and with the fault kinds the simulators declare and handle."""

import inspect
import logging
import re
import tomllib
from importlib import resources
from pathlib import Path
from typing import get_args

import m2s2hil.simulators
import pytest
from m2s2hil.drivers.errors import MoveStalled
from m2s2hil.simulators.clock import VirtualClock
from m2s2hil.simulators.fault_injection import FAULT_KINDS_BY_DEVICE, FaultPlan

import m2s2hil.rig.devices
from m2s2hil.config import PROTOCOLS, DeviceProtocol, RigConfig, default_rig, parse_rig
from m2s2hil.errors import ConfigError
from m2s2hil.rig.devices import CAMERA, KINDS, kind_of
from m2s2hil.rig.devices.kind import CameraKind, MotionKind, RelayKind, Setup, SimParts
from m2s2hil.rig.factory import open_simulated_rig
from m2s2hil.sim_config import build_frame_source, build_world

_CLASS = {"motion": MotionKind, "relay": RelayKind, "camera": CameraKind}


def test_every_protocol_the_rig_file_accepts_has_an_entry():
    accepted = get_args(DeviceProtocol)
    assert tuple(PROTOCOLS) == accepted  # the rig file's rules name the same kinds
    assert set(KINDS) == {*accepted, "u3v"}
    assert CAMERA is KINDS["u3v"]
    for protocol, kind in KINDS.items():
        assert kind.protocol == protocol
        assert isinstance(kind, _CLASS[kind.role]), protocol
        if protocol in PROTOCOLS:
            assert kind.role == PROTOCOLS[protocol].role


def test_each_entrys_fault_kinds_are_its_simulators():
    assert set(FAULT_KINDS_BY_DEVICE) == set(KINDS)
    for protocol, kind in KINDS.items():
        assert kind.fault_kinds == FAULT_KINDS_BY_DEVICE[protocol]


def _asked_by(sim: object) -> set[str]:
    """The fault kinds the code of ``sim``'s classes asks its plan for (as test_fault_injection reads it)."""
    root = Path(m2s2hil.simulators.__file__).parent
    ours = [cls for cls in type(sim).__mro__ if cls.__module__.startswith("m2s2hil.simulators")]
    files = {Path(inspect.getfile(cls)) for cls in ours}
    files |= {p for f in list(files) for p in root.glob(f"{f.stem}_*.py")}  # a simulator split into modules
    asked: set[str] = set()
    for path in files:
        text = path.read_text()
        asked |= set(re.findall(r'faults\.(?:take|pending)\("([a-z_]+)"\)', text))
        for group in re.findall(r"faults\.pending\(k\) for k in \(([^)]*)\)", text):
            asked |= set(re.findall(r'"([a-z_]+)"', group))
    return asked


def _rig_with(protocol: str, **turntable: object) -> tuple[RigConfig, str]:
    """The built-in rig with its stage or its relay board of kind ``protocol``; that device's name.
    ``turntable``: keys of the turntable's axis section to set."""
    doc = tomllib.loads(resources.files("m2s2hil").joinpath("data/default_rig.toml").read_text())
    doc["axes"]["turntable"].update(turntable)
    if PROTOCOLS[protocol].role == "motion":
        doc["devices"]["stage"]["protocol"] = protocol
        if protocol == "zaber":
            doc["axes"]["turntable"]["axis"], doc["axes"]["tilt"]["axis"] = "1", "2"
        doc.get("simulation", {}).pop("devices", None)  # GRBL's simulator options
        return parse_rig(doc, "test"), "stage"
    doc["devices"]["relays"]["protocol"] = protocol
    return parse_rig(doc, "test"), "relays"


@pytest.mark.parametrize("protocol", sorted(KINDS))
def test_the_simulator_an_entry_makes_handles_exactly_its_fault_kinds(protocol):
    clock = VirtualClock()
    if protocol == "u3v":
        config = default_rig()
        world = build_world(config, clock)
        frames = build_frame_source(config, world)
        sim = CAMERA.make_simulator(Setup("camera", config, clock), SimParts(world, FaultPlan(), frames))
    else:
        config, name = _rig_with(protocol)
        world = build_world(config, clock)
        sim = kind_of(protocol).make_simulator(Setup(name, config, clock), SimParts(world, FaultPlan()))
    assert _asked_by(sim) == set(KINDS[protocol].fault_kinds)


# -- how long a move may take: the rig file's axis keys, through the registry to the driver ----
def _stall_time(protocol: str, **turntable: object) -> tuple[float, str]:
    """Open the simulated rig, freeze the turntable halfway (the simulator's ``hang`` fault) and
    move it: the virtual time until the move failed, and the error."""
    config, _ = _rig_with(protocol, **turntable)
    clock = VirtualClock()
    rig = open_simulated_rig(config, clock=clock, faults={"stage": [{"kind": "hang", "fraction": 0.5}]})
    try:
        t0 = clock.monotonic()
        with pytest.raises(MoveStalled) as exc:
            rig.turntable.move_to(100.0)
        return clock.monotonic() - t0, str(exc.value)
    finally:
        rig.close()


@pytest.mark.parametrize("protocol", ["grbl", "zaber"])
def test_a_rig_files_stall_window_decides_when_a_hung_axis_fails(protocol):
    default_s, default_text = _stall_time(protocol)
    patient_s, patient_text = _stall_time(protocol, stall_window_s=9.0)
    assert "no progress for 2 s" in default_text  # the drivers' own window when the file says nothing
    assert "no progress for 9 s" in patient_text
    # The same freeze at the same place: only the window differs (virtual clock).
    assert patient_s - default_s == pytest.approx(7.0, abs=0.5)


@pytest.mark.parametrize("protocol", ["grbl", "zaber"])
def test_a_rig_files_timeout_margin_decides_when_a_slow_move_is_overdue(protocol, caplog):
    slow = {"stage": [{"kind": "slow_motion", "factor": 5.0, "count": -1}]}
    overdue = {}
    for margin in (None, 20.0):
        config, _ = _rig_with(protocol, **({} if margin is None else {"timeout_margin": margin}))
        rig = open_simulated_rig(config, clock=VirtualClock(), faults=slow)
        caplog.clear()
        try:
            with caplog.at_level(logging.WARNING, logger="m2s2hil.drivers"):
                assert rig.turntable.move_to(200.0) == pytest.approx(200.0, abs=0.05)
        finally:
            rig.close()
        overdue[margin] = any("longer than planned" in r.getMessage() for r in caplog.records)
    # Five times slower: overdue past 1.5 x the plan (logged, not failed), not past 20 x.
    assert overdue == {None: True, 20.0: False}


@pytest.mark.parametrize(("key", "value"), [("stall_window_s", 0.1), ("stall_window_s", 601),
                                            ("timeout_margin", 0.5), ("timeout_margin", 21)])
def test_move_timing_keys_are_bounded(key, value):
    with pytest.raises(ConfigError, match=key):
        _rig_with("grbl", **{key: value})


@pytest.mark.parametrize("module", ["factory", "probe", "open_errors", "origin"])
def test_the_rig_code_that_asks_the_registry_names_no_protocol(module):
    """A device kind lives in its registry module: the code that asks the registry has no
    branch on a protocol's name (a new kind then needs no edit there)."""
    text = (Path(m2s2hil.rig.devices.__file__).parent.parent / f"{module}.py").read_text()
    named = set(re.findall(r'"([a-z0-9-]+)"', text)) & {*KINDS, *PROTOCOLS}
    assert not named, f"rig/{module}.py names {sorted(named)}"
