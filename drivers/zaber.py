"""Driver for Zaber rotary stages speaking the ASCII protocol.

Like the official library, every command carries a message id and a checksum
(``/1 1 07 get pos:XX``); a reply counts only if its address and id match, so a late
reply to an earlier command is recognised and dropped, and its checksum is verified.

Error mapping (each names device, command and attempt): ``RJ`` → CommandRejected
(code = RejectReason, or the raw text for an unknown reason); a fault flag (``F*``,
e.g. FS stall, FQ encoder error) in any reply → StageAlarm(code = WarningFlag) until
:meth:`ZaberDevice.clear_faults`; no reply → DeviceTimeout; a bad checksum or garbage
→ ProtocolError; the port vanished → DeviceGone (then :meth:`ZaberDevice.reconnect`).
Queries (``get``, the status poll, ``warnings``) are retried ``retries`` times after a
timeout or a garbled reply; motion commands never are.

Every reply carries the axis's status, ``BUSY`` while it moves and ``IDLE`` otherwise
[Zaber, "Zaber's ASCII Protocol", zaber.com/articles/ascii-protocol; ASCII Protocol
Manual, "Replies"], so a wait on motion polls ``get pos``: one exchange gives both the
status and the position. The wait follows the motion (:mod:`m2s2hil.drivers.motion_watch`):
the trapezoid at the axis's ``maxspeed``/``accel`` (written from the rig file by
:meth:`ZaberAxis.configure`), extended while the position still changes.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any, Unpack

from m2s2hil.drivers.axis_base import AxisSpec, MotionController, RotaryAxisBase
from m2s2hil.drivers.clock import SYSTEM_CLOCK, Clock
from m2s2hil.drivers.errors import (
    CommandRejected,
    DeviceTimeout,
    ProtocolError,
    StageAlarm,
)
from m2s2hil.drivers.locking import one_at_a_time
from m2s2hil.drivers.motion_watch import PLAN_MARGIN, STALL_WINDOW_S, ProgressWatch, braking_s
from m2s2hil.protocols.zaber import (
    ACCEL_DATA_PER_USTEP_S2,
    MAX_MESSAGE_ID,
    VELOCITY_DATA_PER_USTEP_S,
    Alert,
    ChecksumMismatch,
    Command,
    Event,
    Info,
    ProtocolViolation,
    RejectReason,
    Reply,
    WarningFlag,
    ZaberReceiver,
    encode_command,
)

log = logging.getLogger(__name__)
INFO_SETTINGS = ("deviceid", "system.serial", "version", "system.axiscount", "comm.word.size.max")


def _code(enum_type: type, value: str) -> object:
    try:
        return enum_type[value] if enum_type is WarningFlag else enum_type(value)
    except (KeyError, ValueError):
        return value


class ZaberDevice(MotionController[Event]):
    def __init__(
        self,
        url: str,
        *,
        device: str = "zaber",
        address: int = 1,
        baudrate: int = 115200,
        timeout_s: float = 1.0,
        clock: Clock = SYSTEM_CLOCK,
        retries: int = 2,
        poll_interval_s: float = 0.05,
        homing_timeout_s: float = 120.0,
        stall_window_s: float = STALL_WINDOW_S,
    ) -> None:
        if not 1 <= address <= 99:
            raise ValueError(f"Zaber device address must be 1..99, got {address}")
        super().__init__(
            url, device, baudrate, timeout_s, clock, retries, poll_interval_s, homing_timeout_s,
            ZaberReceiver(),
        )
        self.stall_window_s = stall_window_s
        self.address = address
        self._next_id = 0
        self._axes: dict[int, ZaberAxis] = {}
        self.info: dict[str, str] = {}
        self.last_warning = "--"

    # -- connection ------------------------------------------------------------------
    def connect(self) -> dict[str, str]:
        """Open the port and read what the device says about itself."""
        self.link.open()
        self.link.drain_input()
        self._forget()
        self.info = {}
        for name in INFO_SETTINGS:
            try:
                self.info[name] = self.get(name)
            except CommandRejected:
                if name in ("deviceid", "version"):
                    raise
                log.info("%s: device does not know %s", self.device, name)
        return self.info

    def reconnect(self, *, attempts: int = 10, interval_s: float = 0.5) -> Reply:
        """Reopen a vanished port; returns a status poll of the whole device."""
        self.link.reconnect(attempts=attempts, interval_s=interval_s)
        self._forget()
        reply = self.request(0, "", idempotent=True, check_faults=False)
        log.warning("%s: reconnected (%s, flag %s)", self.device, reply.status, reply.warning)
        return reply

    # -- axes ------------------------------------------------------------------------
    def axis(self, number: int, **spec: Unpack[AxisSpec]) -> ZaberAxis:
        """An axis in degrees (``units_per_degree`` microsteps per degree).

        Needs a connected device: writes ``maxspeed``, ``accel``, ``limit.min`` and
        ``limit.max`` so the device itself enforces the speed and the soft limits
        (``move vel`` stops at them)."""
        if not 1 <= number <= 9:
            raise ValueError(f"Zaber axis number must be 1..9, got {number}")
        if number in self._axes:
            raise ValueError(f"axis {number} already belongs to {self._axes[number].name!r}")
        ax = ZaberAxis(self, number, **spec)
        ax.configure()
        self._axes[number] = ax
        return ax

    # -- commands --------------------------------------------------------------------
    def get(self, setting: str, axis: int = 0) -> str:
        return self.request(axis, f"get {setting}", idempotent=True).data

    def request(
        self,
        axis: int,
        text: str,
        *,
        idempotent: bool = False,
        timeout: float | None = None,
        check_faults: bool = True,
    ) -> Reply:
        """Send one command and return its matching reply."""
        if idempotent:
            return self._retry(
                repr(text), lambda attempt: self._request_once(axis, text, timeout, attempt, check_faults)
            )
        return self._request_once(axis, text, timeout, 1, check_faults)

    def home(self) -> Reply:
        """Home every axis of the device at once and wait until they are done."""
        self.request(0, "home")
        return self.wait_until_idle(0, self.homing_timeout_s)

    def clear_faults(self, axis: int = 0) -> list[str]:
        """``warnings clear``: returns the flags that were set (WR stays until homed)."""
        reply = self.request(axis, "warnings clear", check_faults=False)
        return reply.data.split()[1:]

    def wait_until_idle(self, axis: int, timeout: float) -> Reply:
        """Poll the empty command until IDLE (as zaber-motion does)."""
        deadline = self.clock.monotonic() + timeout
        while True:
            reply = self.request(axis, "", idempotent=True)
            if not reply.busy:
                return reply
            remaining = deadline - self.clock.monotonic()
            if remaining <= 0:
                raise DeviceTimeout(
                    f"axis {axis} still BUSY after {timeout:.3g} s",
                    device=self.device,
                    command="(status poll)",
                )
            self.clock.sleep(min(self.poll_interval_s, remaining))

    # -- exchanges -------------------------------------------------------------------
    def _take_id(self) -> int:
        mid = self._next_id
        self._next_id = (mid + 1) % (MAX_MESSAGE_ID + 1)
        return mid

    def _drain_stale(self, command: str) -> None:
        self._events.extend(self._rx.feed(self.link.read_available(command=command)))
        while self._events:
            log.info("%s: dropped stale %r", self.device, self._events.popleft())

    @one_at_a_time
    def _request_once(self, axis: int, text: str, timeout: float | None, attempt: int, check: bool) -> Reply:
        self._drain_stale(text)
        mid = self._take_id()
        data = encode_command(Command(self.address, axis, mid, text))
        shown = data.decode().strip()
        self.link.write(data, command=shown)
        deadline = self.clock.monotonic() + (self.timeout_s if timeout is None else timeout)
        while True:
            ev = self._next_event(deadline, shown, attempt)
            if isinstance(ev, ProtocolViolation):
                kind = "bad checksum" if isinstance(ev, ChecksumMismatch) else "garbled reply"
                raise ProtocolError(
                    f"{kind} {ev.line!r} ({ev.reason})", device=self.device, command=shown, attempt=attempt
                )
            if isinstance(ev, Alert | Info) or ev.address != self.address or ev.message_id != mid:
                log.info("%s: skipped %r while waiting for id %02d", self.device, ev, mid)
                continue
            self.last_warning = ev.warning
            if ev.rejected:
                raise CommandRejected(
                    f"rejected: {ev.data}",
                    code=_code(RejectReason, ev.data),
                    device=self.device,
                    command=shown,
                    attempt=attempt,
                )
            if check and ev.fault:
                flag = _code(WarningFlag, ev.warning)
                meaning = flag.value if isinstance(flag, WarningFlag) else "fault"
                raise StageAlarm(
                    f"fault {ev.warning} ({meaning}); clear_faults() after fixing the cause",
                    code=flag,
                    device=self.device,
                    command=shown,
                    attempt=attempt,
                )
            return ev


class ZaberAxis(RotaryAxisBase):
    """One rotary axis of a Zaber device, in degrees."""

    def __init__(
        self,
        dev: ZaberDevice,
        number: int,
        *,
        name: str,
        units_per_degree: float,
        min_deg: float,
        max_deg: float,
        max_speed_dps: float,
        accel_dps2: float,
        tolerance_deg: float,
        settle_s: float = 0.0,
        stall_window_s: float | None = None,
        timeout_margin: float = PLAN_MARGIN,
    ) -> None:
        super().__init__(
            dev, name, units_per_degree, min_deg, max_deg, max_speed_dps, accel_dps2, tolerance_deg, settle_s,
            stall_window_s, timeout_margin,
        )
        self.dev = dev
        self.number = number

    def _speed_data(self, dps: float) -> int:
        return max(1, round(dps * self.units_per_degree * VELOCITY_DATA_PER_USTEP_S))

    def configure(self) -> None:
        upd = self.units_per_degree
        accel = max(1, round(self.accel_dps2 * upd * ACCEL_DATA_PER_USTEP_S2))
        for setting, value in (
            ("maxspeed", self._speed_data(self.max_speed_dps)),
            ("accel", accel),
            ("limit.min", round(self.min_deg * upd)),
            ("limit.max", round(self.max_deg * upd)),
        ):
            self.dev.request(self.number, f"set {setting} {value}", check_faults=False)

    def home(self) -> None:
        self.dev.request(self.number, "home")
        self.dev.wait_until_idle(self.number, self.dev.homing_timeout_s)

    def _command_move(self, degrees: float) -> str:
        command = f"move abs {round(degrees * self.units_per_degree)}"
        self.dev.request(self.number, command)
        return command

    def _command_rotation(self, speed_dps: float, direction: int) -> None:
        """``move vel``; the device itself stops at the soft limits."""
        self.dev.request(self.number, f"move vel {direction * self._speed_data(speed_dps)}")

    def position(self) -> float:
        return self._degrees(self.dev.get("pos", self.number))

    def _degrees(self, data: str) -> float:
        try:
            return int(data) / self.units_per_degree
        except ValueError:
            raise ProtocolError(f"position {data!r} is not a number", device=self.dev.device) from None

    def _poll_pos(self, *, check_faults: bool = True) -> tuple[bool, float]:
        """``get pos``: (BUSY, position in degrees) from one reply."""
        reply = self.dev.request(self.number, "get pos", idempotent=True, check_faults=check_faults)
        return reply.busy, self._degrees(reply.data)

    def _motion_state(self) -> tuple[bool, float, str]:
        busy, degrees = self._poll_pos()  # a fault flag (FS stall, FQ encoder) raises StageAlarm
        return busy, degrees, "BUSY" if busy else "IDLE"

    def stop(self) -> None:
        """Decelerate to rest (always allowed, even with a fault flag set), waiting the
        braking time plus a margin, and longer while the position still changes."""
        self.dev.request(self.number, "stop", check_faults=False)
        watch = ProgressWatch(
            self.dev.clock, planned_s=braking_s(self.max_speed_dps, self.accel_dps2),
            slack_s=2.0 * self.dev.timeout_s, stall_window_s=self.stall_window_s,
            min_progress=1.0 / self.units_per_degree, margin=self.timeout_margin,  # one microstep
        )
        busy, degrees = self._poll_pos(check_faults=False)
        while busy:
            watch.update(degrees)
            if watch.stalled:
                raise DeviceTimeout(
                    f"{self.name}: did not stop: still BUSY at {degrees:.4f}° with no motion for "
                    f"{watch.stall_window_s:g} s", device=self.dev.device, command="stop",
                )
            self.dev.clock.sleep(self.dev.poll_interval_s)
            busy, degrees = self._poll_pos(check_faults=False)

    def is_moving(self) -> bool:
        return self.dev.request(self.number, "", idempotent=True).busy

    def motion(self) -> tuple[bool, float]:
        return self._poll_pos()

    def wait_until_idle(self, timeout: float) -> None:
        self.dev.wait_until_idle(self.number, timeout)


def open_zaber_axes(
    name: str, dev: Any, axes: Mapping[str, Any], clock: Clock
) -> tuple[ZaberDevice, dict[str, ZaberAxis]]:
    """Connect the Zaber device ``name`` of a rig configuration and make its axes.

    ``dev`` is a ``DeviceConfig`` (port, unit = device address, baudrate, timeout_s,
    retries) and ``axes`` maps roles to ``AxisConfig`` objects whose ``axis`` is the
    Zaber axis number; read by attribute, so drivers need not import the app.
    """
    zd = ZaberDevice(
        dev.port,
        device=name,
        address=dev.unit,
        baudrate=dev.baudrate,
        timeout_s=dev.timeout_s,
        clock=clock,
        retries=dev.retries,
    )
    try:
        zd.connect()
        made = {
            role: zd.axis(
                int(ax.axis),
                name=role,
                units_per_degree=ax.units_per_degree,
                min_deg=ax.min_deg,
                max_deg=ax.max_deg,
                max_speed_dps=ax.max_speed_dps,
                accel_dps2=ax.accel_dps2,
                tolerance_deg=ax.tolerance_deg,
                settle_s=ax.settle_s,
                stall_window_s=ax.stall_window_s,
                timeout_margin=ax.timeout_margin,
            )
            for role, ax in axes.items()
        }
    except BaseException:
        zd.close()
        raise
    return zd, made
