"""A scripted device for byte-exact protocol tests (in the style of pymeasure).

The script is a list of (expected write, reply) pairs. A write that does not match
the next pair fails at once; :meth:`ScriptedDevice.verify` fails if a pair was never
used. Register it as ``sim://NAME`` and point a driver at it.
"""

from __future__ import annotations

from typing import Any

from m2s2hil.simulators.device import SimDevice


class ScriptError(AssertionError):
    pass


class ScriptedDevice(SimDevice):
    def __init__(
        self, name: str, clock: Any, script: list[tuple[bytes, bytes]], *, delay: float = 0.0
    ) -> None:
        super().__init__(name, clock)
        self.script = list(script)
        self.delay = delay
        self._pos = 0
        self._pending = bytearray()
        self.errors: list[str] = []

    def on_bytes(self, data: bytes) -> None:
        self._pending += data
        while self._pending:
            if self._pos >= len(self.script):
                msg = f"unscripted write {bytes(self._pending)!r} after the script ended"
                self.errors.append(msg)
                raise ScriptError(msg)
            expected, reply = self.script[self._pos]
            n = min(len(expected), len(self._pending))
            if bytes(self._pending[:n]) != expected[:n]:
                msg = (
                    f"pair {self._pos}: expected write {expected!r}, "
                    f"got {bytes(self._pending)!r}"
                )
                self.errors.append(msg)
                raise ScriptError(msg)
            if n < len(expected):
                return  # wait for the rest of this write
            del self._pending[:n]
            self._pos += 1
            if reply:
                self.send(reply, self.delay)

    def verify(self) -> None:
        if self.errors:
            raise ScriptError("; ".join(self.errors))
        if self._pending:
            raise ScriptError(f"partial unscripted write {bytes(self._pending)!r}")
        if self._pos != len(self.script):
            unused = self.script[self._pos :]
            raise ScriptError(f"{len(unused)} scripted pair(s) never used, first: {unused[0]!r}")
