"""A Zaber rotary device speaking the ASCII protocol, as a simulated serial device.

One device address, one or more axes. Replies carry the command's message id and a
checksum when the command had them (as zaber-motion sends every command), so the
driver can match them. Positions are in microsteps; ``maxspeed`` and ``move vel`` in
the protocol's velocity data units (microsteps/s × 1.6384), ``accel`` in its
acceleration units (microsteps/s² × 1.6384 / 10000).

Commands: the empty command (status), ``home``, ``move abs|rel|vel N``, ``stop``,
``estop``, ``get``/``set`` of the settings below, ``warnings [clear]``.

Identity: ``deviceid`` (and its firmware-7 name ``device.id``), ``system.serial``,
``version``, ``version.build``, ``system.axiscount`` (ASCII Protocol Manual; the X-MCB1
manual's settings table gives ``version.build`` from 6.17 and ``system.serial`` from 6.15),
and what zaber-motion's ``identify()`` reads besides (found by running it against this
simulator): ``comm.packet.size.max``, ``device.hw.modified``, ``comm.command.packets.max``,
``comm.word.size.max`` (the longest setting name the simulator knows, so every word fits),
``get.settings.max``, and per axis ``resolution`` and ``peripheralid`` (rejected
``BADCOMMAND``: an integrated stage has no peripheral; assumed).

Rejections: ``BADCOMMAND`` (unknown command or setting, writing a read-only one), ``BADDATA`` (a
missing or non-integer number, a target outside ``limit.min..limit.max``, a velocity
above ``maxspeed``), ``BADAXIS`` (no such axis, or a device setting asked of an axis).

Flags: ``WR`` until the axis is homed; ``NI`` after ``stop``/``estop`` interrupted a
move (cleared by the next move); faults persist until ``warnings clear``.
Assumptions: a command with a wrong checksum is dropped without a reply; a move that
reverses a moving axis starts its new profile from rest. A vanished port does not
reset the device (it has its own power supply).

:meth:`ZaberSimulator.axis_position` also answers for a moment just past (``at=``), for
a camera that renders a frame after its exposure (the recent path: a :class:`PathLog`).

Faults (``self.faults``): ``stall`` (``fraction``, default 0.5) stops the next move
part-way and sets ``FS``; ``alarm`` (``flag`` default ``FQ``, ``at`` default 0.5)
stops it mid-move with that fault flag. For a slow or stuck rig: ``slow_motion``
(``factor``, default 5) runs the next move (each move with ``count = -1``) that many times
slower than ``maxspeed``/``accel`` say (speed / factor, acceleration / factor², its stop
too); ``hang`` (``fraction``, default 0.5) freezes the next move part-way while the axis
still replies ``BUSY`` (no progress, no flag) until ``stop``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from m2s2hil.protocols.zaber import (
    ACCEL_DATA_PER_USTEP_S2,
    VELOCITY_DATA_PER_USTEP_S,
    CommandParser,
    ReceivedCommand,
    Reply,
    flag_rank,
    format_reply,
    highest_flag,
)
from m2s2hil.simulators.device import SimDevice
from m2s2hil.simulators.fault_injection import FaultPlan
from m2s2hil.simulators.motion_kit import InOrderReplies, PathLog, Segment, Trapezoid

AXIS_SETTINGS_RW = ("maxspeed", "accel", "limit.min", "limit.max", "pos")
AXIS_SETTINGS_RO = ("resolution", "encoder.pos")

#: The product meant: a Zaber X-RSW60A-E03 motorized rotary stage (integrated controller,
#: firmware 7, resolution 64). ASSUMED, not from a vendor document (none giving them was at
#: hand; see docs/simulators.md): the device id, firmware version and build below, and the
#: 0.000234375° microstep the default speeds are computed with. All are constructor options.
DEVICE_ID = 50000
FIRMWARE_VERSION = "7.38"
FIRMWARE_BUILD = 16100


@dataclass(frozen=True)
class ZaberAxisSettings:
    maxspeed: int = 419430  # about 60°/s at 4266.67 microsteps/° (a 0.000234375° microstep)
    accel: int = 84  # about 120°/s²
    limit_min: int = -10_000_000
    limit_max: int = 10_000_000
    resolution: int = 64
    start: int = 0  # physical position at power-up, microsteps from the home sensor


@dataclass
class _Axis:
    settings: dict[str, int]
    offset: float  # physical = reported position + offset
    rest: float = 0.0
    segment: Segment | None = None
    direction: int = 0
    homed: bool = False
    flags: set[str] = field(default_factory=set)
    alarm: tuple[float, str] | None = None
    slow: float = 1.0  # the current motion's slow_motion factor
    hung: bool = False  # the current move froze part-way but still replies BUSY
    path: PathLog = field(default_factory=PathLog)  # physical positions over the recent changes

    def position(self, now: float) -> float:
        if self.segment is None:
            return self.rest
        return self.rest + self.direction * self.segment.covered(now)

    def note(self, t: float) -> None:
        """Log the motion from ``t`` on (a no-op unless it changed)."""
        seg = self.segment
        if seg is None:
            here = self.rest + self.offset
            self.path.note(t, (None, here), lambda _t, p=here: p)
        else:
            base, d = self.rest + self.offset, self.direction
            self.path.note(seg.t0, (seg, base, d), lambda t_, s=seg, b=base, d=d: b + d * s.covered(t_))

    def speed(self, now: float) -> float:
        seg = self.segment
        if seg is None or (self.hung and seg.covered(now) >= (seg.stop_after or 0.0)):
            return 0.0  # a hung move stands at its freezing point
        return seg.speed(now)

    def all_flags(self) -> set[str]:
        return self.flags | (set() if self.homed else {"WR"})


class ZaberSimulator(InOrderReplies, SimDevice):
    def __init__(
        self,
        name: str,
        clock: Any,
        *,
        address: int = 1,
        axes: list[ZaberAxisSettings] | int = 1,
        faults: FaultPlan | None = None,
        device_id: int = DEVICE_ID,
        serial: int = 12345,
        version: str = FIRMWARE_VERSION,
        build: int = FIRMWARE_BUILD,
    ) -> None:
        super().__init__(name, clock, faults)
        if isinstance(axes, int):
            axes = [ZaberAxisSettings() for _ in range(axes)]
        if not 1 <= len(axes) <= 9 or not 1 <= address <= 99:
            raise ValueError("a Zaber device has 1..9 axes and an address 1..99")
        self.address = address
        self._axes = [
            _Axis(
                {
                    "maxspeed": a.maxspeed,
                    "accel": a.accel,
                    "limit.min": a.limit_min,
                    "limit.max": a.limit_max,
                    "resolution": a.resolution,
                },
                offset=float(a.start),
            )
            for a in axes
        ]
        self.device_settings: dict[str, str] = {
            "deviceid": str(device_id),
            "device.id": str(device_id),  # the firmware-7 name of deviceid [ascii]
            "system.serial": str(serial),
            "version": version,
            "version.build": str(build),
            "device.hw.modified": "0",  # not modified from the catalogue product
            "system.axiscount": str(len(axes)),
            "comm.packet.size.max": "80",
            # One packet per command and one setting per get: the simulator assembles no
            # continuation packets and answers no multi-setting get (assumed values).
            "comm.command.packets.max": "1",
            "get.settings.max": "1",
            "comm.alert": "0",
        }
        # Every word the device reads or writes fits: the longest setting name it knows.
        names = [*self.device_settings, *AXIS_SETTINGS_RW, *AXIS_SETTINGS_RO, "comm.word.size.max"]
        self.device_settings["comm.word.size.max"] = str(max(len(n) for n in names))
        self._parser = CommandParser()
        self.ignored = 0  # commands dropped for a bad checksum or a malformed line
        for ax in self._axes:
            ax.note(clock.monotonic())

    # -- inspection ------------------------------------------------------------------
    def axis_position(self, axis: int = 1, at: float | None = None) -> float:
        """Physical position in microsteps from the home sensor (for the simulated world):
        now, or at clock time ``at`` (any moment since the axis' last 16 motion changes)."""
        with self.lock:
            now = self.clock.monotonic()
            self._advance(now)
            ax = self._axes[axis - 1]
            if at is None:
                return ax.position(now) + ax.offset
            return float(ax.path.at(float(at)))

    # -- SimDevice hooks -------------------------------------------------------------
    def on_bytes(self, data: bytes) -> None:
        now = self.clock.monotonic()
        self._advance(now)
        for item in self._parser.feed(data):
            if not isinstance(item, ReceivedCommand):
                self.ignored += 1
                continue
            cmd = item.command
            if cmd.address not in (None, 0, self.address):
                continue
            axis = cmd.axis or 0
            flag, data_out = self._execute(axis, cmd.text.split(), now)
            targets = self._targets(axis) if axis <= len(self._axes) else self._axes
            reply = Reply(
                address=self.address,
                axis=axis,
                message_id=cmd.message_id,
                flag=flag,
                status="BUSY" if any(a.segment is not None for a in targets) else "IDLE",
                warning=highest_flag(f for a in targets for f in a.all_flags()),
                data=data_out,
            )
            self.send(format_reply(reply, with_checksum=item.checksummed))
        for ax in self._axes:
            ax.note(now)

    def poll(self, now: float) -> None:
        self._advance(now)

    def next_event(self) -> float | None:
        times = [a.segment.t_end for a in self._axes if a.segment is not None and not a.hung]
        times += [a.alarm[0] for a in self._axes if a.alarm is not None]
        return min(times) if times else None

    def on_disconnect(self) -> None:
        self.forget_order()

    # -- motion ------------------------------------------------------------------------
    def _advance(self, now: float) -> None:
        for ax in self._axes:
            seg = ax.segment
            if seg is None:
                continue
            if ax.alarm is not None and ax.alarm[0] <= min(now, seg.t_end):
                when = ax.alarm[0]
                ax.rest = ax.position(when)
                ax.flags.add(ax.alarm[1])
                ax.segment, ax.alarm = None, None
                ax.note(when)
            elif seg.t_end <= now and not ax.hung:
                ax.rest = ax.position(seg.t_end)
                ax.segment, ax.alarm = None, None
                if seg.stop_after is not None:
                    ax.flags.add("FS")
                if seg.kind == "home":
                    ax.offset, ax.rest, ax.homed = 0.0, 0.0, True
                ax.note(seg.t_end)

    def _start(
        self, ax: _Axis, target: float, now: float, *, v_data: float | None = None, kind: str = "move"
    ) -> None:
        pos, v = ax.position(now), ax.speed(now)
        direction = 1 if target >= pos else -1
        v0 = v if direction == ax.direction else 0.0
        slow = None if kind == "home" or target == pos else self.faults.take("slow_motion")
        ax.slow, ax.hung = (float(slow.get("factor", 5.0)) if slow is not None else 1.0), False
        v_max = (v_data if v_data is not None else ax.settings["maxspeed"]) / VELOCITY_DATA_PER_USTEP_S
        v_max /= ax.slow
        accel = max(ax.settings["accel"], 1) / ACCEL_DATA_PER_USTEP_S2 / ax.slow**2
        profile = Trapezoid(abs(target - pos), max(v_max, 1e-9), accel, v0=v0)
        ax.rest, ax.direction, ax.alarm = pos, direction, None
        ax.segment = Segment((0.0,), (abs(target - pos),), now, profile, kind=kind)
        ax.flags.discard("NI")
        if kind == "home" or profile.length == 0:
            return
        stall = self.faults.take("stall")
        if stall is not None:
            ax.segment.stop_after = float(stall.get("fraction", 0.5)) * profile.length
        hang = self.faults.take("hang")
        if hang is not None:
            ax.segment.stop_after = float(hang.get("fraction", 0.5)) * profile.length
            ax.hung = True
        fault = self.faults.take("alarm")
        if fault is not None:
            when = now + float(fault.get("at", 0.5)) * profile.duration
            ax.alarm = (when, str(fault.get("flag", "FQ")))

    def _stop(self, ax: _Axis, now: float, *, hard: bool) -> None:
        if ax.segment is None:
            return
        pos, v = ax.position(now), ax.speed(now)
        ax.flags.add("NI")
        ax.alarm, ax.hung = None, False
        if hard or v <= 0:
            ax.rest, ax.segment = pos, None
            return
        accel = max(ax.settings["accel"], 1) / ACCEL_DATA_PER_USTEP_S2 / ax.slow**2
        length = v * v / (2 * accel)
        ax.rest = pos
        ax.segment = Segment((0.0,), (length,), now, Trapezoid(length, v, accel, v0=v), kind="stop")

    # -- commands ----------------------------------------------------------------------
    def _targets(self, axis: int) -> list[_Axis]:
        return self._axes if axis == 0 else [self._axes[axis - 1]]

    def _execute(self, axis: int, words: list[str], now: float) -> tuple[str, str]:
        """(OK|RJ, data) for one command."""
        if axis > len(self._axes):
            return "RJ", "BADAXIS"
        if not words:
            return "OK", "0"
        head, args = words[0], words[1:]
        targets = self._targets(axis)
        if head == "home" and not args:
            for ax in targets:
                self._start(ax, -ax.offset, now, kind="home")
            return "OK", "0"
        if head == "move" and len(args) == 2:
            return self._move(targets, args[0], args[1], now)
        if head in ("stop", "estop") and not args:
            for ax in targets:
                self._stop(ax, now, hard=head == "estop")
            return "OK", "0"
        if head == "get" and len(args) == 1:
            return self._get(axis, args[0], now)
        if head == "set" and len(args) == 2:
            return self._set(axis, args[0], args[1], now)
        if head == "warnings" and args in ([], ["clear"]):
            flags = sorted({f for ax in targets for f in ax.all_flags()}, key=flag_rank)
            if args:
                for ax in targets:
                    ax.flags.clear()
            return "OK", " ".join([f"{len(flags):02d}", *flags])
        return "RJ", "BADCOMMAND"

    def _move(self, targets: list[_Axis], mode: str, value: str, now: float) -> tuple[str, str]:
        if mode not in ("abs", "rel", "vel"):
            return "RJ", "BADCOMMAND"
        try:
            n = int(value)
        except ValueError:
            return "RJ", "BADDATA"
        plans = []
        for ax in targets:
            lo, hi = ax.settings["limit.min"], ax.settings["limit.max"]
            if mode == "vel":
                if abs(n) > ax.settings["maxspeed"]:
                    return "RJ", "BADDATA"
                plans.append((ax, hi if n > 0 else lo, abs(n)))
                continue
            target = n if mode == "abs" else round(ax.position(now)) + n
            if not lo <= target <= hi:
                return "RJ", "BADDATA"
            plans.append((ax, target, None))
        for ax, target, v in plans:
            if v == 0:
                self._stop(ax, now, hard=False)
            else:
                self._start(ax, target, now, v_data=v)
        return "OK", "0"

    def _get(self, axis: int, name: str, now: float) -> tuple[str, str]:
        if name in self.device_settings:
            return ("OK", self.device_settings[name]) if axis == 0 else ("RJ", "BADAXIS")
        if name in ("pos", "encoder.pos"):
            return "OK", " ".join(str(round(ax.position(now))) for ax in self._targets(axis))
        if name in AXIS_SETTINGS_RW or name in AXIS_SETTINGS_RO:
            return "OK", " ".join(str(ax.settings[name]) for ax in self._targets(axis))
        return "RJ", "BADCOMMAND"

    def _set(self, axis: int, name: str, value: str, now: float) -> tuple[str, str]:
        if name not in AXIS_SETTINGS_RW and name != "comm.alert":
            return "RJ", "BADCOMMAND"
        try:
            n = int(value)
        except ValueError:
            return "RJ", "BADDATA"
        if name == "comm.alert":
            if axis != 0 or n not in (0, 1):
                return "RJ", "BADAXIS" if axis else "BADDATA"
            self.device_settings[name] = str(n)
            return "OK", "0"
        if name in ("maxspeed", "accel") and n <= 0:
            return "RJ", "BADDATA"
        for ax in self._targets(axis):
            if name == "pos":
                if ax.segment is not None:
                    return "RJ", "BADDATA"
                ax.offset += ax.rest - n  # the same physical place gets a new number
                ax.rest = float(n)
            else:
                ax.settings[name] = n
        return "OK", "0"


def zaber_sim_for(
    name: str, dev: Any, axes: Mapping[str, Any], clock: Any, world: Any, faults: FaultPlan | None
) -> ZaberSimulator:
    """The simulator for the Zaber device ``name`` of a rig configuration.

    ``dev`` is a ``DeviceConfig`` (its ``unit`` is the device address) and ``axes`` maps
    roles to ``AxisConfig`` objects (``axis`` = axis number); each role is attached to
    ``world`` (if given) in degrees.
    """
    numbers = {role: int(ax.axis) for role, ax in axes.items()}
    settings = [ZaberAxisSettings() for _ in range(max(numbers.values(), default=1))]
    for role, ax in axes.items():
        upd = ax.units_per_degree
        settings[numbers[role] - 1] = ZaberAxisSettings(
            maxspeed=math.ceil(ax.max_speed_dps * upd * VELOCITY_DATA_PER_USTEP_S),
            accel=max(1, round(ax.accel_dps2 * upd * ACCEL_DATA_PER_USTEP_S2)),
        )
    sim = ZaberSimulator(name, clock, address=dev.unit, axes=settings, faults=faults)
    if world is not None:
        for role, ax in axes.items():
            world.attach_axis(
                role, lambda t, n=numbers[role], upd=ax.units_per_degree: sim.axis_position(n, t) / upd,
                timed=True,
            )
    return sim
