"""GenCP register access over a U3V control pipe.

One transaction at a time: a command with a fresh request id, then acknowledges are
read until the one that matches (same id, command id + 1). A PENDING_ACK extends the
wait by the time it announces; stale or unreadable acknowledges are skipped; no answer
within the timeout resends the command with the resend flag (same request id, so a
device that already executed it only repeats its acknowledge). A non-zero status
raises :class:`GenCPError`, which names it.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable
from typing import Any

from m2s2hil.drivers.errors import CameraError, DeviceTimeout, ProtocolError
from m2s2hil.protocols import u3v
from m2s2hil.protocols.errors import CodecError
from m2s2hil.protocols.u3v_gencp import MAX_PAYLOAD

log = logging.getLogger(__name__)

DEFAULT_MAX_TRANSFER = 1024  # until the SBRM says otherwise


class GenCPError(CameraError):
    """The device answered a GenCP command with an error status."""

    def __init__(self, message: str, *, status: int, address: int | None = None, **kw: Any) -> None:
        self.status = status
        self.status_name = u3v.status_name(status)
        self.address = address
        super().__init__(message, **kw)


class GenCPControl:
    """Register reads and writes with request ids, PENDING_ACK handling and retries."""

    def __init__(
        self,
        link: Any,
        clock: Any,
        *,
        name: str = "camera",
        timeout_s: float = 2.0,
        retries: int = 3,
    ) -> None:
        self.link = link
        self.clock = clock
        self.name = name
        self.timeout_s = float(timeout_s)
        self.retries = max(1, int(retries))
        self.ids = u3v.RequestIds()
        self.max_command = DEFAULT_MAX_TRANSFER
        self.max_ack = DEFAULT_MAX_TRANSFER
        self.resends = 0  # commands sent again after a missing acknowledge
        self.pending_acks = 0  # PENDING_ACKs honoured

    def set_limits(self, *, max_command: int, max_ack: int, response_time_ms: int | None = None) -> None:
        """Transfer limits from the SBRM and the device's maximum response time."""
        if max_command <= u3v.HEADER_SIZE + 8 or max_ack <= u3v.HEADER_SIZE:
            raise ProtocolError(
                f"implausible transfer limits (command {max_command}, ack {max_ack})", device=self.name
            )
        self.max_command = min(max_command, u3v.HEADER_SIZE + MAX_PAYLOAD)
        self.max_ack = min(max_ack, u3v.HEADER_SIZE + MAX_PAYLOAD)
        if response_time_ms:
            # Wait for the device's own bound plus slack, never less than it.
            self.timeout_s = max(self.timeout_s, response_time_ms / 1000.0 * 2)

    # -- transactions -------------------------------------------------------------------
    def _transact(self, build: Callable[[int, bool], u3v.Command], what: str) -> u3v.Ack:
        request_id = self.ids.next()
        for attempt in range(1, self.retries + 1):
            cmd = build(request_id, attempt > 1)
            if attempt > 1:
                self.resends += 1
                log.info("%s: resending %s (attempt %d)", self.name, what, attempt)
            self.link.write_control(cmd.encode(), self.timeout_s)
            ack = self._await_ack(cmd, what, attempt)
            if ack is not None:
                return ack
        raise DeviceTimeout(
            f"no acknowledge after {self.retries} attempts of {self.timeout_s:.3g} s",
            device=self.name,
            command=what,
            attempt=self.retries,
        )

    def _await_ack(self, cmd: u3v.Command, what: str, attempt: int) -> u3v.Ack | None:
        deadline = self.clock.monotonic() + self.timeout_s
        while True:
            remaining = deadline - self.clock.monotonic()
            if remaining <= 0:
                return None
            try:
                raw = self.link.read_control(self.max_ack, remaining)
            except DeviceTimeout:
                return None
            try:
                ack = u3v.decode_ack(raw)
            except CodecError as exc:
                log.warning("%s: unreadable acknowledge to %s skipped: %s", self.name, what, exc)
                continue
            if u3v.is_pending_for(ack, cmd):
                try:
                    wait_ms = u3v.parse_pending_ack(ack)
                except CodecError as exc:
                    raise ProtocolError(str(exc), device=self.name, command=what, attempt=attempt) from exc
                self.pending_acks += 1
                deadline = self.clock.monotonic() + wait_ms / 1000.0
                continue
            if u3v.ack_matches(ack, cmd):
                return ack
            log.debug(
                "%s: stale acknowledge 0x%04X id %d skipped (waiting for id %d)",
                self.name,
                ack.command_id,
                ack.request_id,
                cmd.request_id,
            )

    def _check(self, ack: u3v.Ack, what: str, address: int) -> None:
        if not ack.ok:
            raise GenCPError(
                f"{ack.status_name} (0x{ack.status:04X}) at 0x{address:X}",
                status=ack.status,
                address=address,
                device=self.name,
                command=what,
            )

    # -- memory -------------------------------------------------------------------------
    def read(self, address: int, length: int) -> bytes:
        """``length`` bytes from ``address`` (split into as many READMEMs as needed)."""
        out = bytearray()
        chunk = self.max_ack - u3v.HEADER_SIZE
        while len(out) < length:
            addr = address + len(out)
            n = min(chunk, length - len(out))
            what = f"READMEM 0x{addr:X}+{n}"
            def read_cmd(rid: int, resend: bool, a: int = addr, k: int = n) -> u3v.Command:
                return u3v.read_mem(a, k, rid, resend=resend)

            ack = self._transact(read_cmd, what)
            self._check(ack, what, addr)
            if len(ack.payload) != n:
                raise ProtocolError(
                    f"READMEM_ACK carries {len(ack.payload)} bytes, asked for {n}",
                    device=self.name,
                    command=what,
                )
            out += ack.payload
        return bytes(out)

    def write(self, address: int, data: bytes) -> None:
        chunk = self.max_command - u3v.HEADER_SIZE - 8
        done = 0
        while done < len(data) or not data:
            addr = address + done
            part = bytes(data[done : done + chunk])
            what = f"WRITEMEM 0x{addr:X}+{len(part)}"
            def write_cmd(rid: int, resend: bool, a: int = addr, p: bytes = part) -> u3v.Command:
                return u3v.write_mem(a, p, rid, resend=resend)

            ack = self._transact(write_cmd, what)
            self._check(ack, what, addr)
            try:
                written = u3v.parse_write_mem_ack(ack)
            except CodecError as exc:
                raise ProtocolError(str(exc), device=self.name, command=what) from exc
            if written is not None and written != len(part):
                raise ProtocolError(
                    f"device wrote {written} of {len(part)} bytes", device=self.name, command=what
                )
            done += len(part)
            if not data:
                break

    def read_u32(self, address: int) -> int:
        return struct.unpack("<I", self.read(address, 4))[0]

    def read_u64(self, address: int) -> int:
        return struct.unpack("<Q", self.read(address, 8))[0]

    def write_u32(self, address: int, value: int) -> None:
        self.write(address, struct.pack("<I", value))

    def read_string(self, address: int, length: int = u3v.STRING_LENGTH) -> str:
        try:
            return u3v.decode_string(self.read(address, length))
        except CodecError as exc:
            raise ProtocolError(str(exc), device=self.name, command=f"READMEM 0x{address:X}") from exc
