"""Open a rig from its configuration.

Every device gets its driver; every device whose port is ``sim://NAME`` also gets an
in-process simulator registered under NAME, all sharing one simulated world. A rig
whose devices are all simulated runs on a virtual clock unless ``realtime`` is asked
for; a rig with any real device runs in real time.

Axes follow their homing policy (``homing`` in the rig file): only axes with switches are
homed; an axis without switches must stand in its recorded origin (m2s2hil/rig/origin.py).
A device that cannot be opened raises :class:`~m2s2hil.rig.open_errors.RigOpenError`: one
line naming the device, the port and the cause, with a hint and an exit code.
"""

from __future__ import annotations

import contextlib
import logging
import urllib.parse
from collections.abc import Mapping
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

from m2s2hil.config import AxisConfig, DeviceConfig, RigConfig, default_rig
from m2s2hil.drivers.clock import SYSTEM_CLOCK, Clock
from m2s2hil.drivers.interfaces import ContinuousRotation
from m2s2hil.errors import ConfigError
from m2s2hil.rig.open_errors import opening
from m2s2hil.rig.opened import AXIS_ROLES, DeviceLink, Rig, link_for
from m2s2hil.rig.origin import establish_origins

if TYPE_CHECKING:
    from m2s2hil.drivers.u3v import U3VCamera

log = logging.getLogger(__name__)


def _sim_name(url: str) -> str | None:
    if not url.startswith("sim://"):
        return None
    parts = urllib.parse.urlsplit(url)
    return parts.netloc or parts.path.lstrip("/")


def _axes_of(config: RigConfig, device: str) -> dict[str, AxisConfig]:
    return {role: ax for role, ax in config.axes.items() if ax.device == device}


