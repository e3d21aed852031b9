"""Axes without home switches: the operator's origin, set on the controller and recorded.

A turntable or tilt stage without switches (``homing = "none"`` in the rig file, the
default: a factory GRBL 1.1 has homing off, ``$22=0``) cannot find its zero by itself.
The operator turns it to the zero mark and runs ``m2s2hil rig origin AXIS --rig FILE``,
which makes where the axis stands its zero on the controller, as its motion kind does it
(:class:`~m2s2hil.rig.devices.kind.MotionKind` ``set_origin``, ``stored_origin``,
``use_origin``): GRBL writes the G54 work offset with ``G10 L20`` (kept in EEPROM), Zaber
sets ``pos`` to 0 (:mod:`m2s2hil.rig.devices.grbl`, :mod:`m2s2hil.rig.devices.zaber`).

The origin is recorded in the rig's state file, ``<rig file stem>.state.json`` next to
the rig file (it describes that rig; sessions on any data root use it), with what the
controller reported. When the rig opens (:func:`establish_origins`), every axis without
switches must have a recorded origin, and the controller must still hold it: GRBL not in
alarm and its G54 offset the recorded one; Zaber the same device (serial number) and no
fault flag. Otherwise opening stops with a :class:`~m2s2hil.rig.open_errors.RigOpenError`
telling the operator to run ``rig origin``. Limits (docs/rig-setup.md): GRBL zeroes its
machine position at power-up, and a board that resets when its port opens (an Arduino's
DTR line) does so at every connection; the G54 offset survives, so the origin holds as
long as the axis is not moved while the controller is off. Neither controller can tell
that an axis was turned by hand.

In-process simulated axes (``sim://``) start from their power-up position, which is their
origin: they need no record.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import json
from collections.abc import Iterator, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from m2s2hil.config import AxisConfig, DeviceConfig, RigConfig
from m2s2hil.drivers.clock import SYSTEM_CLOCK, Clock
from m2s2hil.errors import M2S2Error, UsageError
from m2s2hil.rig.devices import motion_kind
from m2s2hil.rig.devices.kind import OFFSET_TOLERANCE_UNITS, OriginReading, Setup
from m2s2hil.rig.open_errors import RigOpenError, opening
from m2s2hil.sim_config import is_simulated

if TYPE_CHECKING:
    from m2s2hil.rig.opened import Rig

STATE_FORMAT = "m2s2hil-rig-state/1"


class StateFileError(UsageError):
    """A rig state file that cannot be read or written."""


class PositionLost(M2S2Error):
    """A controller restarted (power cycle, replugged USB) under axes without switches: their
    position is gone and only the operator can set the origin again. Not a device fault the
    engine may retry: the run stops."""

    fault_class = "other"

    def __init__(self, device: str, roles: list[str]) -> None:
        self.device = device
        self.roles = roles
        super().__init__(f"{device} restarted: {', '.join(roles)} lost the position (no home switches); "
                         "turn each to its zero mark and run `m2s2hil rig origin AXIS --rig FILE`, "
                         "then resume")


@dataclass(frozen=True)
class AxisOrigin:
    device: str  # the rig file's device name
    protocol: str
    axis: str  # GRBL letter or Zaber axis number
    controller: str  # what the controller said it is ("GRBL 1.1h.20190830", "Zaber 50000 serial 12345")
    offset_units: float  # GRBL: the G54 offset written by G10 L20; Zaber: 0 (set pos 0)
    set_at: str  # UTC, ISO 8601


@dataclass
class RigState:
    rig: str = ""
    origins: dict[str, AxisOrigin] = field(default_factory=dict)

    @classmethod
    def load(cls, path: Path | None) -> RigState:
        if path is None or not path.exists():
            return cls()
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
            if doc.get("format") != STATE_FORMAT:
                raise ValueError(f"format {doc.get('format')!r}, expected {STATE_FORMAT!r}")
            origins = {role: AxisOrigin(**o) for role, o in dict(doc.get("origins", {})).items()}
        except (OSError, ValueError, TypeError, AttributeError) as exc:
            raise StateFileError(f"{path}: not a usable rig state file ({exc}); delete it and set the "
                                 "origins again with `m2s2hil rig origin`") from None
        return cls(rig=str(doc.get("rig", "")), origins=origins)

    def save(self, path: Path) -> None:
        from m2s2hil.atomic import write_text_atomic

        doc = {"format": STATE_FORMAT, "rig": self.rig,
               "origins": {role: asdict(o) for role, o in sorted(self.origins.items())}}
        try:
            write_text_atomic(path, json.dumps(doc, indent=2) + "\n")
        except OSError as exc:
            raise StateFileError(f"{path}: cannot write the rig state ({exc})") from None


def state_path(config: RigConfig) -> Path | None:
    """``my_rig.state.json`` next to ``my_rig.toml``; None for a rig that has no file."""
    src = config.source_path
    return None if src is None else src.with_name(src.stem + ".state.json")


def _now() -> str:
    return dt.datetime.now(dt.UTC).isoformat(timespec="seconds")


def _axis(config: RigConfig, role: str) -> AxisConfig:
    if role not in config.axes:
        raise UsageError(f"no axis {role!r} in the rig file; axes: {', '.join(sorted(config.axes))}")
    return config.axes[role]  # type: ignore[index]


def set_origin(config: RigConfig, role: str, *, clock: Clock = SYSTEM_CLOCK,
               path: Path | None = None) -> AxisOrigin:
    """Make where axis ``role`` stands its zero, on the controller and in the state file."""
    ax = _axis(config, role)
    dev = config.devices[ax.device]
    path = path or state_path(config)
    if is_simulated(dev.port):
        raise UsageError(f"{role} is simulated in-process ({dev.port}): it starts at its origin every time "
                         "the rig opens, there is nothing to record")
    if path is None:
        raise UsageError("the rig has no file to keep its state next to: pass --rig FILE")
    state = RigState.load(path)
    kind = motion_kind(dev.protocol)
    ctl = kind.controller(Setup(ax.device, config, clock))
    with _connected(ctl, ax, dev):
        origin = _record(kind.set_origin(ctl, ax, dev), ax, dev)
    state.rig = config.rig.name
    state.origins[role] = origin
    state.save(path)
    return origin


def _record(reading: OriginReading, ax: AxisConfig, dev: DeviceConfig) -> AxisOrigin:
    return AxisOrigin(ax.device, dev.protocol, reading.axis, reading.controller, reading.offset_units, _now())


@contextlib.contextmanager
def _connected(driver: Any, ax: AxisConfig, dev: DeviceConfig) -> Iterator[None]:
    """A connection of our own for the command line (closed afterwards); errors as when opening a rig."""
    try:
        with opening(ax.device, dev.port, dev.protocol, dev.baudrate):
            driver.connect()
        yield
    finally:
        driver.close()


def set_origin_open(rig: Rig, role: str) -> AxisOrigin:
    """:func:`set_origin` through the opened rig's own connection (the daemon holds the ports
    exclusively, so it cannot open them a second time); the axis driver counts from the new
    origin at once."""
    from m2s2hil.rig.mirror import MirroredAxis

    config = rig.config
    ax = _axis(config, role)
    dev = config.devices[ax.device]
    if ax.homing != "none":
        raise UsageError(f"{role} homes on its switches (homing = \"switches\"): home it instead")
    if is_simulated(dev.port):
        raise UsageError(f"{role} is simulated in-process ({dev.port}): it starts at its origin every time "
                         "the rig opens, there is nothing to record")
    path = state_path(config)
    if path is None:
        raise UsageError("the rig has no file to keep its state next to: start the daemon with --rig FILE")
    link = next((lk for lk in rig.links if lk.means(ax.device)), None)
    owner = link.reconnect if link is not None else None
    if owner is None:
        raise UsageError(f"{role}: no open connection to {ax.device} to set the origin through")
    kind = motion_kind(dev.protocol)
    origin = _record(kind.set_origin(owner, ax, dev), ax, dev)
    drv: object = rig.axis(role)  # type: ignore[arg-type]
    kind.use_origin(drv.wrapped if isinstance(drv, MirroredAxis) else drv, origin.offset_units)
    state = RigState.load(path)
    state.rig = config.rig.name
    state.origins[role] = origin
    state.save(path)
    return origin


# -- when the rig opens ----------------------------------------------------------------------
def establish_origins(config: RigConfig, controllers: Mapping[str, Any], axes: Mapping[str, Any],
                      *, path: Path | None = None) -> dict[str, float]:
    """Check every axis without switches stands in a known frame and put its origin into the driver.

    ``controllers`` maps device names to connected drivers, ``axes`` roles to axis drivers.
    Returns each checked role's origin offset (machine units). Raises RigOpenError when an
    origin was never set or the controller no longer holds it.
    """
    path = path or state_path(config)
    state: RigState | None = None
    out: dict[str, float] = {}
    for role, ax in config.axes.items():
        if ax.homing != "none" or ax.device not in controllers:
            continue
        dev = config.devices[ax.device]
        kind = motion_kind(dev.protocol)
        with opening(ax.device, dev.port, dev.protocol, dev.baudrate):
            held = kind.stored_origin(controllers[ax.device], role, ax, dev)
        offset, identity = held.offset_units, held.controller
        if not is_simulated(dev.port):
            if state is None:
                state = RigState.load(path)
            rec = state.origins.get(role)
            where = f" (state file {path})" if path is not None else " (the rig has no file to keep state in)"
            if rec is None or rec.device != ax.device or rec.axis.upper() != ax.axis.upper():
                raise RigOpenError(role, dev.port, "no origin",
                                   f"{role} has no home switches and no recorded origin{where}")
            if rec.controller != identity:
                raise RigOpenError(role, dev.port, "position unknown",
                                   f"the origin was set on {rec.controller}, this is {identity}")
            if abs(rec.offset_units - offset) > OFFSET_TOLERANCE_UNITS:
                raise RigOpenError(role, dev.port, "position unknown",
                                   f"the controller's stored origin is {offset:g}, the recorded one "
                                   f"{rec.offset_units:g} (changed by another program, or its EEPROM reset)")
        drv = axes.get(role)
        if drv is not None:
            kind.use_origin(drv, offset)
            drv.position()  # the controller reports a position in this frame (raises if it cannot)
        out[role] = offset
    return out
