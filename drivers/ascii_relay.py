"""The relay board on a Numato-style ASCII command line (``relay on 0``, ``relay readall``).

Serial I/O goes through :class:`SerialLink` (timeouts on the injected clock, typed
errors) and the text through the sans-I/O codec in ``m2s2hil.protocols.ascii_relay``.
A transaction writes one command line and reads until the prompt; the echo must
repeat the command (a garbled line or a half-typed line left on the board shows up
here). Timeouts, garbage and a vanished port are retried up to ``retries`` more times,
reopening the port first when it vanished. The board never says "error": it ignores
a line it does not understand, so a missing answer is a :class:`ProtocolError`.

``set`` writes the whole mask with ``relay writeall`` and reads it back with
``relay readall``; a difference is :class:`RelayNotSwitched`.
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable, Iterable
from typing import Any, TypeVar

from m2s2hil.drivers.clock import SYSTEM_CLOCK, Clock
from m2s2hil.drivers.errors import (
    DeviceError,
    DeviceGone,
    DeviceTimeout,
    ProtocolError,
    RelayNotSwitched,
)
from m2s2hil.drivers.serial_link import SerialLink
from m2s2hil.protocols.ascii_relay import (
    MAX_CHANNELS,
    NEED_DATA,
    Answer,
    Command,
    Echo,
    EmptyLine,
    Prompt,
    ReadAll,
    RelayOff,
    RelayOn,
    RelayRead,
    ReplyParser,
    Version,
    WriteAll,
    encode,
    parse_mask,
)
from m2s2hil.protocols.errors import CodecError

_F = TypeVar("_F", bound=Callable[..., Any])


def _one_at_a_time(method: _F) -> _F:
    """Serialise public calls: a write and its read-back must not interleave with another
    thread's transaction on the same line (the engine sets lamps while the API reads them)."""

    @functools.wraps(method)
    def wrapper(self, *args: Any, **kwargs: Any) -> Any:
        with self._lock:
            return method(self, *args, **kwargs)

    return wrapper  # type: ignore[return-value]


