"""Driver for a GRBL 1.1 controller carrying rotary axes (turntable, tilt stage).

One :class:`GrblController` owns the serial port; :meth:`GrblController.axis` hands
out :class:`GrblAxis` objects (``RotaryAxis``) that share it. Lines are sent one at a
time and each waits for its ``ok``/``error``; a :class:`CharacterCounter` still keeps
the books, so a reply that arrives late after a timeout retires the right line instead
of being mistaken for the next one (GRBL replies carry no ids, only their order).

Error mapping (every error names device, command and attempt):
``error:N`` → CommandRejected(code=GrblError); ``ALARM:N`` → StageAlarm(code=GrblAlarm);
no reply in time → DeviceTimeout; a garbled or unexpected reply → ProtocolError;
the port vanished → DeviceGone (then :meth:`GrblController.reconnect`).
Idempotent queries (``?``, ``$I``, ``$$``, soft reset) are retried ``retries`` times
after a timeout or a garbled reply; motion commands never are.

After ``ALARM:1``/``ALARM:2`` GRBL ignores everything but a soft reset, so the driver
refuses commands with StageAlarm until :meth:`GrblController.clear_alarm`.

Waits on motion follow the motion (:mod:`m2s2hil.drivers.motion_watch`): a move's from
its trapezoid at the axis's speed and acceleration, lowered to ``$110+``/``$120+`` (units/min,
units/s², [GRBL wiki "Grbl v1.1 Configuration"]); a stop's from the braking time. Both are
extended while the ``?`` report's position still changes. Stopping a G-code move is a feed
hold (``!``) until ``Hold:0`` ("Hold complete. Ready to resume"; ``Hold:1`` is "Hold
in-progress. Reset will throw an alarm" [GRBL wiki "Grbl v1.1 Interface", status report]);
a hold that stops progressing without completing is escalated, once, to a soft reset
(0x18, "immediately halts and safely resets Grbl" [wiki "Grbl v1.1 Commands"]) and the
state is read again: ALARM:3 ("Reset while in motion ... re-homing is highly recommended"
[wiki "Grbl v1.1 Alarm codes"]) leaves the controller locked, and the rig's recovery
clears it as the axis's homing policy says (``$X`` for an axis without switches, never ``$H``).
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Unpack

from m2s2hil.drivers.axis_base import AxisSpec, MotionController, RotaryAxisBase
from m2s2hil.drivers.clock import SYSTEM_CLOCK, Clock
from m2s2hil.drivers.errors import (
    CommandRejected,
    ControllerLocked,
    DeviceGone,
    DeviceTimeout,
    ProtocolError,
    StageAlarm,
)
from m2s2hil.drivers.locking import one_at_a_time
from m2s2hil.drivers.motion_watch import PLAN_MARGIN, STALL_WINDOW_S, ProgressWatch, braking_s
from m2s2hil.protocols.grbl import (
    AXES,
    BUILD_INFO,
    CRITICAL_ALARMS,
    HOME,
    SETTINGS,
    UNLOCK,
    Alarm,
    Banner,
    BuildInfo,
    BuildOptions,
    CharacterCounter,
    Error,
    Event,
    GrblAlarm,
    GrblError,
    GrblReceiver,
    Message,
    Ok,
    ProtocolViolation,
    Realtime,
    Setting,
    StatusReport,
    encode_line,
    jog_line,
    move_line,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReconnectReport:
    reset: bool  # the controller restarted (lost power): position lost, home again
    status: StatusReport


def _name(code: object) -> str:
    return getattr(code, "name", "unknown")


def _held_or_idle(st: StatusReport) -> bool:
    return st.state == "Idle" or (st.state == "Hold" and st.substate == 0)


class GrblController(MotionController[Event]):
    def __init__(
        self,
        url: str,
        *,
        device: str = "stage",
        baudrate: int = 115200,
        timeout_s: float = 1.0,
        clock: Clock = SYSTEM_CLOCK,
        retries: int = 2,
        poll_interval_s: float = 0.05,
        homing_timeout_s: float = 120.0,
        stall_window_s: float = STALL_WINDOW_S,
    ) -> None:
        super().__init__(
            url, device, baudrate, timeout_s, clock, retries, poll_interval_s, homing_timeout_s,
            GrblReceiver(),
        )
        self.stall_window_s = stall_window_s
        self._counter = CharacterCounter()
        self._axes: dict[str, GrblAxis] = {}
        self._wco: tuple[float, ...] | None = None
        self.settings: dict[int, float] = {}
        self.version: str | None = None
        self.critical = False  # halted after a hard/soft limit until a soft reset
        self.last_alarm: GrblAlarm | int | None = None
        self.restarts = 0  # banners seen that the driver did not ask for
        self.messages: deque[str] = deque(maxlen=50)

    # -- connection ------------------------------------------------------------------
    def connect(self, *, reset: bool = True) -> StatusReport:
        """Open the port, soft-reset (or just wake with an empty line), check the
        firmware is GRBL 1.1 and read its settings."""
        self.link.open()
        self._forget()
        if reset:
            self.soft_reset()
        else:
            self.command("", idempotent=True)  # an empty line is answered "ok"
        info = self.command(BUILD_INFO, idempotent=True)
        ver = next((e for e in info if isinstance(e, BuildInfo)), None)
        if ver is None or not ver.version.startswith("1.1"):
            found = ver.version if ver else "no [VER:] line"
            raise ProtocolError(f"not GRBL 1.1 (found {found})", device=self.device, command=BUILD_INFO)
        self.version = ver.version
        opt = next((e for e in info if isinstance(e, BuildOptions)), None)
        if opt is not None and opt.rx_buffer:
            self._counter = CharacterCounter(opt.rx_buffer - 1)
        self.read_settings()
        return self.status()

    def reconnect(self, *, attempts: int = 10, interval_s: float = 0.5) -> ReconnectReport:
        """Reopen a vanished port and re-synchronise; says whether the controller restarted."""
        self.link.reconnect(attempts=attempts, interval_s=interval_s)
        self._forget()
        before = self.restarts
        status = self.status()
        report = ReconnectReport(reset=self.restarts > before, status=status)
        log.warning(
            "%s: reconnected (%s)", self.device, "controller restarted" if report.reset else "no reset"
        )
        return report

    def _forget(self) -> None:
        super()._forget()
        self._counter.reset()

    # -- axes ------------------------------------------------------------------------
    def axis(self, letter: str, **spec: Unpack[AxisSpec]) -> GrblAxis:
        letter = letter.upper()
        if letter not in AXES:
            raise ValueError(f"GRBL axis must be one of {', '.join(AXES)}, got {letter!r}")
        if letter in self._axes:
            raise ValueError(f"axis {letter} already belongs to {self._axes[letter].name!r}")
        ax = GrblAxis(self, letter, **spec)
        self._axes[letter] = ax
        return ax

    # -- commands --------------------------------------------------------------------
    def command(self, text: str, *, idempotent: bool = False, timeout: float | None = None) -> list[Event]:
        """Send one line and wait for its ok; returns the lines that came before it."""
        data = encode_line(text)
        if idempotent:
            return self._retry(text, lambda attempt: self._command_once(data, text, timeout, attempt))
        return self._command_once(data, text, timeout, 1)

    def status(self) -> StatusReport:
        return self._retry("?", self._status_once)

    def read_settings(self) -> dict[int, float]:
        events = self.command(SETTINGS, idempotent=True)
        self.settings = {e.number: e.value for e in events if isinstance(e, Setting)}
        return self.settings

    def soft_reset(self) -> Banner:
        """0x18: stops everything, flushes GRBL's buffers; ALARM:3 if it was moving."""
        return self._retry("soft reset", self._reset_once)

    def home(self) -> StatusReport:
        """``$H``: homes every axis that has a switch (GRBL homes them all in one cycle)."""
        self.command(HOME, timeout=self.homing_timeout_s)
        return self.status()

    def unlock(self) -> None:
        self.command(UNLOCK)

    def clear_alarm(self, *, home: bool = False) -> StatusReport:
        """Soft reset, then ``$H`` (position re-established) or ``$X`` (trust it)."""
        self.soft_reset()
        if home:
            return self.home()
        self.unlock()
        return self.status()

    def realtime(self, byte: bytes) -> None:
        self.link.write(byte, command=f"realtime {byte!r}")

    def wait_until_idle(self, timeout: float) -> StatusReport:
        """Poll ``?`` through the clock until Idle; StageAlarm on Alarm, DeviceTimeout if late."""
        deadline = self.clock.monotonic() + timeout
        while True:
            st = self.status()
            if st.state == "Idle":
                return st
            if st.state == "Alarm":
                raise StageAlarm(
                    "controller in Alarm state", code=self.last_alarm, device=self.device, command="?"
                )
            remaining = deadline - self.clock.monotonic()
            if remaining <= 0:
                raise DeviceTimeout(
                    f"still {st.state_text} after {timeout:.3g} s", device=self.device, command="?"
                )
            self.clock.sleep(min(self.poll_interval_s, remaining))

    def stop(self) -> StatusReport | None:
        """Stop all motion without losing position, waiting as long as it still decelerates.

        A jog is cancelled (0x85, decelerates and flushes the jog); a G-code move is
        feed-held (``!``) and once it stands (Hold:0) a soft reset flushes the rest of
        the planner (no alarm, position kept); homing can only be reset (ALARM:6).
        A hold or jog cancel that stops progressing unfinished is escalated to a soft
        reset, once (:meth:`_escalate`). A controller halted by a limit alarm is already
        stopped: returns None.
        """
        if self.critical:
            return None
        st = self.status()
        if st.state == "Jog":
            self.realtime(Realtime.JOG_CANCEL)
            done = self._await_rest(st, lambda s: s.state == "Idle", "jog cancel (0x85)")
            return done if done is not None else self._escalate("jog cancel (0x85)")
        if st.state in ("Run", "Hold"):
            self.realtime(Realtime.FEED_HOLD)
            held = self._await_rest(st, _held_or_idle, "!")
            if held is None:
                return self._escalate("feed hold (!)")
            self.soft_reset()
        elif st.state == "Home":
            self.soft_reset()
        return self.status()

    def _await_rest(
        self, st: StatusReport, done: Callable[[StatusReport], bool], what: str
    ) -> StatusReport | None:
        """Poll until ``done``: the braking time plus a margin, extended while the position
        still changes; None when it stopped changing for the stall window unfinished."""
        watch = ProgressWatch(
            self.clock, planned_s=self._braking_s(st), slack_s=2.0 * self.timeout_s,
            stall_window_s=self.stall_window_s, min_progress=1e-3,  # GRBL reports 3 decimals
        )
        while not done(st):
            pos = st.machine_position(self._wco)
            if pos is not None:
                watch.update(sum(abs(p) for p in pos))
            if watch.stalled:
                log.warning(
                    "%s: %s not complete after %.3g s: still %s, no motion for %g s",
                    self.device, what, watch.elapsed, st.state_text, self.stall_window_s,
                )
                return None
            self.clock.sleep(self.poll_interval_s)
            st = self.status()
        return st

    def _escalate(self, what: str) -> StatusReport:
        """A stop that did not complete: soft reset (0x18) once, then read the state again."""
        log.warning("%s: %s did not complete; soft reset (0x18) to stop the motion", self.device, what)
        self.soft_reset()
        st = self.status()
        if st.moving:
            raise DeviceTimeout(
                f"still {st.state_text} after a {what} and a soft reset", device=self.device, command="0x18"
            )
        if st.state == "Alarm":
            log.warning(
                "%s: stopped by the reset, now in Alarm (ALARM:%s: position not guaranteed); the alarm is "
                "cleared as the axes' homing policy says ($X without switches, $H with)",
                self.device, int(self.last_alarm) if self.last_alarm is not None else "?",
            )
        return st

    def _braking_s(self, st: StatusReport) -> float:
        """Deceleration time from the reported feed (or the top rate) at the lowest ``$12x``."""
        accels = [self.settings[120 + i] for i in range(len(AXES)) if self.settings.get(120 + i, 0) > 0]
        if not accels:
            return 0.0
        rates = [self.settings.get(110 + i, 0.0) for i in range(len(AXES))]
        feed = st.feed if st.feed else max(rates)
        return braking_s(feed / 60.0, min(accels))

    def position_in(self, st: StatusReport, letter: str) -> float:
        """The machine position of axis ``letter`` in a status report."""
        pos = st.machine_position(self._wco)
        if pos is None:
            raise ProtocolError("status report without a usable position", device=self.device, command="?")
        return pos[AXES.index(letter)]

    def axis_position(self, letter: str) -> float:
        return self.position_in(self.status(), letter)

    # -- exchanges -------------------------------------------------------------------
    def _check_critical(self, command: str) -> None:
        if self.critical:
            raise StageAlarm(
                f"controller halted after ALARM:{int(self.last_alarm or 0)} ({_name(self.last_alarm)}); "
                "it ignores everything until a soft reset: call clear_alarm()",
                code=self.last_alarm,
                device=self.device,
                command=command,
            )

    def _drain_pending(self, command: str) -> None:
        """Deal with whatever arrived unasked (late replies, alarms, a restart)."""
        self._events.extend(self._rx.feed(self.link.read_available(command=command)))
        while self._events:
            self._handle_async(self._events.popleft(), command, 1)

    def _handle_async(self, ev: Event, command: str, attempt: int) -> None:
        if isinstance(ev, Ok | Error):
            if self._counter.in_flight:
                self._counter.acknowledged()  # the late reply of a line given up on
        elif isinstance(ev, Alarm):
            self._on_alarm(ev, command, attempt)
        elif isinstance(ev, Banner):
            self.restarts += 1
            self._counter.reset()
            self.critical = False
            log.warning("%s: controller restarted (banner Grbl %s)", self.device, ev.version)
        elif isinstance(ev, Message):
            self.messages.append(ev.text)
        elif isinstance(ev, ProtocolViolation):
            log.warning("%s: discarded garbage %r (%s)", self.device, ev.line, ev.reason)
        elif isinstance(ev, StatusReport) and ev.wco is not None:
            self._wco = ev.wco

    def _on_alarm(self, ev: Alarm, command: str, attempt: int) -> None:
        self.last_alarm = ev.code
        self._counter.reset()  # GRBL answers none of the lines it still held
        if ev.code in CRITICAL_ALARMS:
            self.critical = True
        raise StageAlarm(
            f"ALARM:{int(ev.code)} ({_name(ev.code)})",
            code=ev.code,
            device=self.device,
            command=command,
            attempt=attempt,
        )

    def _settle(self, command: str) -> None:
        """Wait for replies still owed to lines given up on; declare them lost after a timeout."""
        deadline = self.clock.monotonic() + self.timeout_s
        while self._counter.in_flight:
            try:
                ev = self._next_event(deadline, command, 1)
            except DeviceTimeout:
                log.warning("%s: %d reply(ies) never came", self.device, self._counter.in_flight)
                self._counter.reset()
                return
            if isinstance(ev, ProtocolViolation):
                self._counter.acknowledged()
            else:
                self._handle_async(ev, command, 1)

    def _quiesce(self, command: str) -> None:
        """Discard input until the line has been quiet for a moment, then forget all debts."""
        quiet = min(0.1, self.timeout_s / 4)
        end = self.clock.monotonic() + self.timeout_s
        while self.clock.monotonic() < end:
            try:
                self.link.read_until(b"\n", timeout=quiet, command=command)
            except DeviceTimeout:
                break
        self.link.drain_input()
        self._forget()

    @one_at_a_time
    def _command_once(self, data: bytes, text: str, timeout: float | None, attempt: int) -> list[Event]:
        self._check_critical(text)
        self._drain_pending(text)
        if self._counter.in_flight:
            self._settle(text)
        self._counter.sent(data)
        try:
            self.link.write(data, command=text)
        except DeviceGone:
            self._counter.reset()
            raise
        deadline = self.clock.monotonic() + (self.timeout_s if timeout is None else timeout)
        collected: list[Event] = []
        while True:
            ev = self._next_event(deadline, text, attempt)
            if isinstance(ev, Ok):
                self._counter.acknowledged()
                return collected
            if isinstance(ev, Error):
                self._counter.acknowledged()
                rejected = ControllerLocked if int(ev.code) == int(GrblError.LOCKED) else CommandRejected
                raise rejected(
                    f"error:{int(ev.code)} ({_name(ev.code)})",
                    code=ev.code,
                    device=self.device,
                    command=text,
                    attempt=attempt,
                )
            if isinstance(ev, ProtocolViolation):
                # Was it our ok, or one line of a longer answer? Unknowable: let the
                # rest of the answer pass, then start afresh.
                self._quiesce(text)
                raise ProtocolError(
                    f"garbled reply {ev.line!r} ({ev.reason})",
                    device=self.device,
                    command=text,
                    attempt=attempt,
                )
            if isinstance(ev, Banner):
                self._handle_async(ev, text, attempt)
                raise ProtocolError(
                    "controller restarted before answering", device=self.device, command=text, attempt=attempt
                )
            if isinstance(ev, Alarm):
                self._on_alarm(ev, text, attempt)
            if isinstance(ev, StatusReport):
                continue  # the late answer to an earlier '?'
            if isinstance(ev, Message):
                self.messages.append(ev.text)
            collected.append(ev)

    @one_at_a_time
    def _status_once(self, attempt: int) -> StatusReport:
        self._check_critical("?")
        self._drain_pending("?")
        self.link.write(Realtime.STATUS, command="?")
        deadline = self.clock.monotonic() + self.timeout_s
        while True:
            ev = self._next_event(deadline, "?", attempt)
            if isinstance(ev, StatusReport):
                if ev.wco is not None:
                    self._wco = ev.wco
                return ev
            if isinstance(ev, ProtocolViolation):
                raise ProtocolError(
                    f"garbled status {ev.line!r} ({ev.reason})",
                    device=self.device,
                    command="?",
                    attempt=attempt,
                )
            self._handle_async(ev, "?", attempt)

    @one_at_a_time
    def _reset_once(self, attempt: int) -> Banner:
        self.link.drain_input()
        self._forget()
        self.link.write(Realtime.SOFT_RESET, command="soft reset")
        self.critical = False
        deadline = self.clock.monotonic() + self.timeout_s
        while True:
            ev = self._next_event(deadline, "soft reset", attempt)
            if isinstance(ev, Banner):
                self._drain_pending("soft reset")  # the unlock message usually follows
                return ev
            if isinstance(ev, Alarm):
                self.last_alarm = ev.code  # ALARM:3/6: it was moving when reset
                log.warning("%s: reset while moving: ALARM:%d", self.device, int(ev.code))


