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

from typing import Any

from m2s2hil.drivers.clock import SYSTEM_CLOCK, Clock
from m2s2hil.drivers.errors import DeviceGone, ProtocolError, RelayNotSwitched
from m2s2hil.drivers.locking import one_at_a_time
from m2s2hil.drivers.relay_base import RelayBoardBase
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


class AsciiRelayBoard(RelayBoardBase):
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
        super().__init__(
            device, channels, MAX_CHANNELS, retries=retries, timeout_s=timeout_s, clock=clock,
            reconnect_attempts=reconnect_attempts, reconnect_interval_s=reconnect_interval_s,
        )
        self._link = SerialLink(url, device=device, baudrate=baudrate, timeout_s=timeout_s, clock=clock)
        self._parser = ReplyParser()

    # -- connection -----------------------------------------------------------------------
    @one_at_a_time
    def connect(self) -> None:
        """Open the port, clear any half-typed line on the board and read the relays."""
        self._transact(EmptyLine(), "sync")
        self.state()

    @one_at_a_time
    def version(self) -> str:
        return self._one_answer(Version(), "ver")

    # -- LightBank ------------------------------------------------------------------------
    @one_at_a_time
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

    @one_at_a_time
    def state(self) -> frozenset[int]:
        text = self._one_answer(ReadAll(), "relay readall")
        try:
            mask = parse_mask(text, self.channels)
        except CodecError as exc:
            raise ProtocolError(f"readall answer: {exc}", device=self.name, command="relay readall") from exc
        return frozenset(ch for ch in range(self.channels) if mask >> ch & 1)

    # -- internals --------------------------------------------------------------------------
    def _write_all(self, wanted: frozenset[int]) -> str:
        """``relay writeall`` with the whole mask."""
        command = WriteAll(sum(1 << ch for ch in wanted), self.channels)
        self._no_answer(command, command.text)
        return command.text

    def _one_answer(self, command: Command, label: str) -> str:
        answers = self._transact(command, label, answers=1)
        return answers[0]

    def _no_answer(self, command: Command, label: str) -> None:
        self._transact(command, label, answers=0)

    def _transact(self, command: Command, label: str, answers: int = 0) -> list[str]:
        return self._retrying(lambda attempt: self._attempt(command, label, attempt, answers))

    def _attempt(self, command: Command, label: str, attempt: int, n_answers: int) -> list[str]:
        where: dict[str, Any] = {"device": self.name, "command": label, "attempt": attempt}
        try:
            self._open_line()
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

        def missing() -> str:
            return (
                f"no prompt within {self.timeout_s:.3g} s (echo {echo!r}, answers {answers!r}, "
                f"pending {self._parser.buffered!r})"
            )

        while True:
            event = self._decoded(self._parser.next_event, label, attempt)
            if event is NEED_DATA:
                self._parser.receive_data(self._read_some(deadline, label, attempt, missing))
            elif isinstance(event, Echo):  # the parser gives one echo per prompt
                echo = event.text
            elif isinstance(event, Answer):
                answers.append(event.text)
            elif isinstance(event, Prompt):
                return echo, answers
