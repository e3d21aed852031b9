"""What the rotary-axis drivers (GRBL, Zaber) have in common.

:class:`MotionController` is the serial side of a controller that answers in lines:
the link, the receiver's queue of decoded events read against a deadline, and the
retries of idempotent exchanges. :class:`RotaryAxisBase` is one axis in degrees: the
checks of its settings, the soft limits and the verified ``move_to`` (command, wait
for arrival, settle, read back, compare). The wait follows the move
(:mod:`m2s2hil.drivers.motion_watch`): planned from its trapezoid, extended while the
read-back progresses, a :class:`~m2s2hil.drivers.errors.MoveStalled` when it does not. A
subclass says how to command a move or a rotation, how to read the position and the
motion state, and how to wait.
"""

from __future__ import annotations

import logging
import threading
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable
from typing import Generic, NotRequired, Protocol, TypedDict, TypeVar

from m2s2hil.drivers.clock import Clock
from m2s2hil.drivers.errors import DeviceTimeout, MoveNotVerified, MoveStalled, ProtocolError, SoftLimitError
from m2s2hil.drivers.motion_watch import PLAN_MARGIN, STALL_WINDOW_S, ProgressWatch, trapezoid_s
from m2s2hil.drivers.serial_link import SerialLink

#: How long after a move's planned end the first poll for its arrival goes out (clock rounding).
ARRIVAL_MARGIN_S = 0.001

T = TypeVar("T")
E = TypeVar("E")


class AxisSpec(TypedDict):
    """The keywords an axis is made with, after its controller and its address."""

    name: str
    units_per_degree: float
    min_deg: float
    max_deg: float
    max_speed_dps: float
    accel_dps2: float
    tolerance_deg: float
    settle_s: NotRequired[float]
    stall_window_s: NotRequired[float | None]
    timeout_margin: NotRequired[float]


class _Receiver(Protocol[E]):
    def feed(self, data: bytes) -> list[E]: ...

    def clear(self) -> None: ...


class MotionController(Generic[E]):
    """A motion controller on a serial line whose replies are lines decoded by ``receiver``."""

    def __init__(
        self,
        url: str,
        device: str,
        baudrate: int,
        timeout_s: float,
        clock: Clock,
        retries: int,
        poll_interval_s: float,
        homing_timeout_s: float,
        receiver: _Receiver[E],
    ) -> None:
        self.device = device
        self.clock = clock
        self.timeout_s = timeout_s
        self.retries = retries
        self.poll_interval_s = poll_interval_s
        self.homing_timeout_s = homing_timeout_s
        self.link = SerialLink(url, device=device, baudrate=baudrate, timeout_s=timeout_s, clock=clock)
        self._rx = receiver
        self._events: deque[E] = deque()
        self._lock = threading.RLock()  # one transaction at a time (see drivers.locking)
        #: No progress of a motion for this long (s) is a stall (drivers.motion_watch).
        self.stall_window_s = STALL_WINDOW_S

    def close(self) -> None:
        self.link.close()

    def _forget(self) -> None:
        """Drop a partial line and the events not yet taken."""
        self._rx.clear()
        self._events.clear()

    def _retry(self, what: str, once: Callable[[int], T]) -> T:
        """``once(attempt)`` again after a timeout or a garbled reply, ``retries`` times at most."""
        attempt = 1
        while True:
            try:
                return once(attempt)
            except (DeviceTimeout, ProtocolError) as exc:
                if attempt > self.retries:
                    raise
                # Under the concrete driver's logger, so its logging configuration applies.
                logging.getLogger(type(self).__module__).warning(
                    "%s: %s; retrying %s", self.device, exc, what
                )
                attempt += 1

    def _next_event(self, deadline: float, command: str, attempt: int) -> E:
        while not self._events:
            remaining = deadline - self.clock.monotonic()
            try:
                if remaining <= 0:
                    raise DeviceTimeout("no reply", device=self.device, command=command)
                line = self.link.read_until(b"\n", timeout=remaining, command=command)
            except DeviceTimeout as exc:
                # Whatever partial line is buffered is garbage now: drop it.
                self.link.drain_input()
                self._rx.clear()
                raise DeviceTimeout(
                    exc.detail, device=self.device, command=command, attempt=attempt
                ) from None
            self._events.extend(self._rx.feed(line))
        return self._events.popleft()


