"""What the relay-board drivers (Modbus RTU, ASCII) have in common.

:func:`one_at_a_time` serialises a board's public calls. :class:`RelayBoardBase` holds
the settings checks, the channel checks, ``set`` verified by read-back
(:class:`RelayNotSwitched`), the retries of a transaction (the port reopened after it
vanished) and the timed read of the next bytes. A subclass provides the wire
transactions: writing the whole mask, reading the relays, switching one.

Every error leaving a board names it and has a fault class: an I/O error that escapes
the serial layer untyped (e.g. ``termios.error`` EIO from flushing a pseudo-terminal or
adapter that went away, a raw ``OSError``) is a :class:`DeviceGone` of this board,
retried after reopening the port like any vanished port.
"""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable
from typing import Self, TypeVar

import serial
from m2s2hil.drivers.clock import Clock
from m2s2hil.drivers.errors import DeviceError, DeviceGone, DeviceTimeout, ProtocolError, RelayNotSwitched
from m2s2hil.drivers.locking import one_at_a_time
from m2s2hil.drivers.serial_link import SerialLink
from m2s2hil.protocols.errors import CodecError

T = TypeVar("T")

try:  # POSIX serial ports flush and configure through termios, whose error is no OSError
    import termios

    _PORT_ERRORS: tuple[type[BaseException], ...] = (OSError, serial.SerialException, termios.error)
except ImportError:  # pragma: no cover - not POSIX
    _PORT_ERRORS = (OSError, serial.SerialException)


class RelayBoardBase(ABC):
    """A :class:`~m2s2hil.drivers.interfaces.LightBank` on a serial relay board.

    A subclass sets ``_link`` (its :class:`SerialLink`) after calling ``__init__``."""

    _link: SerialLink

    def __init__(
        self,
        device: str,
        channels: int,
        max_channels: int,
        *,
        retries: int,
        timeout_s: float,
        clock: Clock,
        reconnect_attempts: int,
        reconnect_interval_s: float,
    ) -> None:
        if not 1 <= channels <= max_channels:
            raise ValueError(f"{device}: channels {channels} outside 1..{max_channels}")
        if retries < 0:
            raise ValueError(f"{device}: retries must be >= 0, not {retries}")
        if not timeout_s > 0:
            raise ValueError(f"{device}: timeout_s must be > 0, not {timeout_s}")
        self.name = device
        self.channels = channels
        self.retries = retries
        self.clock = clock
        self.timeout_s = timeout_s
        self.reconnect_attempts = reconnect_attempts
        self.reconnect_interval_s = reconnect_interval_s
        self._lock = threading.RLock()
        self._needs_reconnect = False
        self._ever_opened = False  # a port that never opened is a wrong path, not a glitch

    # -- what a subclass provides -------------------------------------------------------
    @abstractmethod
    def _write_all(self, wanted: frozenset[int]) -> str:
        """Command exactly ``wanted`` on; returns the command's name for error reports."""

    @abstractmethod
    def state(self) -> frozenset[int]: ...

    @abstractmethod
    def connect(self) -> None: ...

    # -- connection -----------------------------------------------------------------------
    @one_at_a_time
    def close(self) -> None:
        self._link.close()

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- LightBank ------------------------------------------------------------------------
    @one_at_a_time
    def set(self, on_channels: Iterable[int]) -> None:
        """Switch exactly ``on_channels`` on, verified by read-back."""
        wanted = self._check_channels(on_channels)
        command = self._write_all(wanted)
        actual = self.state()
        if actual != wanted:
            raise RelayNotSwitched(
                f"read-back {sorted(actual)} differs from commanded {sorted(wanted)} "
                f"(stuck: {sorted(actual ^ wanted)})",
                device=self.name,
                command=command,
            )

    def all_off(self) -> None:
        self.set(())

    # -- internals --------------------------------------------------------------------------
    def _check_channels(self, channels: Iterable[int]) -> frozenset[int]:
        out = set()
        for ch in channels:
            if isinstance(ch, bool) or not isinstance(ch, int) or not 0 <= ch < self.channels:
                raise ValueError(f"{self.name}: channel {ch!r} outside 0..{self.channels - 1}")
            out.add(ch)
        return frozenset(out)

    def _retrying(self, once: Callable[[int], T]) -> T:
        """``once(attempt)``, tried again up to ``retries`` times after a timeout, garbage or a
        vanished port (reopened by the next :meth:`_open_line`). Anything else is final, e.g.
        CommandRejected: the board understood and refused, asking again changes nothing."""
        last: DeviceError | None = None
        for attempt in range(1, self.retries + 2):
            try:
                return once(attempt)
            except DeviceGone as exc:
                if not self._ever_opened:
                    raise
                self._needs_reconnect = True
                last = exc
            except (DeviceTimeout, ProtocolError) as exc:
                last = exc
            except _PORT_ERRORS as exc:  # untyped I/O trouble of the port itself
                gone = DeviceGone(f"I/O error on the port: {type(exc).__name__}: {exc}", device=self.name,
                                  attempt=attempt)
                if not self._ever_opened:
                    raise gone from exc
                self._needs_reconnect = True
                last = gone
        assert last is not None
        raise last

    def _open_line(self) -> None:
        """Open the port (reopen it after it vanished) and drop what is waiting on it:
        a late answer to an earlier command must not count."""
        if self._needs_reconnect:
            self._link.reconnect(attempts=self.reconnect_attempts, interval_s=self.reconnect_interval_s)
        elif not self._link.is_open:
            self._link.open()
        self._needs_reconnect = False
        self._ever_opened = True
        self._link.drain_input()

    def _read_some(self, deadline: float, command: str, attempt: int, missing: Callable[[], str]) -> bytes:
        """At least one byte before ``deadline`` and whatever else has arrived; if nothing
        comes, a DeviceTimeout whose message is ``missing()`` (what was still awaited)."""
        remaining = deadline - self.clock.monotonic()
        try:
            if remaining <= 0:
                raise DeviceTimeout("deadline passed", device=self.name)
            chunk = self._link.read_exact(1, timeout=remaining, command=command)
            return chunk + self._link.read_available(command=command)
        except DeviceTimeout as exc:
            raise DeviceTimeout(missing(), device=self.name, command=command, attempt=attempt) from exc

    def _decoded(self, next_event: Callable[[], T], command: str, attempt: int) -> T:
        """The decoder's next event; its CodecError as a ProtocolError."""
        try:
            return next_event()
        except CodecError as exc:
            raise ProtocolError(
                f"garbled answer: {exc}", device=self.name, command=command, attempt=attempt
            ) from exc