def build_simulators(
    config: RigConfig, clock: Any, *, faults: dict[str, list[dict]] | None = None, seed: int = 0,
    only_sim_ports: bool = True,
) -> tuple[Any, dict[str, Any], Any]:
    """Create the simulated world and a simulator per device.

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
        reg = _sim_name(dev.port)
        if reg is None and only_sim_ports:
            continue
        sim = _make_device_sim(name, dev, config, clock, world, plans[name])
        sims[name] = sim
        if reg is not None:
            registry.register(reg, sim)

    frame_source = None
    if _sim_name(config.camera.port) is not None or not only_sim_ports:
        from m2s2hil.simulators.toucan import ToucanCamera

        model = config.camera.model
        cam_name = camera_sim_name(config)
        frame_source = build_frame_source(config, world, seed=seed)
        sims[cam_name] = ToucanCamera(
            clock=clock,
            frame_source=frame_source,
            width=model.width,
            height=model.height,
            bit_depth=model.bit_depth,
            faults=plans[cam_name],
            name=cam_name,
            max_fps=model.max_fps,
            temperature_c=lambda: world.sensor_temperature_c,
            serial=config.simulation.camera_serial,
        )
    return world, sims, frame_source


def _make_device_sim(name: str, dev: DeviceConfig, config: RigConfig, clock: Any, world: Any, faults: Any):
    axes = _axes_of(config, name)
    if dev.protocol == "grbl":
        from m2s2hil.simulators.grbl import grbl_sim_for

        try:
            options = dict(config.simulation.device_options(name))
            # A simulated controller has switches where the rig file's axes do, unless told otherwise.
            options.setdefault("homing_switches", any(a.homing == "switches" for a in axes.values()))
            return grbl_sim_for(name, axes, clock, world, faults, options)
        except ValueError as exc:
            raise ConfigError("rig", f"simulation.devices.{name}", str(exc)) from None
    if dev.protocol == "zaber":
        from m2s2hil.simulators.zaber import zaber_sim_for

        return zaber_sim_for(name, dev, axes, clock, world, faults)
    if dev.protocol == "modbus-rtu":
        from m2s2hil.simulators.modbus_relay import ModbusRelaySim

        return ModbusRelaySim(name, clock, faults, unit=dev.unit, on_change=world.set_lamp)
    if dev.protocol == "ascii-relay":
        from m2s2hil.simulators.ascii_relay import AsciiRelaySim

        return AsciiRelaySim(name, clock, faults, on_change=world.set_lamp)
    raise ConfigError("rig", f"devices.{name}.protocol", f"no simulator for {dev.protocol!r}")


def _open_axes(name: str, dev: DeviceConfig, config: RigConfig, clock: Clock) -> tuple[Any, dict[str, Any]]:
    axes = _axes_of(config, name)
    if dev.protocol == "grbl":
        from m2s2hil.drivers.grbl import GrblController

        ctl = GrblController(
            dev.port, device=name, baudrate=dev.baudrate, timeout_s=dev.timeout_s, clock=clock,
            retries=dev.retries,
        )
        _connect_or_close(ctl)
        out = {
            role: ctl.axis(
                ax.axis, name=role, units_per_degree=ax.units_per_degree, min_deg=ax.min_deg,
                max_deg=ax.max_deg, max_speed_dps=ax.max_speed_dps, accel_dps2=ax.accel_dps2,
                tolerance_deg=ax.tolerance_deg, settle_s=ax.settle_s,
            )
            for role, ax in axes.items()
        }
        return ctl, out
    if dev.protocol == "zaber":
        from m2s2hil.drivers.zaber import open_zaber_axes

        return open_zaber_axes(name, dev, axes, clock)
    raise ConfigError("rig", f"devices.{name}.protocol", f"{dev.protocol} is not a motion protocol")


def _open_lights(name: str, dev: DeviceConfig, clock: Clock) -> Any:
    if dev.protocol == "modbus-rtu":
        from m2s2hil.drivers.modbus_relay import ModbusRelayBoard

        if dev.unit == 0:
            raise ConfigError(
                "rig", f"devices.{name}.unit", "unit 0 is broadcast: a relay board never answers it"
            )
        board = ModbusRelayBoard(
            dev.port, device=name, unit=dev.unit, baudrate=dev.baudrate, timeout_s=dev.timeout_s,
            clock=clock, retries=dev.retries, parity=dev.parity, stopbits=dev.stopbits,
        )
    else:
        from m2s2hil.drivers.ascii_relay import AsciiRelayBoard

        board = AsciiRelayBoard(
            dev.port, device=name, baudrate=dev.baudrate, timeout_s=dev.timeout_s, clock=clock,
            retries=dev.retries,
        )
    _connect_or_close(board)
    return board


def _connect_or_close(driver: Any) -> None:
    """Connect, or close the port again before the error leaves: anyone looking at the port next
    (:func:`m2s2hil.rig.open_errors.identify_port`, a retry) finds it free."""
    try:
        driver.connect()
    except BaseException:
        driver.close()
        raise


def open_camera(config: RigConfig, clock: Clock, sims: Mapping[str, Any]) -> U3VCamera:
    """The rig file's camera: over the in-process simulator of a ``sim://`` port (from
    ``sims``, as :func:`build_simulators` made them), else on USB; errors as RigOpenError."""
    from m2s2hil.drivers.u3v import U3VCamera

    cam_cfg = config.camera
    with opening("camera", cam_cfg.port, "u3v"):
        if cam_cfg.port.startswith("sim://"):
            from m2s2hil.sim_config import camera_sim_name
            from m2s2hil.simulators.u3v_backend import SimUsbBackend

            toucan = sims[camera_sim_name(config)]
            return U3VCamera.open(backend=SimUsbBackend(toucan), serial=toucan.serial, clock=clock,
                                  timeout_s=cam_cfg.timeout_s, name="camera")
        return U3VCamera.open(vendor_id=cam_cfg.vendor_id, product_id=cam_cfg.product_id,
                              serial=cam_cfg.serial, clock=clock, timeout_s=cam_cfg.timeout_s, name="camera")


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
    all_sim = all(p.startswith("sim://") for p in ports)
    any_sim = any(p.startswith("sim://") for p in ports)
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
            if dev.protocol in ("grbl", "zaber"):
                if not _axes_of(config, name):
                    continue
                with opening(name, dev.port, dev.protocol, dev.baudrate):
                    ctl, got = _open_axes(name, dev, config, clock)
                opened.append(ctl)
                controllers[name] = ctl
                axes.update(got)
                roles = tuple(r for r in AXIS_ROLES if r in got)
                links.append(link_for(name, roles, ctl, *(str(a.name) for a in got.values())))
            else:
                with opening(name, dev.port, dev.protocol, dev.baudrate):
                    lights = _open_lights(name, dev, clock)
                opened.append(lights)
                links.append(link_for(name, ("lights",), lights, lights.name))
        camera = open_camera(config, clock, sims)
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
        switched = [role for role, ax in _axes_of(config, name).items() if ax.homing == "switches"]
        if not switched:
            continue
        dev = config.devices[name]
        with opening(name, dev.port, dev.protocol, dev.baudrate):
            if dev.protocol == "grbl":
                ctl.home()
            else:
                for role in switched:
                    axes[role].home()


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
    real = [n for n, d in config.devices.items() if not d.port.startswith("sim://")]
    if not config.camera.port.startswith("sim://"):
        real.append("camera")
    if real:
        raise ConfigError("rig", "devices", f"not simulated: {', '.join(real)} (ports must be sim://NAME)")
    return open_rig(config, clock=clock, realtime=realtime, faults=faults, seed=seed)
