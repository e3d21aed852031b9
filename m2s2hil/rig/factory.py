"""Open a rig from its configuration.

Every device gets the driver of its kind (its entry in m2s2hil/rig/devices/); every device
whose port is ``sim://NAME`` also gets its kind's in-process simulator, registered under NAME,
all sharing one simulated world. A rig whose devices are all simulated runs on a virtual
clock unless ``realtime`` is asked for; a rig with any real device runs in real time.

Axes follow their homing policy (``homing`` in the rig file): only axes with switches are
homed; an axis without switches must stand in its recorded origin (m2s2hil/rig/origin.py).
A device that cannot be opened raises :class:`~m2s2hil.rig.open_errors.RigOpenError`: one
line naming the device, the port and the cause, with a hint and an exit code.
"""

from __future__ import annotations

import contextlib
import logging
from types import MappingProxyType
from typing import Any

from m2s2hil.config import AxisConfig, RigConfig, default_rig
from m2s2hil.drivers.clock import SYSTEM_CLOCK, Clock
from m2s2hil.drivers.interfaces import ContinuousRotation
from m2s2hil.errors import ConfigError
from m2s2hil.rig.devices import CAMERA, kind_of, motion_kind, relay_kind
from m2s2hil.rig.devices.kind import MotionKind, Setup, SimParts
from m2s2hil.rig.open_errors import opening
from m2s2hil.rig.opened import AXIS_ROLES, DeviceLink, Rig, link_for
from m2s2hil.rig.origin import establish_origins
from m2s2hil.sim_config import is_simulated, sim_name

log = logging.getLogger(__name__)


def _axes_of(config: RigConfig, device: str) -> dict[str, AxisConfig]:
    return {role: ax for role, ax in config.axes.items() if ax.device == device}


def build_simulators(
    config: RigConfig, clock: Any, *, faults: dict[str, list[dict]] | None = None, seed: int = 0,
    only_sim_ports: bool = True,
) -> tuple[Any, dict[str, Any], Any]:
    """Create the simulated world and a simulator per device (its kind's, m2s2hil/rig/devices/).

    Returns ``(world, sims, frame_source)``; ``sims`` maps device names (and
    ``"toucan"`` for the camera) to simulator objects. With ``only_sim_ports`` only the
    devices whose port is ``sim://`` are simulated (and registered under their names);
    otherwise every device is (``m2s2hil sim serve``).
    """
    import m2s2hil.simulators  # noqa: F401  (registers sim:// with pyserial)
    from m2s2hil.sim_config import build_frame_source, build_world, camera_sim_name, fault_plans
    from m2s2hil.simulators import registry

    plans = fault_plans(config, faults, seed=seed)
    world = build_world(config, clock)
    sims: dict[str, Any] = {}
    for name, dev in config.devices.items():
        reg = sim_name(dev.port)
        if reg is None and only_sim_ports:
            continue
        sim = kind_of(dev.protocol).make_simulator(Setup(name, config, clock), SimParts(world, plans[name]))
        sims[name] = sim
        if reg is not None:
            registry.register(reg, sim)

    frame_source = None
    if is_simulated(config.camera.port) or not only_sim_ports:
        cam_name = camera_sim_name(config)
        frame_source = build_frame_source(config, world, seed=seed)
        sims[cam_name] = CAMERA.make_simulator(Setup("camera", config, clock),
                                               SimParts(world, plans[cam_name], frame_source))
    return world, sims, frame_source


