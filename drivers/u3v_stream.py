"""The U3V streaming interface seen from the host: SIRM set-up and block reading.

Set-up reads the required payload, leader and trailer sizes and the alignment from
the SIRM, chooses a transfer plan (``count`` transfers of ``size`` bytes, one final
transfer for the remainder), writes it and enables the interface.

A block is read as leader, payload transfers, trailer, and validated: magic numbers,
leader and trailer block ids equal and in sequence, image size and pixel format as
expected, valid payload size equal to the expected size, trailer status 0. Whatever
fails raises FrameIncomplete (something missing) or FrameCorrupt (something wrong);
gaps in the block ids are recorded in ``missing_block_ids``. Transfers left over from
a broken block are skipped before the next leader.
"""

from __future__ import annotations

import array
import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
from m2s2hil.drivers.errors import CameraError, DeviceTimeout, FrameCorrupt, FrameIncomplete
from m2s2hil.protocols import u3v
from m2s2hil.protocols.errors import CodecError

log = logging.getLogger(__name__)

MAX_TRANSFER = 1 << 20  # 1 MiB payload transfers: few calls per frame, modest buffers


def _align_up(n: int, a: int) -> int:
    return (n + a - 1) // a * a


@dataclass(frozen=True)
class StreamPlan:
    payload_size: int
    leader_size: int
    trailer_size: int
    alignment: int
    transfer_size: int
    transfer_count: int
    final1_size: int
    final2_size: int = 0

    @property
    def capacity(self) -> int:
        return self.transfer_size * self.transfer_count + self.final1_size + self.final2_size