class AsciiRelayBoard:
    """A :class:`~m2s2hil.drivers.interfaces.LightBank` on a Numato-style relay board."""

    def __init__(
        self,
        url: str,
        *,
        device: str = "relays",
        baudrate: int = 19200,
        timeout_s: float = 0.5,
        clock: Clock = SYSTEM_CLOCK,
        channels: int = 8,
        retries: int = 2,
        reconnect_attempts: int = 4,
        reconnect_interval_s: float = 0.5,
    ) -> None:
        if not 1 <= channels <= MAX_CHANNELS:
            raise ValueError(f"{device}: channels {channels} outside 1..{MAX_CHANNELS}")
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
        self._link = SerialLink(url, device=device, baudrate=baudrate, timeout_s=timeout_s, clock=clock)
        self._parser = ReplyParser()
        self._lock = threading.RLock()
        self._needs_reconnect = False
        self._ever_opened = False  # a port that never opened is a wrong path, not a glitch

    # -- connection -----------------------------------------------------------------------
    @_one_at_a_time
    def connect(self) -> None:
        """Open the port, clear any half-typed line on the board and read the relays."""
        self._transact(EmptyLine(), "sync")
        self.state()

    @_one_at_a_time
    def close(self) -> None:
        self._link.close()

    def __enter__(self) -> AsciiRelayBoard:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @_one_at_a_time
    def version(self) -> str:
        return self._one_answer(Version(), "ver")

    # -- LightBank ------------------------------------------------------------------------
    @_one_at_a_time
    def set(self, on_channels: Iterable[int]) -> None:
        """Switch exactly ``on_channels`` on (``relay writeall``), verified by read-back."""
        wanted = self._check_channels(on_channels)
        command = WriteAll(sum(1 << ch for ch in wanted), self.channels)
        self._no_answer(command, command.text)
        actual = self.state()
        if actual != wanted:
            raise RelayNotSwitched(
                f"read-back {sorted(actual)} differs from commanded {sorted(wanted)} "
                f"(stuck: {sorted(actual ^ wanted)})",
                device=self.name,
                command=command.text,
            )

    @_one_at_a_time
    def switch(self, channel: int, on: bool) -> None:
        """Switch one relay (``relay on/off N``), verified with ``relay read N``."""
        (ch,) = self._check_channels([channel])
        command = RelayOn(ch) if on else RelayOff(ch)
        self._no_answer(command, command.text)
        read = self._one_answer(RelayRead(ch), RelayRead(ch).text)
        if read not in ("on", "off"):
            raise ProtocolError(f"'relay read' answered {read!r}", device=self.name, command=command.text)
        if (read == "on") != on:
            raise RelayNotSwitched(
                f"relay {ch} reads {read} after switching it {'on' if on else 'off'}",
                device=self.name,
                command=command.text,
            )

    def all_off(self) -> None:
        self.set(())

    @_one_at_a_time
    def state(self) -> frozenset[int]:
        text = self._one_answer(ReadAll(), "relay readall")
        try:
            mask = parse_mask(text, self.channels)
        except CodecError as exc:
            raise ProtocolError(f"readall answer: {exc}", device=self.name, command="relay readall") from exc
        return frozenset(ch for ch in range(self.channels) if mask >> ch & 1)

    # -- internals --------------------------------------------------------------------------
    def _check_channels(self, channels: Iterable[int]) -> frozenset[int]:
        out = set()
        for ch in channels:
            if isinstance(ch, bool) or not isinstance(ch, int) or not 0 <= ch < self.channels:
                raise ValueError(f"{self.name}: channel {ch!r} outside 0..{self.channels - 1}")
            out.add(ch)
        return frozenset(out)

    def _one_answer(self, command: Command, label: str) -> str:
        answers = self._transact(command, label, answers=1)
        return answers[0]

    def _no_answer(self, command: Command, label: str) -> None:
        self._transact(command, label, answers=0)

    def _transact(self, command: Command, label: str, answers: int = 0) -> list[str]:
        last: DeviceError | None = None
        for attempt in range(1, self.retries + 2):
            try:
                return self._attempt(command, label, attempt, answers)
            except DeviceGone as exc:
                if not self._ever_opened:
                    raise
                self._needs_reconnect = True
                last = exc
            except (DeviceTimeout, ProtocolError) as exc:
                last = exc
        assert last is not None
        raise last

    def _attempt(self, command: Command, label: str, attempt: int, n_answers: int) -> list[str]:
        where = {"device": self.name, "command": label, "attempt": attempt}
        try:
            if self._needs_reconnect:
                self._link.reconnect(attempts=self.reconnect_attempts, interval_s=self.reconnect_interval_s)
            elif not self._link.is_open:
                self._link.open()
            self._needs_reconnect = False
            self._ever_opened = True
            self._link.drain_input()  # a late answer to an earlier command must not count
            self._parser.reset()
            self._link.write(encode(command), command=label)
            echo, answers = self._read_reply(label, attempt)
        except DeviceGone as exc:
            raise DeviceGone(exc.detail, **where) from exc
        if echo != command.text:
            raise ProtocolError(f"echo {echo!r} differs from the command {command.text!r}", **where)
        if len(answers) != n_answers and not isinstance(command, EmptyLine):
            if not answers:
                raise ProtocolError("no answer (the board ignores commands it does not know)", **where)
            raise ProtocolError(f"expected {n_answers} answer line(s), got {answers!r}", **where)
        return answers

    def _read_reply(self, label: str, attempt: int) -> tuple[str, list[str]]:
        deadline = self.clock.monotonic() + self.timeout_s
        echo = ""
        answers: list[str] = []
        while True:
            event = self._next_event(label, attempt)
            if event is NEED_DATA:
                remaining = deadline - self.clock.monotonic()
                try:
                    if remaining <= 0:
                        raise DeviceTimeout("deadline passed", device=self.name)
                    chunk = self._link.read_exact(1, timeout=remaining, command=label)
                    chunk += self._link.read_available(command=label)
                except DeviceTimeout as exc:
                    raise DeviceTimeout(
                        f"no prompt within {self.timeout_s:.3g} s (echo {echo!r}, answers {answers!r}, "
                        f"pending {self._parser.buffered!r})",
                        device=self.name,
                        command=label,
                        attempt=attempt,
                    ) from exc
                self._parser.receive_data(chunk)
            elif isinstance(event, Echo):  # the parser gives one echo per prompt
                echo = event.text
            elif isinstance(event, Answer):
                answers.append(event.text)
            elif isinstance(event, Prompt):
                return echo, answers

    def _next_event(self, label: str, attempt: int) -> Echo | Answer | Prompt | object:
        try:
            return self._parser.next_event()
        except CodecError as exc:
            raise ProtocolError(
                f"garbled answer: {exc}", device=self.name, command=label, attempt=attempt
            ) from exc
