"""Acquisition on a U3V camera through its SFNC features: settings, modes, frames.

Two modes run on the device: "triggered" (continuous acquisition on software
triggers, one frame per :meth:`Acquisition.snap`) and "streaming" (free-running at a
frame rate clamped to the device's range). Switching stops acquisition and disables
the stream interface first. A frame is a stream block decoded into a
:class:`~m2s2hil.drivers.interfaces.Frame` with the device timestamp converted to
seconds. What the host asked for is kept in :class:`CameraSettings` so a reconnect can
re-apply it (:meth:`Acquisition.reapply`).

The class holds no locks and does not know about unplugs: the camera facade
(:class:`~m2s2hil.drivers.u3v.U3VCamera`) serialises calls and marks a session gone.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from m2s2hil.drivers.clock import Clock
from m2s2hil.drivers.errors import CameraError, DeviceTimeout, FrameCorrupt, FrameIncomplete
from m2s2hil.drivers.interfaces import Frame
from m2s2hil.drivers.u3v_session import U3VSession
from m2s2hil.protocols import u3v
from m2s2hil.protocols.errors import CodecError

TEMPERATURE_MAX_AGE_S = 1.0  # frames reuse a temperature read this recently


@dataclass
class CameraSettings:
    """What the host asked for last; re-applied after a reconnect."""

    exposure_s: float | None = None
    gain: float | None = None
    pixel_format: str | None = None
    mode: str = "idle"  # "idle", "triggered" (snap) or "streaming"
    fps: float | None = None


class Acquisition:
    """Settings, acquisition modes and frame reading over the current session."""

    def __init__(
        self, session: Callable[[], U3VSession], clock: Clock, *, name: str, timeout_s: float
    ) -> None:
        self._session = session  # the live session, or DeviceGone/CameraError
        self.clock = clock
        self.name = name
        self.timeout_s = timeout_s
        self.settings = CameraSettings()
        self.rearm = False  # a snap failed: re-arm before the next one
        self.last_frame_at: float | None = None
        self.stream_fps: float | None = None  # the frame rate the device was given
        self._temperature: tuple[float, float] | None = None  # (clock time, value)

    # -- settings -----------------------------------------------------------------------
    def configure(self, exposure_s: float | None, gain: float | None) -> None:
        f = self._session().features
        if exposure_s is not None:
            if not (math.isfinite(exposure_s) and exposure_s > 0):
                raise CameraError(f"exposure {exposure_s!r} s is not a positive time", device=self.name)
            f.set("ExposureTime", exposure_s * 1e6)
            self.settings.exposure_s = float(f.get("ExposureTime", fresh=True)) * 1e-6
        if gain is not None:
            if not (math.isfinite(gain) and gain > 0):
                raise CameraError(f"gain {gain!r} is not a positive factor", device=self.name)
            f.set("Gain", gain)
            self.settings.gain = float(f.get("Gain", fresh=True))

    def set_pixel_format(self, name: str) -> None:
        try:
            u3v.pixel_format(name)
        except CodecError as exc:
            raise CameraError(
                f"pixel format {name!r} cannot be decoded by this driver", device=self.name
            ) from exc
        mode = self.settings.mode
        self.halt()
        self._session().features.set("PixelFormat", name)
        self.settings.pixel_format = name
        self.resume(mode)

    # -- modes --------------------------------------------------------------------------
    def halt(self) -> None:
        """Acquisition stopped and the stream interface disabled."""
        s = self._session()
        if self.settings.mode != "idle":
            s.features.execute("AcquisitionStop")
        if s.stream.enabled:
            s.stream.disable()
        self.settings.mode = "idle"

    def _enable_stream(self) -> None:
        stream = self._session().stream
        if not stream.enabled:
            stream.configure()
            stream.enable()

    def resume(self, mode: str) -> None:
        if mode == "triggered":
            self.arm_trigger()
        elif mode == "streaming":
            self.start_stream(self.settings.fps)

    def arm_trigger(self) -> None:
        f = self._session().features
        self.halt()
        if f.has("TriggerSelector"):
            f.set("TriggerSelector", "FrameStart")
        f.set("AcquisitionMode", "Continuous")
        f.set("TriggerMode", "On")
        f.set("TriggerSource", "Software")
        self._enable_stream()
        f.execute("AcquisitionStart")
        self.settings.mode = "triggered"

    def snap(self, timeout: float | None) -> Frame:
        self.trigger()
        return self.read_triggered(timeout)

    def trigger(self) -> None:
        """The first half of :meth:`snap`: the exposure starts (its frame is read with
        :meth:`read_triggered`; the stage may move once the exposure has ended)."""
        if self.settings.mode != "triggered" or self.rearm:
            # After a failed snap a late frame may still be on its way: stopping and
            # starting acquisition discards it, so no snap returns an older trigger's frame.
            self.arm_trigger()
            self.rearm = False
        self._session().features.execute("TriggerSoftware")

    def read_triggered(self, timeout: float | None) -> Frame:
        """The second half of :meth:`snap`: the triggered frame after its readout."""
        try:
            return self.read(timeout)
        except (DeviceTimeout, FrameIncomplete, FrameCorrupt):
            self.rearm = True
            raise

    def start_stream(self, fps: float | None) -> None:
        f = self._session().features
        self.halt()
        if f.has("TriggerSelector"):
            f.set("TriggerSelector", "FrameStart")
        f.set("TriggerMode", "Off")
        f.set("AcquisitionMode", "Continuous")
        if f.has("AcquisitionFrameRate"):
            lo, hi = f.range("AcquisitionFrameRate")
            if fps is not None and not (math.isfinite(fps) and fps > 0):
                raise CameraError(f"frame rate {fps!r} is not positive", device=self.name)
            self.stream_fps = min(max(fps or hi, lo), hi)
            f.set("AcquisitionFrameRate", self.stream_fps)
        else:
            self.stream_fps = fps
        self._enable_stream()
        f.execute("AcquisitionStart")
        self.settings.mode = "streaming"
        self.settings.fps = fps

    # -- frames -------------------------------------------------------------------------
    def _frame_timeout(self) -> float:
        exposure = self.settings.exposure_s
        if exposure is None:
            exposure = float(self._session().features.get("ExposureTime")) * 1e-6
        period = 1.0 / self.settings.fps if self.settings.fps else 0.0
        return exposure + period + self.timeout_s

    def read(self, timeout: float | None) -> Frame:
        s = self._session()
        f = s.features
        fmt = u3v.pixel_format(str(f.get("PixelFormat")))
        wait = self._frame_timeout() if timeout is None else timeout
        try:
            block = s.stream.read_block(wait, expect=(int(fmt), s.width, s.height))
        except DeviceTimeout as exc:
            hint = "; a stalled stream needs restart_stream()" if self.settings.mode == "streaming" else ""
            raise DeviceTimeout(
                f"no frame within {wait:.3g} s ({self.settings.mode}){hint}",
                device=self.name,
                command="snap" if self.settings.mode == "triggered" else "read_frame",
            ) from exc
        try:
            data = u3v.decode_image(block.payload, fmt, s.width, s.height)
        except CodecError as exc:
            raise FrameCorrupt(f"block {block.leader.block_id}: {exc}", device=self.name) from exc
        now = self.clock.monotonic()
        self.last_frame_at = now
        settings = self.settings
        return Frame(
            data=data,
            block_id=block.leader.block_id,
            timestamp_s=block.leader.timestamp * s.timestamp_ns_per_tick * 1e-9,
            exposure_s=settings.exposure_s
            if settings.exposure_s is not None
            else float(f.get("ExposureTime")) * 1e-6,
            gain=settings.gain if settings.gain is not None else float(f.get("Gain")),
            pixel_format=fmt.name,
            temperature_c=self.temperature_c(max_age=TEMPERATURE_MAX_AGE_S),
            host_time_s=now,
        )

    def temperature_c(self, max_age: float) -> float:
        now = self.clock.monotonic()
        if max_age > 0 and self._temperature is not None and now - self._temperature[0] <= max_age:
            return self._temperature[1]
        value = float(self._session().features.get("DeviceTemperature"))
        self._temperature = (now, value)
        return value

    # -- after a reconnect --------------------------------------------------------------
    def reapply(self) -> dict[str, Any]:
        """Apply the last settings to a freshly plugged device; returns what was applied."""
        wanted = self.settings
        mode = wanted.mode
        wanted.mode = "idle"  # the device came back powered on: nothing is running
        done: dict[str, Any] = {}
        if wanted.pixel_format is not None:
            self._session().features.set("PixelFormat", wanted.pixel_format)
            done["PixelFormat"] = wanted.pixel_format
        if wanted.exposure_s is not None or wanted.gain is not None:
            self.configure(wanted.exposure_s, wanted.gain)
            if wanted.exposure_s is not None:
                done["ExposureTime"] = wanted.exposure_s * 1e6
            if wanted.gain is not None:
                done["Gain"] = wanted.gain
        self.resume(mode)
        if mode != "idle":
            done["mode"] = mode
            done["TriggerMode"] = "On" if mode == "triggered" else "Off"
            if mode == "streaming":
                done["AcquisitionFrameRate"] = self.stream_fps
            done["stream"] = self._session().stream.plan
        return done
