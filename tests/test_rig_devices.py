"""The device registry (m2s2hil/rig/devices/): one entry per kind the rig file accepts, agreeing
with the rig file's rules and with the fault kinds the simulators declare and handle."""

import inspect
import re
import tomllib
from importlib import resources
from pathlib import Path
from typing import get_args

import m2s2hil.simulators
import pytest
from m2s2hil.simulators.clock import VirtualClock
from m2s2hil.simulators.fault_injection import FAULT_KINDS_BY_DEVICE, FaultPlan

from m2s2hil.config import PROTOCOLS, DeviceProtocol, RigConfig, default_rig, parse_rig
from m2s2hil.rig.devices import CAMERA, KINDS, kind_of
from m2s2hil.rig.devices.kind import CameraKind, MotionKind, RelayKind, Setup, SimParts
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


def _rig_with(protocol: str) -> tuple[RigConfig, str]:
    """The built-in rig with its stage or its relay board of kind ``protocol``; that device's name."""
    doc = tomllib.loads(resources.files("m2s2hil").joinpath("data/default_rig.toml").read_text())
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