def plan_stream(
    payload_size: int, leader_size: int, trailer_size: int, alignment: int, max_transfer: int = MAX_TRANSFER
) -> StreamPlan:
    """Transfer sizes that carry ``payload_size`` bytes with every buffer aligned."""
    if payload_size <= 0:
        raise ValueError(f"payload size {payload_size}")
    size = min(max_transfer // alignment * alignment, payload_size // alignment * alignment)
    count = payload_size // size if size else 0
    rest = payload_size - size * count
    final1 = _align_up(rest, alignment) if rest else 0
    return StreamPlan(
        payload_size=payload_size,
        leader_size=leader_size,
        trailer_size=trailer_size,
        alignment=alignment,
        transfer_size=size,
        transfer_count=count,
        final1_size=final1,
    )


@dataclass(frozen=True)
class Block:
    """One validated block: its leader, trailer and payload bytes."""

    leader: u3v.ImageLeader
    trailer: u3v.Trailer
    payload: np.ndarray  # uint8, exactly the expected payload size


class StreamChannel:
    """SIRM set-up and block reading for one U3V stream interface."""

    def __init__(
        self, link: Any, control: Any, sirm_address: int, clock: Any, *, name: str = "camera"
    ) -> None:
        self.link = link
        self.control = control
        self.sirm = sirm_address
        self.clock = clock
        self.name = name
        self.plan: StreamPlan | None = None
        self.enabled = False
        self.last_block_id: int | None = None
        self.missing_block_ids: list[int] = []  # gaps seen in the block ids
        self.skipped_transfers = 0  # leftovers of broken blocks dropped while resyncing
        self._pending_leader: bytes | None = None
        self._buffers: list[array.array] = []
        self._head = array.array("B")

    # -- set-up -------------------------------------------------------------------------
    def configure(self) -> StreamPlan:
        """Read the requirements, write a transfer plan (interface must be disabled)."""
        c, base = self.control, self.sirm
        try:
            alignment = u3v.sirm_alignment(c.read_u32(base + u3v.SIRM.INFO))
        except CodecError as exc:
            raise CameraError(f"SIRM info: {exc}", device=self.name) from exc
        payload = c.read_u64(base + u3v.SIRM.REQUIRED_PAYLOAD_SIZE)
        leader = c.read_u32(base + u3v.SIRM.REQUIRED_LEADER_SIZE)
        trailer = c.read_u32(base + u3v.SIRM.REQUIRED_TRAILER_SIZE)
        if not (0 < payload < 1 << 32 and u3v.IMAGE_LEADER_SIZE <= leader < 1 << 16):
            raise CameraError(
                f"implausible stream requirements: payload {payload}, leader {leader}", device=self.name
            )
        if not u3v.TRAILER_MIN_SIZE <= trailer < 1 << 16:
            raise CameraError(f"implausible trailer size {trailer}", device=self.name)
        plan = plan_stream(payload, leader, trailer, alignment)
        for reg, value in (
            (u3v.SIRM.MAX_LEADER_SIZE, plan.leader_size),
            (u3v.SIRM.PAYLOAD_TRANSFER_SIZE, plan.transfer_size),
            (u3v.SIRM.PAYLOAD_TRANSFER_COUNT, plan.transfer_count),
            (u3v.SIRM.FINAL_TRANSFER1_SIZE, plan.final1_size),
            (u3v.SIRM.FINAL_TRANSFER2_SIZE, plan.final2_size),
            (u3v.SIRM.MAX_TRAILER_SIZE, plan.trailer_size),
        ):
            c.write_u32(base + reg, value)
        self.plan = plan
        sizes = [plan.transfer_size] * plan.transfer_count + [plan.final1_size]
        self._buffers = [array.array("B", bytes(n)) for n in sizes if n]
        # Leaders, trailers and stray transfers land here: big enough for any transfer.
        self._head = array.array("B", bytes(max(plan.leader_size, plan.trailer_size, *sizes)))
        return plan

    def enable(self) -> None:
        if self.plan is None:
            self.configure()
        self.control.write_u32(self.sirm + u3v.SIRM.CONTROL, u3v.SI_CONTROL_ENABLE)
        self.enabled = True

    def disable(self) -> None:
        self.control.write_u32(self.sirm + u3v.SIRM.CONTROL, 0)
        self.enabled = False
        self._pending_leader = None

    # -- reading ------------------------------------------------------------------------
    def _read(self, buf: array.array, deadline: float, what: str) -> int:
        remaining = deadline - self.clock.monotonic()
        if remaining <= 0:
            raise DeviceTimeout(f"no {what} in time", device=self.name, command=what)
        return self.link.read_stream(buf, remaining)

    def read_block(self, timeout_s: float, *, expect: tuple[int, int, int] | None = None) -> Block:
        """The next block. ``expect`` = (pixel format, width, height) to check the leader."""
        if self.plan is None or not self.enabled:
            raise CameraError("stream interface is not enabled", device=self.name)
        plan = self.plan
        deadline = self.clock.monotonic() + timeout_s
        leader = self._next_leader(deadline)
        self._sequence(leader.block_id)
        try:
            payload, trailer = self._read_rest(leader, deadline)
        except DeviceTimeout as exc:
            raise FrameIncomplete(
                f"block {leader.block_id}: leader seen, rest missing ({exc.detail})",
                device=self.name,
                command="stream",
            ) from exc
        if trailer.block_id != leader.block_id:
            raise FrameCorrupt(
                f"trailer block id {trailer.block_id} after leader {leader.block_id}", device=self.name
            )
        if trailer.status != u3v.Status.SUCCESS:
            raise FrameCorrupt(
                f"block {leader.block_id}: trailer status {u3v.status_name(trailer.status)}"
                f" (0x{trailer.status:04X})",
                device=self.name,
            )
        if trailer.valid_payload_size != plan.payload_size or payload is None:
            got = trailer.valid_payload_size
            raise FrameIncomplete(
                f"block {leader.block_id}: {got} of {plan.payload_size} payload bytes", device=self.name
            )
        if expect is not None:
            fmt, width, height = expect
            if (leader.pixel_format, leader.size_x, leader.size_y) != (fmt, width, height):
                raise FrameCorrupt(
                    f"block {leader.block_id}: leader says 0x{leader.pixel_format:08X}"
                    f" {leader.size_x}x{leader.size_y}, expected 0x{fmt:08X} {width}x{height}",
                    device=self.name,
                )
        return Block(leader, trailer, payload)

    def _next_leader(self, deadline: float) -> u3v.ImageLeader:
        if self._pending_leader is not None:
            raw, self._pending_leader = self._pending_leader, None
        else:
            while True:
                n = self._read(self._head, deadline, "leader")
                raw = self._head[:n].tobytes()
                if u3v.stream_prefix(raw) == u3v.LEADER_PREFIX:
                    break
                self.skipped_transfers += 1  # the tail of a block we gave up on
        try:
            return u3v.decode_leader(raw)
        except CodecError as exc:
            raise FrameCorrupt(f"bad leader: {exc}", device=self.name) from exc

    def _read_rest(self, leader: u3v.ImageLeader, deadline: float) -> tuple[np.ndarray | None, u3v.Trailer]:
        plan = self.plan
        assert plan is not None
        out = np.empty(plan.payload_size, np.uint8)
        got = 0
        for buf in self._buffers:
            if got >= plan.payload_size:
                break
            n = self._read(buf, deadline, "payload")
            chunk = memoryview(buf)[:n]
            if n < len(buf) and n <= plan.trailer_size + 64:
                prefix = u3v.stream_prefix(chunk)
                if prefix == u3v.TRAILER_PREFIX:  # the device ended the block early
                    return None, self._decode_trailer(chunk)
                if prefix == u3v.LEADER_PREFIX:  # the next block began: this one lost its end
                    self._pending_leader = bytes(chunk)
                    raise FrameIncomplete(
                        f"block {leader.block_id}: next leader after {got} payload bytes", device=self.name
                    )
            take = min(n, plan.payload_size - got)
            out[got : got + take] = np.frombuffer(chunk, np.uint8, take)
            got += n
        n = self._read(self._head, deadline, "trailer")
        raw = memoryview(self._head)[:n]
        if u3v.stream_prefix(raw) == u3v.LEADER_PREFIX:
            self._pending_leader = bytes(raw)
            raise FrameIncomplete(
                f"block {leader.block_id}: no trailer before the next leader", device=self.name
            )
        trailer = self._decode_trailer(raw)
        return (out if got == plan.payload_size else None), trailer

    def _decode_trailer(self, raw: memoryview) -> u3v.Trailer:
        try:
            return u3v.decode_trailer(bytes(raw))
        except CodecError as exc:
            raise FrameCorrupt(f"bad trailer: {exc}", device=self.name) from exc

    def _sequence(self, block_id: int) -> None:
        last = self.last_block_id
        self.last_block_id = block_id
        if last is None or block_id == last + 1:
            return
        if block_id <= last:
            raise FrameCorrupt(f"block id {block_id} after {last}: out of sequence", device=self.name)
        missing = list(range(last + 1, block_id))
        self.missing_block_ids.extend(missing)
        log.warning("%s: block ids %s never arrived", self.name, _ranges(missing))


def _ranges(ids: list[int]) -> str:
    return f"{ids[0]}" if len(ids) == 1 else f"{ids[0]}..{ids[-1]} ({len(ids)})"
