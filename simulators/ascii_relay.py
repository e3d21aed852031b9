"""A simulated Numato-style ASCII relay board.

It echoes every printable character as it arrives (LF is swallowed), and on CR runs
the line and prints LF CR, the answer lines and the ``>`` prompt. Assumption about
commands it does not understand, from Numato Lab's own answer on their forum
("If the device receive a incorrectly formatted command, it will ignore the command
silently ... If bad data is trailing an otherwise correct command, the command will
still be executed"): an unknown or malformed line gets only the line end and a new
prompt, and words after a complete command are ignored. Commands are lower case.

``on_change(channel, on)`` is called for every relay that really changes. Device
fault ``relay_stuck`` (param ``channel``, default 0): each occurrence is one switching
command (``relay on/off``, ``relay writeall``) during which that relay keeps its
state while the board answers as usual. Generic faults hit the answer (line end,
answers, prompt), not the echo. A vanished port keeps the relays as they were and
loses a half-typed line.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from m2s2hil.protocols.ascii_relay import (
    MAX_CHANNELS,
    MAX_LINE,
    Command,
    ReadAll,
    RelayOff,
    RelayOn,
    RelayRead,
    Version,
    WriteAll,
    encode_reply,
    format_mask,
    parse_command,
)
from m2s2hil.simulators.device import SimDevice
from m2s2hil.simulators.fault_injection import FaultPlan

OnChange = Callable[[int, bool], None]


class AsciiRelaySim(SimDevice):
    baudrate = 19200

    def __init__(
        self,
        name: str,
        clock: Any,
        faults: FaultPlan | None = None,
        *,
        channels: int = 8,
        version: str = "00000008",
        on_change: OnChange | None = None,
        response_delay_s: float = 0.002,
    ) -> None:
        super().__init__(name, clock, faults)
        if not 1 <= channels <= MAX_CHANNELS:
            raise ValueError(f"channels {channels} outside 1..{MAX_CHANNELS}")
        self.channels = channels
        self.version = version
        self.on_change = on_change
        self.response_delay_s = response_delay_s
        self._relays = [False] * channels
        self._line = bytearray()
        self.ignored_lines: list[str] = []  # lines the board did not understand, for tests

    @property
    def relays(self) -> tuple[bool, ...]:
        with self.lock:
            return tuple(self._relays)

    @property
    def on_channels(self) -> frozenset[int]:
        with self.lock:
            return frozenset(i for i, on in enumerate(self._relays) if on)

    def on_disconnect(self) -> None:
        self._line.clear()

    def on_bytes(self, data: bytes) -> None:
        echo = bytearray()
        for b in data:
            if b == 0x0D:
                if echo:
                    self.send(bytes(echo), reply=False)
                    echo.clear()
                line, self._line = self._line.decode("ascii"), bytearray()
                self.send(encode_reply(self._run(line)), self.response_delay_s)
            elif 0x20 <= b <= 0x7E:
                echo.append(b)
                if len(self._line) < MAX_LINE:  # a full input buffer drops characters
                    self._line.append(b)
            # LF and other control bytes are neither echoed nor stored.
        if echo:
            self.send(bytes(echo), reply=False)

    def _run(self, line: str) -> list[str]:
        command = parse_command(line, self.channels)
        if command is None:
            self.ignored_lines.append(line)
            return []
        return self._execute(command)

    def _execute(self, command: Command) -> list[str]:
        if isinstance(command, RelayRead):
            return ["on" if self.relays[command.channel] else "off"]
        if isinstance(command, ReadAll):
            mask = sum(1 << i for i, on in enumerate(self.relays) if on)
            return [format_mask(mask, self.channels)]
        if isinstance(command, Version):
            return [self.version]
        if isinstance(command, RelayOn | RelayOff):
            self._switch({command.channel: isinstance(command, RelayOn)})
        elif isinstance(command, WriteAll):
            self._switch({ch: bool(command.mask >> ch & 1) for ch in range(self.channels)})
        return []  # EmptyLine and switching commands print nothing but the prompt

    def _switch(self, wanted: dict[int, bool]) -> None:
        stuck = self.faults.take("relay_stuck")
        stuck_channel = int(stuck.get("channel", 0)) if stuck is not None else None
        changed: list[tuple[int, bool]] = []
        with self.lock:
            for channel, on in wanted.items():
                if channel == stuck_channel or self._relays[channel] == on:
                    continue
                self._relays[channel] = on
                changed.append((channel, on))
        if self.on_change is not None:
            for channel, on in changed:
                self.on_change(channel, on)