class GrblAxis(RotaryAxisBase):
    """One rotary axis of a GRBL controller, in degrees (``units_per_degree`` machine
    units per degree). Moves use machine coordinates (G53), so work offsets never
    shift the angle."""

    def __init__(
        self,
        controller: GrblController,
        letter: str,
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
            controller, name, units_per_degree, min_deg, max_deg, max_speed_dps, accel_dps2, tolerance_deg,
            settle_s, stall_window_s, timeout_margin,
        )
        self.ctl = controller
        self.letter = letter
        #: Machine units of the axis's zero: the G54 offset an operator set with ``G10 L20`` on an
        #: axis without switches (m2s2hil/rig/origin.py); 0 for a homed axis.
        self.origin_units = 0.0

    def _feed(self, dps: float) -> float:
        return dps * self.units_per_degree * 60.0

    def _speed_limits(self) -> tuple[float, float]:
        """The configured limits, lowered to the firmware's ($110+, $120+) once read."""
        i = AXES.index(self.letter)
        v = self.max_speed_dps
        a = self.accel_dps2
        if self.ctl.settings:
            v = min(v, self.ctl.settings.get(110 + i, v * 60) / 60.0 / self.units_per_degree)
            a = min(a, self.ctl.settings.get(120 + i, a) / self.units_per_degree)
        return v, a

    def home(self) -> None:
        self.ctl.home()

    def _command_move(self, degrees: float) -> str:
        line = move_line(
            {self.letter: degrees * self.units_per_degree + self.origin_units},
            feed=self._feed(self.max_speed_dps), machine=True,
        )
        self.ctl.command(line)
        return line

    def _command_rotation(self, speed_dps: float, direction: int) -> None:
        """A jog towards the soft limit on that side; stop() ends it."""
        target = self.max_deg if direction > 0 else self.min_deg
        line = jog_line(
            {self.letter: target * self.units_per_degree + self.origin_units}, feed=self._feed(speed_dps),
            machine=True,
        )
        self.ctl.command(line)

    def position(self) -> float:
        return self._degrees_in(self.ctl.status())

    def stop(self) -> None:
        self.ctl.stop()

    def is_moving(self) -> bool:
        return self.ctl.status().moving

    def motion(self) -> tuple[bool, float]:
        st = self.ctl.status()
        return st.moving, self._degrees_in(st)

    def _degrees_in(self, st: StatusReport) -> float:
        """This axis's position in a status report, in degrees from its origin."""
        return (self.ctl.position_in(st, self.letter) - self.origin_units) / self.units_per_degree

    def _motion_state(self) -> tuple[bool, float, str]:
        """One ``?``: anything but Idle is still on its way (Hold:0 too, and it makes no progress)."""
        st = self.ctl.status()
        if st.state == "Alarm":
            raise StageAlarm(
                f"{self.name}: controller in Alarm state during a move", code=self.ctl.last_alarm,
                device=self.ctl.device, command="?",
            )
        degrees = self._degrees_in(st)
        return st.state != "Idle", degrees, st.state_text

    def wait_until_idle(self, timeout: float) -> None:
        self.ctl.wait_until_idle(timeout)


# Codes worth importing together with the driver.
__all__ = ["GrblAlarm", "GrblAxis", "GrblController", "GrblError", "ReconnectReport"]