def open_rig(
    config: RigConfig | None = None,
    *,
    clock: Clock | None = None,
    realtime: bool = False,
    faults: dict[str, list[dict]] | None = None,
    seed: int = 0,
    home: bool = True,
) -> Rig:
    """Open every device of ``config`` (default: the built-in simulated rig)."""
    config = config or default_rig()
    calibration = None
    if config.camera.calibration_file is not None:
        from m2s2hil.processing.calibration import load_calibration

        calibration = load_calibration(config.camera.calibration_file, config.camera.model)
    ports = [d.port for d in config.devices.values()] + [config.camera.port]
    all_sim = all(is_simulated(p) for p in ports)
    any_sim = any(is_simulated(p) for p in ports)
    if clock is None:
        if all_sim and not realtime:
            from m2s2hil.simulators.clock import VirtualClock

            clock = VirtualClock()
        else:
            clock = SYSTEM_CLOCK
    world = frame_source = None
    sims: dict[str, Any] = {}
    if any_sim:
        world, sims, frame_source = build_simulators(config, clock, faults=faults, seed=seed)

    opened: list[Any] = []
    try:
        controllers: dict[str, Any] = {}
        axes: dict[str, Any] = {}
        lights = None
        links: list[DeviceLink] = []  # each connection's capabilities, checked here once
        for name, dev in config.devices.items():
            kind = kind_of(dev.protocol)
            setup = Setup(name, config, clock)
            if isinstance(kind, MotionKind):
                if not setup.axes:
                    continue
                with opening(name, dev.port, dev.protocol, dev.baudrate):
                    ctl, got = kind.open_axes(setup)
                opened.append(ctl)
                controllers[name] = ctl
                axes.update(got)
                roles = tuple(r for r in AXIS_ROLES if r in got)
                links.append(link_for(name, roles, ctl, *(str(a.name) for a in got.values())))
            else:
                with opening(name, dev.port, dev.protocol, dev.baudrate):
                    lights = relay_kind(dev.protocol).open_lights(setup)
                opened.append(lights)
                links.append(link_for(name, ("lights",), lights, lights.name))
        camera = CAMERA.open_camera(Setup("camera", config, clock, sims))
        opened.append(camera)
        links.append(link_for(camera.name, ("camera",), camera))
        if home:
            _home_switched_axes(config, controllers, axes)
        establish_origins(config, controllers, axes)  # axes without switches: a known origin or stop
        if lights is None:
            raise ConfigError("rig", "devices", "no relay board for the lamps")
        if frame_source is not None:
            axes, lights = _mirror_into_world(config, world, sims, axes, lights)
        rig = Rig(
            config=config,
            clock=clock,
            turntable=axes["turntable"],
            tilt=axes["tilt"],
            lights=lights,
            camera=camera,
            links=tuple(links),
            rotation=axes["turntable"] if isinstance(axes["turntable"], ContinuousRotation) else None,
            world=world,
            simulated=all_sim,
            sims=MappingProxyType(sims),
            frame_source=frame_source,
            calibration=calibration,
        )
        rig.lights.set(())
        return rig
    except BaseException:
        for dev in reversed(opened):
            with contextlib.suppress(Exception):
                dev.close()
        raise


def _home_switched_axes(config: RigConfig, controllers: dict[str, Any], axes: dict[str, Any]) -> None:
    """Home what has switches (``homing = "switches"``), nothing else: a factory GRBL answers
    ``$H`` with error:5. A GRBL homes all its switched axes in one ``$H``; a Zaber axis by axis."""
    for name, ctl in controllers.items():
        served = _axes_of(config, name)
        switched = {role: axes[role] for role, ax in served.items() if ax.homing == "switches"}
        if not switched:
            continue
        dev = config.devices[name]
        with opening(name, dev.port, dev.protocol, dev.baudrate):
            motion_kind(dev.protocol).home(ctl, switched)


def _mirror_into_world(
    config: RigConfig, world: Any, sims: dict, axes: dict[str, Any], lights: Any
) -> tuple[dict[str, Any], Any]:
    """A local simulated camera with non-simulated motion or relays: wrap those drivers so
    the camera's world follows what they read back. Returns the (possibly wrapped) devices."""
    from m2s2hil.rig.mirror import MirroredAxis, MirroredLights

    out = dict(axes)
    for role, ax in axes.items():
        if config.axes[role].device not in sims:
            out[role] = MirroredAxis(ax, world, role)
            out[role].position()
    if config.relay_device not in sims:
        lights = MirroredLights(lights, world)
    return out, lights


def open_simulated_rig(
    config: RigConfig | None = None,
    *,
    clock: Clock | None = None,
    realtime: bool = False,
    faults: dict[str, list[dict]] | None = None,
    seed: int = 0,
) -> Rig:
    """The rig of ``config`` (default: built-in) with every device simulated in-process."""
    config = config or default_rig()
    real = [n for n, d in config.devices.items() if not is_simulated(d.port)]
    if not is_simulated(config.camera.port):
        real.append("camera")
    if real:
        raise ConfigError("rig", "devices", f"not simulated: {', '.join(real)} (ports must be sim://NAME)")
    return open_rig(config, clock=clock, realtime=realtime, faults=faults, seed=seed)
