"""The opened rig: the devices the engine drives, what each can do, and the way back to a safe state.

What a device can do beyond its basic interface (:mod:`m2s2hil.drivers.interfaces`: reconnect,
clear an alarm, home, rotate continuously) is checked once, when the rig opens
(:func:`m2s2hil.rig.factory.open_rig`), and recorded here: one :class:`DeviceLink` per
connection to the hardware (a motion controller serving one or more axes, a relay board, the
camera) and ``rotation`` for the turntable. Nothing asks a device for a capability later.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Literal, TypeGuard

from m2s2hil.config import RigConfig
from m2s2hil.drivers.clock import Clock
from m2s2hil.drivers.interfaces import (
    AlarmClearing,
    Camera,
    Connecting,
    ContinuousRotation,
    Homing,
    LightBank,
    Reconnecting,
    RotaryAxis,
)

if TYPE_CHECKING:
    from m2s2hil.processing.calibration import CameraCalibration
    from m2s2hil.simulators.frames import SimFrameSource
    from m2s2hil.simulators.world import World

log = logging.getLogger(__name__)

AxisRole = Literal["turntable", "tilt"]
Role = Literal["turntable", "tilt", "lights", "camera"]
AXIS_ROLES: tuple[AxisRole, AxisRole] = ("turntable", "tilt")


def is_axis(role: Role) -> TypeGuard[AxisRole]:
    return role in AXIS_ROLES


@dataclass(frozen=True)
class DeviceLink:
    """One connection to the hardware and what it can do, as checked when the rig opened.

    ``device`` is the name errors carry (the rig file's device name); ``names`` every other
    name that means this link (its roles, the drivers' own names).
    """

    device: str
    roles: tuple[Role, ...]
    names: frozenset[str]
    #: The driver that reopens the link: with ``reconnect()``, or else ``connect()``.
    reconnect: Reconnecting | Connecting | None = None
    alarm: AlarmClearing | None = None
    homing: Homing | None = None

    @property
    def axis_roles(self) -> tuple[AxisRole, ...]:
        """The axes this link drives (a stage controller may drive both)."""
        return tuple(r for r in self.roles if is_axis(r))

    def means(self, device: str | None) -> bool:
        return device is not None and (device == self.device or device in self.names)

    def do_reconnect(self) -> object:
        """Reopen the link (``reconnect()`` where the driver has it, else ``connect()``; None
        for a link that cannot be reopened). The type was checked when the rig opened."""
        if isinstance(self.reconnect, Reconnecting):
            return self.reconnect.reconnect()
        if self.reconnect is not None:
            return self.reconnect.connect()
        return None


def link_for(device: str, roles: tuple[Role, ...], owner: object, *names: str) -> DeviceLink:
    """Record what ``owner`` (the object holding the connection) can do: checked here, once."""
    reconnect = owner if isinstance(owner, (Reconnecting, Connecting)) else None
    return DeviceLink(
        device=device, roles=roles, names=frozenset({*roles, *names}), reconnect=reconnect,
        alarm=owner if isinstance(owner, AlarmClearing) else None,
        homing=owner if isinstance(owner, Homing) else None,
    )


@dataclass
class Rig:
    config: RigConfig
    clock: Clock
    turntable: RotaryAxis
    tilt: RotaryAxis
    lights: LightBank
    camera: Camera
    #: One per connection, with its capabilities (see the module docstring).
    links: tuple[DeviceLink, ...] = ()
    #: The turntable's continuous rotation, when its driver has it (continuous capture needs it).
    rotation: ContinuousRotation | None = None
    world: World | None = None  # the simulated world when any device is simulated here, else None
    simulated: bool = False
    #: The in-process simulators by device name (``"toucan"`` or the camera's sim name for the camera).
    sims: Mapping[str, object] = field(default_factory=lambda: MappingProxyType({}))
    #: The simulated camera's frame source (its ground truth), when the camera is simulated here.
    frame_source: SimFrameSource | None = None
    #: The camera's calibration when the rig file names one: the real mosaic layout,
    #: crosstalk matrix, white reference.
    calibration: CameraCalibration | None = None
    #: Called to cap/uncap a simulated camera's lens instead of its world's (tests). A real
    #: camera's cap is the operator's: a capture run parks and waits for them
    #: (``lens_needs_operator``; :mod:`m2s2hil.engine.darks`).
    lens_cap_hook: Callable[[bool], None] | None = None

    @property
    def lens_needs_operator(self) -> bool:
        """True when the camera is not simulated in this process (no frame source here, as
        :func:`~m2s2hil.rig.factory.open_rig` leaves it for a real camera): nothing here can
        put its lens cap on or check that it is on."""
        return self.frame_source is None

    def axis(self, role: AxisRole) -> RotaryAxis:
        return self.turntable if role == "turntable" else self.tilt

    def cap_lens(self, on: bool) -> None:
        if self.lens_cap_hook is not None:
            self.lens_cap_hook(on)
        elif self.world is not None:
            self.world.set_lens_cap(on)

    def show_white_panel(self, on: bool) -> None:
        """Hold the white calibration panel in view, or take it away. A simulated rig shows its
        own panel target (:mod:`m2s2hil.simulators.targets`); on a real rig the operator does."""
        if self.world is not None:
            self.world.set_target("white_panel" if on else "mockup")

    def mount(self, satellite: str, build: str) -> None:
        """Tell the simulated world which mockup is on the turntable (a no-op on the bench)."""
        if self.world is not None:
            self.world.mount(satellite, build)

    def safe(self) -> list[Exception]:
        """Lamps off and motion stopped; every step is tried even if another fails.

        Returns the errors met on the way (empty when the rig is safe) so a caller in
        teardown can record them without losing the original exception.
        """
        errors: list[Exception] = []
        steps: tuple[Callable[[], object], ...] = (lambda: self.lights.set(()), self.turntable.stop,
                                                   self.tilt.stop)
        for step in steps:
            try:
                step()
            except Exception as exc:  # teardown must try every step
                log.error("safe state step failed: %s", exc)
                errors.append(exc)
        return errors

    def close(self) -> None:
        devices: tuple[Camera | LightBank | RotaryAxis, ...] = (self.camera, self.lights, self.turntable,
                                                                self.tilt)
        for dev in devices:
            try:
                dev.close()
            except Exception as exc:
                log.warning("closing %s failed: %s", dev.name, exc)