class RotaryAxisBase(ABC):
    """One rotary axis in degrees (a ``RotaryAxis``) on a :class:`MotionController`."""

    def __init__(
        self,
        owner: MotionController,
        name: str,
        units_per_degree: float,
        min_deg: float,
        max_deg: float,
        max_speed_dps: float,
        accel_dps2: float,
        tolerance_deg: float,
        settle_s: float,
        stall_window_s: float | None = None,
        timeout_margin: float = PLAN_MARGIN,
    ) -> None:
        if units_per_degree <= 0 or max_speed_dps <= 0 or accel_dps2 <= 0 or tolerance_deg <= 0:
            raise ValueError(f"{name}: units, speed, acceleration and tolerance must be positive")
        if not min_deg < max_deg:
            raise ValueError(f"{name}: min_deg {min_deg} must be below max_deg {max_deg}")
        self._owner = owner
        self.name = name
        self.units_per_degree = units_per_degree
        self.min_deg, self.max_deg = min_deg, max_deg
        self.max_speed_dps, self.accel_dps2 = max_speed_dps, accel_dps2
        self.tolerance_deg = tolerance_deg
        self.settle_s = settle_s
        #: No progress of this axis's motion for this long (s) is a stall; the controller's by default.
        self.stall_window_s = owner.stall_window_s if stall_window_s is None else stall_window_s
        #: A move is overdue (logged) after its planned duration x this, plus the reply slack.
        self.timeout_margin = timeout_margin

    # -- what a subclass provides ------------------------------------------------------
    @abstractmethod
    def _command_move(self, degrees: float) -> str:
        """Start the move to ``degrees`` (within the limits); returns the command sent."""

    @abstractmethod
    def _command_rotation(self, speed_dps: float, direction: int) -> None:
        """Start a continuous rotation (speed and direction already checked)."""

    @abstractmethod
    def position(self) -> float: ...

    @abstractmethod
    def wait_until_idle(self, timeout: float) -> None: ...

    @abstractmethod
    def _motion_state(self) -> tuple[bool, float, str]:
        """One poll of the controller: (still moving or held, position in degrees, its state
        as the controller names it); a typed error when it reports a fault."""

    @abstractmethod
    def home(self) -> None: ...

    @abstractmethod
    def stop(self) -> None: ...

    @abstractmethod
    def is_moving(self) -> bool: ...

    @abstractmethod
    def motion(self) -> tuple[bool, float]:
        """(moving, position in degrees) from one poll, as :meth:`is_moving` and
        :meth:`position` judge them: a view built from two polls can pair a mid-move position
        with "standing" when the move ends between them."""

    def _speed_limits(self) -> tuple[float, float]:
        """Top speed (°/s) and acceleration (°/s²) a move may use."""
        return self.max_speed_dps, self.accel_dps2

    # -- shared ------------------------------------------------------------------------
    def _check(self, degrees: float) -> None:
        if not (self.min_deg <= degrees <= self.max_deg):
            raise SoftLimitError(
                f"{self.name}: target {degrees:g}° outside [{self.min_deg:g}, {self.max_deg:g}]°",
                device=self._owner.device,
            )

    def _watch(self, start: float, target: float) -> ProgressWatch:
        v, a = self._speed_limits()
        return ProgressWatch(
            self._owner.clock, planned_s=trapezoid_s(target - start, v, a),
            slack_s=2.0 * self._owner.timeout_s, stall_window_s=self.stall_window_s,
            min_progress=self.tolerance_deg / 10, target=target, margin=self.timeout_margin,
        )

    def _await_arrival(self, start: float, target: float, command: str, since: float | None = None) -> None:
        """Poll until the controller says the axis stands; MoveStalled when it stops progressing
        towards ``target`` for the stall window while still said to move (it is stopped first).

        The polls are timed to the planned arrival (the trapezoid from ``start``, commanded at
        ``since``, by default now): one lands just after it, then a few at a fifth of the
        interval, so a move's end is seen within milliseconds rather than up to a whole
        ``poll_interval_s`` late (at 50 ms, ~25 ms lost per move on average)."""
        watch = self._watch(start, target)
        owner, overdue_logged = self._owner, False
        arrive = (owner.clock.monotonic() if since is None else since) + watch.planned_s + ARRIVAL_MARGIN_S
        while True:
            moving, position, state = self._motion_state()
            if not moving:
                return
            watch.update(position)
            if watch.stalled:
                self._stop_quietly()
                raise MoveStalled(
                    f"{self.name}: stalled at {position:.4f}° ({state}) on the way from {start:.4f}° to "
                    f"{target:.4f}°: no progress for {watch.stall_window_s:g} s",
                    axis=self.name, start=start, target=target, actual=position,
                    device=owner.device, command=command,
                )
            if watch.overdue and not overdue_logged:
                overdue_logged = True
                logging.getLogger(type(self).__module__).warning(
                    "%s: move to %.4f° longer than planned (%.3g s), still progressing at %.4f°: waiting",
                    self.name, target, watch.planned_s, position,
                )
            left = arrive - owner.clock.monotonic()
            if left > 0:
                owner.clock.sleep(min(owner.poll_interval_s, left))
            elif left > -2 * owner.poll_interval_s:
                owner.clock.sleep(owner.poll_interval_s / 5)
            else:
                owner.clock.sleep(owner.poll_interval_s)

    def _stop_quietly(self) -> None:
        """Stop a stalled axis before reporting it; the stall is the error worth raising."""
        try:
            self.stop()
        except Exception as exc:  # the MoveStalled that follows says what matters
            log = logging.getLogger(type(self).__module__)
            log.error("%s: stopping after a stall failed: %s", self.name, exc)

    def move_to(self, degrees: float, *, wait: bool = True) -> float:
        self._check(degrees)
        start = self.position() if wait else None
        command = self._command_move(degrees)
        if not wait:
            return degrees
        assert start is not None
        return self.finish_move(start, degrees, command)

    def finish_move(self, start: float, degrees: float, command: str = "",
                    since: float | None = None) -> float:
        """The second half of ``move_to(degrees)`` after a ``move_to(degrees, wait=False)``
        from ``start`` (commanded at clock time ``since``): wait for it as ``move_to`` waits
        (MoveStalled) and verify the read-back (MoveNotVerified), without commanding it again
        (a move that ended short must not be hidden by a second one)."""
        self._await_arrival(start, degrees, command or f"move to {degrees:g}", since)
        if self.settle_s:
            self._owner.clock.sleep(self.settle_s)
        actual = self.position()
        if abs(actual - degrees) > self.tolerance_deg:
            raise MoveNotVerified(
                f"{self.name}: at {actual:.4f}° after a move to {degrees:.4f}° "
                f"(tolerance {self.tolerance_deg:g}°)",
                target=degrees,
                actual=actual,
                device=self._owner.device,
                command=command,
            )
        return actual

    def rotate(self, speed_dps: float, direction: int = +1) -> None:
        """Continuous rotation at ``speed_dps`` towards ``direction`` (+1/-1) until stop();
        the soft limits still end it."""
        if direction not in (1, -1):
            raise ValueError(f"direction must be +1 or -1, got {direction}")
        if not 0 < speed_dps <= self.max_speed_dps:
            raise SoftLimitError(
                f"{self.name}: speed {speed_dps:g}°/s outside (0, {self.max_speed_dps:g}]°/s",
                device=self._owner.device,
            )
        self._command_rotation(speed_dps, direction)

    def close(self) -> None:
        """Closes the shared controller (idempotent: every axis may call it)."""
        self._owner.close()
