"""The simulated TOUCAN's stream channel: when frames are exposed and read out, which reach the
host, and the transfers that carry them (leader, payload, trailer).

Free-running, frame *k* of an acquisition starts its exposure at ``t0 + k·period`` (period
``max(1/AcquisitionFrameRate, exposure)``); triggered, at the trigger or when the sensor is
free. A frame is ready after its exposure and one readout (``1/max_fps``), and waits in the
device's buffer of ``frame_buffer`` frames until the host reads it: a full buffer drops the
frames that come due. The stream faults (``unplug``, ``stall``, ``frame_timeout``,
``incomplete``, ``trailer_error``) are drawn once per frame when it is due.

The payload is split as the host wrote the SIRM (``count`` transfers of ``size``, then the two
final transfers); a short (``incomplete``) payload keeps trailer status 0 and says its valid
size, as a real device does.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

from m2s2hil.protocols import u3v
from m2s2hil.protocols.u3v import SIRM, PixelFormat, Status
from m2s2hil.simulators.fault_injection import FaultPlan
from m2s2hil.simulators.toucan_render import FrameSource, render
from m2s2hil.simulators.u3v_backend import Overflow

if TYPE_CHECKING:
    from m2s2hil.simulators.toucan_registers import RegisterSpace

# faults that end or interrupt the stream: a full buffer's drops are not skipped over them
_STREAM_STOPPERS = ("unplug", "stall", "frame_timeout")


@dataclass
class _Job:
    """A frame the sensor has finished and the device will send."""

    block_id: int
    start: float  # exposure start (clock time)
    ready: float  # end of readout
    exposure_s: float
    gain: float
    pixel_format: PixelFormat
    incomplete: float | None = None  # fraction of the payload sent
    trailer_status: int = Status.SUCCESS


class ToucanStream:
    """The stream channel of one camera, timed by the register settings in ``registers``."""

    def __init__(self, registers: RegisterSpace, faults: FaultPlan, *, max_fps: float,
                 frame_buffer: int) -> None:
        self.registers = registers
        self.faults = faults
        self.max_fps = max_fps
        self.frame_buffer = frame_buffer
        # what tests look at
        self.sent_block_ids: deque[int] = deque(maxlen=512)  # leaders sent, in order
        self.dropped_block_ids: deque[int] = deque(maxlen=4096)  # lost in the device (buffer, faults)
        self.power_on()

    def power_on(self) -> None:
        """Block ids from 1, nothing acquiring."""
        self._next_block = 1
        self.reset()

    def reset(self) -> None:
        """Acquisition stopped: pending triggers, frames and transfers are gone."""
        self.acquiring = False
        self.stalled = False
        self._acq_t0 = 0.0
        self._frames_scheduled = 0  # free-run frames accounted for since start
        # triggered frames: (exposure start, exposure_s, gain) as set when triggered
        self._triggers: deque[tuple[float, float, float]] = deque()
        self._last_start = -math.inf
        self._last_period = 0.0  # the frame period when the last trigger was taken
        self._jobs: deque[_Job] = deque()
        self._transfers: deque[bytes | memoryview] = deque()
        self._single_done = False

    def drop_transfers(self) -> None:
        self._transfers.clear()

    # -- acquisition control (AcquisitionStart, TriggerSoftware) ---------------------------
    def start(self, t0: float) -> None:
        """Start acquiring, the first exposure at ``t0`` (no-op if already acquiring)."""
        if not self.acquiring:
            self.reset()
            self.acquiring = True
            self._acq_t0 = t0

    def trigger(self, now: float) -> None:
        now = max(now, self._acq_t0)
        # The previous frame occupies the sensor for ITS period (its own exposure), not
        # the one just configured: a long exposure after a short one starts at once.
        start = max(now, self._last_start + self._last_period)
        self._last_start = start
        self._last_period = self._period()
        self._triggers.append((start, self._exposure_s(), self.registers.settings.gain))

    # -- timing ------------------------------------------------------------------------------
    def _exposure_s(self) -> float:
        return self.registers.settings.exposure_us * 1e-6

    def _period(self) -> float:
        return max(1.0 / self.registers.settings.frame_rate, self._exposure_s())

    def _readout_s(self) -> float:
        return 1.0 / self.max_fps

    def next_ready(self) -> float | None:
        """When the next frame finishes (None if none is coming)."""
        if not self.acquiring or self.stalled or not self.registers.si_enabled or self._single_done:
            return None
        if self.registers.settings.trigger_mode == 1:
            if not self._triggers:
                return None
            start, exposure, _gain = self._triggers[0]
            return start + exposure + self._readout_s()
        tail = self._exposure_s() + self._readout_s()
        return self._acq_t0 + self._frames_scheduled * self._period() + tail

    def next_due(self, now: float) -> float | None:
        """When the stream endpoint next has data: now if a frame is waiting."""
        if self._transfers or self._jobs:
            return now
        return self.next_ready()

    def schedule(self, now: float) -> float | None:
        """Turn frames finished by ``now`` into jobs (faults are drawn here). If an ``unplug``
        fault fired, its duration: the device must leave the bus."""
        self._skip_overflow(now)
        s = self.registers.settings
        while True:
            ready = self.next_ready()
            if ready is None or ready > now:
                return None
            if s.trigger_mode == 1:
                start, exposure, gain = self._triggers.popleft()
            else:
                start = self._acq_t0 + self._frames_scheduled * self._period()
                exposure, gain = self._exposure_s(), s.gain
                self._frames_scheduled += 1
            if s.acquisition_mode == 1:
                self._single_done = True
            block_id = self._next_block
            self._next_block += 1
            unplug_s = self._frame_faults(block_id, start, ready, exposure, gain)
            if unplug_s is not None:
                return unplug_s
            if self._single_done:
                self.acquiring = False

    def _skip_overflow(self, now: float) -> None:
        """Free-running with a full buffer: drop the frames due by ``now`` in one step."""
        s = self.registers.settings
        if (
            s.trigger_mode == 1
            or s.acquisition_mode == 1
            or len(self._jobs) < self.frame_buffer
            or any(self.faults.pending(k) for k in _STREAM_STOPPERS)
        ):
            return
        ready = self.next_ready()
        if ready is None or ready > now:
            return
        n = int((now - ready) / self._period()) + 1
        self.dropped_block_ids.extend(range(self._next_block, self._next_block + n))
        self._next_block += n
        self._frames_scheduled += n

    def _frame_faults(self, block_id: int, start: float, ready: float, exposure: float,
                      gain: float) -> float | None:
        """Apply this frame's faults and queue it; the unplug duration if it leaves the bus."""
        unplug = self.faults.take("unplug")
        if unplug is not None:
            self.dropped_block_ids.append(block_id)
            return float(unplug.get("duration_s", 1.0))
        if self.faults.take("stall") is not None:
            self.stalled = True
            self.dropped_block_ids.append(block_id)
            return None
        if self.faults.take("frame_timeout") is not None or len(self._jobs) >= self.frame_buffer:
            self.dropped_block_ids.append(block_id)
            return None
        job = _Job(block_id, start, ready, exposure, gain, self.registers.settings.pixel_format)
        inc = self.faults.take("incomplete")
        if inc is not None:
            job.incomplete = float(inc.get("fraction", 0.5))
        err = self.faults.take("trailer_error")
        if err is not None:
            job.trailer_status = int(err.get("status", Status.DATA_DISCARDED))
        self._jobs.append(job)
        return None

    # -- transfers ---------------------------------------------------------------------------
    @property
    def sending(self) -> bool:
        """Whether a frame's transfers are under way."""
        return bool(self._transfers)

    def begin_frame(self, source: FrameSource) -> bool:
        """Render the oldest waiting frame into its transfers; False if none is waiting."""
        if not self._jobs:
            return False
        self._transfers.extend(self._transfers_of(self._jobs.popleft(), source))
        return True

    def next_transfer(self, max_len: int) -> bytes | memoryview:
        chunk = self._transfers.popleft()
        if len(chunk) > max_len:  # like babble on the bus: the transfer is lost
            raise Overflow(f"stream transfer of {len(chunk)} bytes, buffer {max_len}")
        return chunk

    def _transfers_of(self, job: _Job, source: FrameSource) -> list[bytes | memoryview]:
        regs = self.registers
        img = render(source, job.exposure_s, job.gain, job.start, (regs.height, regs.width))
        payload = memoryview(u3v.encode_image(img, job.pixel_format)).cast("B")
        total = len(payload)
        send = total if job.incomplete is None else int(total * job.incomplete)
        h = regs.sirm_host
        sizes = [h[SIRM.PAYLOAD_TRANSFER_SIZE]] * h[SIRM.PAYLOAD_TRANSFER_COUNT]
        sizes += [h[SIRM.FINAL_TRANSFER1_SIZE], h[SIRM.FINAL_TRANSFER2_SIZE]]
        leader = u3v.ImageLeader(
            block_id=job.block_id,
            timestamp=round((job.start - regs.boot) * 1e9),
            pixel_format=int(job.pixel_format),
            size_x=regs.width,
            size_y=regs.height,
        )
        out: list[bytes | memoryview] = [leader.encode()]
        pos = 0
        for size in sizes:
            if pos >= send or size == 0:
                continue
            out.append(payload[pos : min(pos + size, send)])
            pos = min(pos + size, send)
        # A short payload keeps status 0: the host must notice the valid size itself.
        out.append(u3v.Trailer(job.block_id, job.trailer_status, pos, regs.height).encode())
        self.sent_block_ids.append(job.block_id)
        return out
