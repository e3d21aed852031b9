"""What a registry entry holds: one device kind (a rig file's protocol, or the U3V camera).

An entry says everything the application needs about a kind beyond its codec, driver and
simulator: its role (from the rig file's rules, ``config.PROTOCOLS``), how its simulator and
driver are made from the rig file, what ``m2s2hil rig probe`` reads from it, how it is
recognised when it answers on another device's port and what its driver's errors mean while
it opens, and (read from the simulators, which declare them) its fault kinds. The rig
factory, the probe and :mod:`m2s2hil.rig.open_errors` ask the registry
(:mod:`m2s2hil.rig.devices`) and hold no per-protocol branches.
"""

from __future__ import annotations

import contextlib
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

from m2s2hil.config import PROTOCOLS, AxisConfig, DeviceConfig, RigConfig
from m2s2hil.drivers.clock import Clock
from m2s2hil.rig.open_errors import RigOpenError
from m2s2hil.simulators.fault_injection import FAULT_KINDS_BY_DEVICE

if TYPE_CHECKING:
    from m2s2hil.drivers.interfaces import LightBank, RotaryAxis
    from m2s2hil.drivers.u3v import U3VCamera
    from m2s2hil.rig.devices.findings import ProbeReport
    from m2s2hil.simulators.fault_injection import FaultPlan
    from m2s2hil.simulators.frames import SimFrameSource
    from m2s2hil.simulators.world import World

Role = Literal["motion", "relay", "camera"]

#: How far (machine units) a controller's stored origin may differ from the recorded one.
OFFSET_TOLERANCE_UNITS = 1e-3


@dataclass(frozen=True)
class Setup:
    """One device of a rig being opened, simulated or probed: its rig-file name (``camera``
    for the camera), the rig, the clock, and the rig's in-process simulators by name."""

    name: str
    config: RigConfig
    clock: Clock
    sims: Mapping[str, Any] = field(default_factory=dict)

    @property
    def device(self) -> DeviceConfig:
        return self.config.devices[self.name]

    @property
    def axes(self) -> dict[str, AxisConfig]:
        """The axes this device drives, by role."""
        return {role: ax for role, ax in self.config.axes.items() if ax.device == self.name}


@dataclass(frozen=True)
class SimParts:
    """What a simulator is built into: the shared world, this device's fault plan, and (for
    the camera) the frame source rendering that world."""

    world: World
    faults: FaultPlan
    frame_source: SimFrameSource | None = None


@dataclass(frozen=True)
class Signature:
    """How a kind is recognised on a port it was not expected on: ``probe`` is sent, and a
    reply matching ``reply`` means this kind answers. With ``own_probe_only`` the match counts
    only for the reply to its own probe (a bare prompt could answer anything)."""

    probe: bytes
    reply: re.Pattern[bytes]
    own_probe_only: bool = False


@dataclass(frozen=True, kw_only=True)
class DeviceKind:
    """One device kind: ``protocol`` is its rig-file name (``u3v`` for the camera), ``title``
    how messages name it (also what :func:`~m2s2hil.rig.open_errors.identify_port` returns)."""

    protocol: str
    title: str
    make_simulator: Callable[[Setup, SimParts], Any]
    #: ``rig probe``: read the device's identity and settings into the report (``apply``:
    #: write the rig file's settings first, where the kind can).
    probe: Callable[[Setup, ProbeReport, bool], None]
    signature: Signature | None = None
    #: What an error of this kind's driver means while it opens, before the generic reading of
    #: :func:`~m2s2hil.rig.open_errors.explain`: ``explain(exc, device, port)``, None to leave it.
    explain: Callable[[BaseException, str, str], RigOpenError | None] | None = None

    @property
    def role(self) -> Role:
        return PROTOCOLS[self.protocol].role

    @property
    def fault_kinds(self) -> Mapping[str, tuple[str, ...]]:
        """The faults its simulator handles and each one's parameters, as the simulators
        declare them (``simulators.fault_injection.FAULT_KINDS_BY_DEVICE``)."""
        return FAULT_KINDS_BY_DEVICE[self.protocol]


@dataclass(frozen=True)
class OriginReading:
    """An axis origin as its controller holds it: the axis as the controller names it (GRBL
    letter, Zaber number), what the controller says it is, and the offset in machine units."""

    axis: str
    controller: str
    offset_units: float


def _no_offset(axis: Any, offset_units: float) -> None:
    """An axis whose controller counts from the origin itself: nothing for the driver to add."""


@dataclass(frozen=True, kw_only=True)
class MotionKind(DeviceKind):
    """A motion controller serving one or more axes.

    The origin hooks serve axes without switches (:mod:`m2s2hil.rig.origin`): both take a
    connected controller, the axis's and its device's configuration, and raise
    :class:`~m2s2hil.rig.open_errors.RigOpenError` where the controller cannot be trusted.
    """

    #: Connect and make the axes of :attr:`Setup.axes`: ``(controller, axes by role)``.
    open_axes: Callable[[Setup], tuple[Any, dict[str, RotaryAxis]]]
    #: Home the axes that have switches (``homing = "switches"``), given by role.
    home: Callable[[Any, Mapping[str, Any]], None]
    #: The controller, not yet connected, on a connection of its own (``rig origin`` from the
    #: command line).
    controller: Callable[[Setup], Any]
    #: Make where the axis stands its zero on the controller, read back.
    set_origin: Callable[[Any, AxisConfig, DeviceConfig], OriginReading]
    #: The origin the controller holds now, when the rig opens: ``(controller, role, axis, device)``.
    stored_origin: Callable[[Any, str, AxisConfig, DeviceConfig], OriginReading]
    #: Make the axis driver count from an origin offset (machine units).
    use_origin: Callable[[Any, float], None] = _no_offset


@dataclass(frozen=True, kw_only=True)
class RelayKind(DeviceKind):
    """A relay board switching the lamps."""

    open_lights: Callable[[Setup], LightBank]


@dataclass(frozen=True, kw_only=True)
class CameraKind(DeviceKind):
    """The camera (the rig file's ``[camera]`` table)."""

    open_camera: Callable[[Setup], U3VCamera]

    @property
    def role(self) -> Role:
        return "camera"


def connect_or_close(driver: Any) -> None:
    """Connect, or close the port again before the error leaves: anyone looking at the port next
    (:func:`m2s2hil.rig.open_errors.identify_port`, a retry) finds it free."""
    try:
        driver.connect()
    except BaseException:
        driver.close()
        raise


def close_quietly(driver: Any) -> None:
    """Close a driver on the way out of a probe; a close that fails hides nothing the probe found."""
    with contextlib.suppress(Exception):
        driver.close()

