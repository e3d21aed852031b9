"""Zaber ASCII motion devices: driver, simulator, ``rig probe`` and recognition.

``rig probe`` reads, per axis, ``maxspeed``, ``accel``, ``limit.min`` and ``limit.max`` in the
device's data units, converted as the driver converts them. The driver writes these when the
rig opens, so a mismatch only says the stored values differ.

An axis without switches gets its origin with ``set pos 0``: the current place becomes
position 0 without moving (the ``pos`` setting is writable: Zaber ASCII Protocol Manual,
firmware 7, "pos"). When the rig opens the device must be the one the origin was set on (its
serial number) and show no fault flag.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

from m2s2hil.config import AxisConfig, DeviceConfig
from m2s2hil.drivers.interfaces import RotaryAxis
from m2s2hil.rig.devices.findings import Finding, ProbeReport
from m2s2hil.rig.devices.kind import MotionKind, OriginReading, Setup, Signature, SimParts, close_quietly
from m2s2hil.rig.open_errors import RigOpenError, opening


def _simulator(setup: Setup, parts: SimParts) -> Any:
    from m2s2hil.simulators.zaber import zaber_sim_for

    return zaber_sim_for(setup.name, setup.device, setup.axes, setup.clock, parts.world, parts.faults)


def _open_axes(setup: Setup) -> tuple[Any, dict[str, RotaryAxis]]:
    from m2s2hil.drivers.zaber import open_zaber_axes

    zd, axes = open_zaber_axes(setup.name, setup.device, setup.axes, setup.clock)
    return zd, dict(axes)


def _home(device: Any, switched: Mapping[str, Any]) -> None:
    for axis in switched.values():  # a Zaber device homes axis by axis
        axis.home()


def _expected(ax: AxisConfig) -> dict[str, int]:
    from m2s2hil.protocols.zaber import ACCEL_DATA_PER_USTEP_S2, VELOCITY_DATA_PER_USTEP_S

    upd = ax.units_per_degree
    return {
        "maxspeed": max(1, round(ax.max_speed_dps * upd * VELOCITY_DATA_PER_USTEP_S)),
        "accel": max(1, round(ax.accel_dps2 * upd * ACCEL_DATA_PER_USTEP_S2)),
        "limit.min": round(ax.min_deg * upd),
        "limit.max": round(ax.max_deg * upd),
    }


_EFFECTS = {
    "maxspeed": "stored maximum speed differs (the driver sets the rig file's when the rig opens)",
    "accel": "stored acceleration differs (the driver sets the rig file's when the rig opens)",
    "limit.min": "stored travel limit differs (the driver sets the rig file's when the rig opens)",
    "limit.max": "stored travel limit differs (the driver sets the rig file's when the rig opens)",
}


def _controller(setup: Setup) -> Any:
    from m2s2hil.drivers.zaber import ZaberDevice

    dev = setup.device
    return ZaberDevice(dev.port, device=setup.name, address=dev.unit, baudrate=dev.baudrate,
                       timeout_s=dev.timeout_s, clock=setup.clock, retries=dev.retries)


def _identity(zd: Any) -> str:
    return f"Zaber {zd.info.get('deviceid', '?')} serial {zd.info.get('system.serial', '?')}"


def _set_origin(zd: Any, ax: AxisConfig, dev: DeviceConfig) -> OriginReading:
    """``set pos 0`` on a connected device, read back."""
    with opening(ax.device, dev.port, dev.protocol, dev.baudrate):
        number = int(ax.axis)
        zd.request(number, "set pos 0", check_faults=False)
        pos = zd.get("pos", number)
    if pos.strip() != "0":
        raise RigOpenError(ax.device, dev.port, "device error", f"after set pos 0 the axis reports {pos}")
    return OriginReading(str(number), _identity(zd), 0.0)


def _stored_origin(zd: Any, role: str, ax: AxisConfig, dev: DeviceConfig) -> OriginReading:
    """No fault flag on the axis; the position counts from the origin itself (offset 0)."""
    reply = zd.request(int(ax.axis), "", idempotent=True, check_faults=False)
    if reply.fault:
        raise RigOpenError(ax.device, dev.port, "alarm", f"axis {ax.axis} reports fault {reply.warning}")
    return OriginReading(str(int(ax.axis)), _identity(zd), 0.0)


def _probe(setup: Setup, report: ProbeReport, apply: bool) -> None:
    name, dev = setup.name, setup.device
    zd = _controller(setup)
    add = report.findings.append
    try:
        with opening(name, dev.port, dev.protocol, dev.baudrate):
            info = zd.connect()
            add(Finding(name, "device id", "", info.get("deviceid", "?"), None))
            add(Finding(name, "firmware", "", info.get("version", "?"), None))
            add(Finding(name, "serial", "", info.get("system.serial", "?"), None))
            for role, ax in setup.axes.items():
                number = int(ax.axis)
                for setting, want in _expected(ax).items():
                    if apply:
                        zd.request(number, f"set {setting} {want}", check_faults=False)
                    raw = zd.get(setting, number)
                    try:
                        have = int(raw.split()[0])
                    except (ValueError, IndexError):
                        have = None
                    ok = have == want
                    add(Finding(name, f"axis {number} {setting} ({role})", str(want), raw, ok,
                                "" if ok else _EFFECTS[setting],
                                None if ok else (setting, float(want))))
                reply = zd.request(number, "", idempotent=True, check_faults=False)
                add(Finding(name, f"axis {number} flag ({role})", "", reply.warning,
                            False if reply.fault else None, "a fault: moves are refused until it is cleared"))
    finally:
        close_quietly(zd)


KIND = MotionKind(
    protocol="zaber",
    title="Zaber ASCII",
    make_simulator=_simulator,
    open_axes=_open_axes,
    home=_home,
    controller=_controller,
    set_origin=_set_origin,
    stored_origin=_stored_origin,
    probe=_probe,
    # A status poll (``/``) is answered ``@nn a OK IDLE -- 0`` by every Zaber device
    # (Zaber ASCII protocol manual, "Reply messages").
    signature=Signature(b"\n/\n", re.compile(rb"^@\d\d \d ", re.M)),
)
