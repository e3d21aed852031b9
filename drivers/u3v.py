"""A USB3 Vision camera (the TOUCAN, or any U3V camera with SFNC features) over pyusb.

::

    cam = U3VCamera.open(serial="TOUCAN-0001")             # a real camera (libusb)
    cam = U3VCamera.open(backend=SimUsbBackend(toucan), clock=vclock)   # the simulator
    cam.configure(exposure_s=0.02, gain=1.0)
    frame = cam.snap()                                      # one frame on a software trigger
    cam.start_stream(fps=30); frame = cam.read_frame(); cam.stop_stream()

Opening finds the device with ``usb.core.find`` (U3V interface class, optionally
vendor/product id and serial number), claims its interfaces, reads the bootstrap
registers, fetches the GenICam XML through the manifest and drives features by their
SFNC names through ``genicam.genapi``. After an unplug every call raises DeviceGone
until :meth:`U3VCamera.reconnect` finds the same serial again, re-applies the last
settings and reports what was lost.
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass, field
from typing import Any, TypedDict, Unpack

from m2s2hil.drivers.clock import SYSTEM_CLOCK, Clock
from m2s2hil.drivers.errors import (
    CameraError,
    DeviceError,
    DeviceGone,
    DeviceTimeout,
    FrameCorrupt,
    FrameIncomplete,
)
from m2s2hil.drivers.genicam_port import Features, fetch_device_xml
from m2s2hil.drivers.interfaces import Frame
from m2s2hil.drivers.u3v_control import GenCPControl
from m2s2hil.drivers.u3v_stream import StreamChannel, StreamPlan
from m2s2hil.drivers.u3v_usb import U3VLink, find_u3v_devices
from m2s2hil.protocols import u3v
from m2s2hil.protocols.errors import CodecError

log = logging.getLogger(__name__)

TEMPERATURE_MAX_AGE_S = 1.0  # frames reuse a temperature read this recently
RECONNECT_POLL_S = 0.1


@dataclass
class CameraSettings:
    """What the host asked for last; re-applied after a reconnect."""

    exposure_s: float | None = None
    gain: float | None = None
    pixel_format: str | None = None
    mode: str = "idle"  # "idle", "triggered" (snap) or "streaming"
    fps: float | None = None


@dataclass(frozen=True)
class ReconnectReport:
    serial: str | None
    downtime_s: float
    lost_block_ids: tuple[int, ...]  # block ids of the old session that never arrived
    reapplied: dict[str, Any] = field(default_factory=dict)
    resumed_mode: str = "idle"


@dataclass
class _Session:
    """Everything that belongs to one plug-in of the device."""

    link: U3VLink
    control: GenCPControl
    features: Features
    stream: StreamChannel
    manifest: u3v.ManifestEntry
    timestamp_ns_per_tick: float
    width: int
    height: int


class CameraOptions(TypedDict, total=False):
    """The keywords of :class:`U3VCamera` (and so of :meth:`U3VCamera.open`)."""

    backend: Any
    vendor_id: int | None
    product_id: int | None
    serial: str | None
    clock: Clock
    timeout_s: float
    name: str


class U3VCamera:
    """drivers.interfaces.Camera over USB3 Vision. Build it with :meth:`open`."""

    def __init__(
        self,
        *,
        backend: Any = None,
        vendor_id: int | None = None,
        product_id: int | None = None,
        serial: str | None = None,
        clock: Clock = SYSTEM_CLOCK,
        timeout_s: float = 2.0,
        name: str = "camera",
    ) -> None:
        self.name = name
        self.clock = clock
        self.timeout_s = float(timeout_s)
        self._backend = backend
        self._vendor_id = vendor_id
        self._product_id = product_id
        self._serial = serial
        self._lock = threading.RLock()
        self._s: _Session | None = None
        self.settings = CameraSettings()
        self._gone_at: float | None = None
        self._gone_in_read = False
        self._rearm = False
        self._last_frame_at: float | None = None
        self._stream_fps: float | None = None  # the frame rate the device was given
        self._temperature: tuple[float, float] | None = None  # (clock time, value)
        self._missing_before: list[int] = []
        self._pending_lost: list[int] | None = None
        self.reconnects: list[ReconnectReport] = []
        self.last_reconnect: ReconnectReport | None = None

    @classmethod
    def open(cls, **options: Unpack[CameraOptions]) -> U3VCamera:
        """Find and open a U3V camera (``backend=None``: a real one through libusb); takes
        the constructor's keywords."""
        cam = cls(**options)
        cam._connect()
        return cam

    # -- connection ---------------------------------------------------------------------
    def _connect(self) -> None:
        matches = list(
            find_u3v_devices(
                backend=self._backend,
                vendor_id=self._vendor_id,
                product_id=self._product_id,
                serial=self._serial,
            )
        )
        if not matches:
            raise DeviceGone(
                f"no USB3 Vision camera found ({self._filters()})", device=self.name, command="open"
            )
        if len(matches) > 1:
            log.warning(
                "%s: %d U3V cameras match (%s); using serial %s",
                self.name,
                len(matches),
                ", ".join(str(sn) for _, sn in matches),
                matches[0][1],
            )
        dev, serial = matches[0]
        link = U3VLink.open(dev, serial, name=self.name)
        try:
            self._s = self._bootstrap(link)
        except BaseException:
            link.close()
            raise
        self._serial = self._serial or serial
        self._gone_at = None
        self._rearm = False

    def _filters(self) -> str:
        parts = [
            f"{k}={v}"
            for k, v in (
                ("vendor_id", self._vendor_id),
                ("product_id", self._product_id),
                ("serial", self._serial),
            )
            if v is not None
        ]
        return ", ".join(parts) or "any"

    def _bootstrap(self, link: U3VLink) -> _Session:
        control = GenCPControl(link, self.clock, name=self.name, timeout_s=self.timeout_s)
        sbrm = control.read_u64(u3v.ABRM.SBRM_ADDRESS)
        control.set_limits(
            max_command=control.read_u32(sbrm + u3v.SBRM.MAX_COMMAND_TRANSFER_LENGTH),
            max_ack=control.read_u32(sbrm + u3v.SBRM.MAX_ACK_TRANSFER_LENGTH),
            response_time_ms=control.read_u32(u3v.ABRM.MAX_DEVICE_RESPONSE_TIME),
        )
        if control.read_u32(sbrm + u3v.SBRM.NUM_STREAM_CHANNELS) < 1:
            raise CameraError("the device has no stream channel", device=self.name)
        sirm = control.read_u64(sbrm + u3v.SBRM.SIRM_ADDRESS)
        tick = control.read_u64(u3v.ABRM.TIMESTAMP_INCREMENT) or 1
        xml, manifest = fetch_device_xml(control)
        features = Features(xml, control)
        stream = StreamChannel(link, control, sirm, self.clock, name=self.name)
        # A previous session may have left the camera streaming.
        if features.has("AcquisitionStop"):
            features.execute("AcquisitionStop")
        stream.disable()
        width, height = int(features.get("Width")), int(features.get("Height"))
        return _Session(link, control, features, stream, manifest, float(tick), width, height)

    @property
    def _session(self) -> _Session:
        if self._gone_at is not None:
            raise DeviceGone("the camera is gone; call reconnect()", device=self.name)
        if self._s is None:
            raise CameraError("the camera is closed", device=self.name)
        return self._s

    def _guard(self, fn, *args, in_read: bool = False, **kw):
        """Run ``fn``; a DeviceGone marks the session dead until reconnect()."""
        try:
            return fn(*args, **kw)
        except DeviceGone:
            if self._gone_at is None:
                self._gone_at = self.clock.monotonic()
                self._gone_in_read = in_read
            raise

    # -- information --------------------------------------------------------------------
    @property
    def serial(self) -> str | None:
        return self._serial

    @property
    def features(self) -> Features:
        """The GenICam features, for anything beyond the Camera interface."""
        return self._session.features

    @property
    def control(self) -> GenCPControl:
        """Raw GenCP register access (bootstrap registers, diagnostics)."""
        return self._session.control

    @property
    def device_info(self) -> u3v.DeviceInfoDescriptor | None:
        """The U3V device-info descriptor of the control interface, if the device has one."""
        return self._session.link.device_info

    @property
    def stream_plan(self) -> StreamPlan | None:
        """The transfer plan written to the SIRM (None before the first acquisition)."""
        return self._session.stream.plan

    @property
    def width(self) -> int:
        return self._session.width

    @property
    def height(self) -> int:
        return self._session.height

    @property
    def pixel_format(self) -> str:
        return str(self._guard(self._session.features.get, "PixelFormat"))

    @property
    def manifest(self) -> u3v.ManifestEntry:
        return self._session.manifest

    @property
    def missing_block_ids(self) -> list[int]:
        """Block ids that never arrived: gaps in the stream and frames lost to unplugs."""
        current = self._s.stream.missing_block_ids if self._s is not None else []
        return self._missing_before + current

    # -- settings -----------------------------------------------------------------------
    def configure(self, *, exposure_s: float | None = None, gain: float | None = None) -> None:
        with self._lock:
            self._guard(self._configure, exposure_s, gain)

    def _configure(self, exposure_s: float | None, gain: float | None) -> None:
        f = self._session.features
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
        """Switch the pixel format (stops acquisition and re-plans the stream)."""
        with self._lock:
            self._guard(self._set_pixel_format, name)

    def _set_pixel_format(self, name: str) -> None:
        try:
            u3v.pixel_format(name)
        except CodecError as exc:
            raise CameraError(
                f"pixel format {name!r} cannot be decoded by this driver", device=self.name
            ) from exc
        mode = self.settings.mode
        self._halt()
        self._session.features.set("PixelFormat", name)
        self.settings.pixel_format = name
        self._resume(mode)

    # -- acquisition --------------------------------------------------------------------
    def _halt(self) -> None:
        """Acquisition stopped and the stream interface disabled."""
        s = self._session
        if self.settings.mode != "idle":
            s.features.execute("AcquisitionStop")
        if s.stream.enabled:
            s.stream.disable()
        self.settings.mode = "idle"

    def _enable_stream(self) -> None:
        stream = self._session.stream
        if not stream.enabled:
            stream.configure()
            stream.enable()

    def _resume(self, mode: str) -> None:
        if mode == "triggered":
            self._arm_trigger()
        elif mode == "streaming":
            self._start_stream(self.settings.fps)

    def _arm_trigger(self) -> None:
        f = self._session.features
        self._halt()
        if f.has("TriggerSelector"):
            f.set("TriggerSelector", "FrameStart")
        f.set("AcquisitionMode", "Continuous")
        f.set("TriggerMode", "On")
        f.set("TriggerSource", "Software")
        self._enable_stream()
        f.execute("AcquisitionStart")
        self.settings.mode = "triggered"

    def snap(self, timeout: float | None = None) -> Frame:
        with self._lock:
            return self._guard(self._snap, timeout, in_read=True)

    def _snap(self, timeout: float | None) -> Frame:
        if self.settings.mode != "triggered" or self._rearm:
            # After a failed snap a late frame may still be on its way: stopping and
            # starting acquisition discards it, so no snap returns an older trigger's frame.
            self._arm_trigger()
            self._rearm = False
        self._session.features.execute("TriggerSoftware")
        try:
            return self._read(timeout)
        except (DeviceTimeout, FrameIncomplete, FrameCorrupt):
            self._rearm = True
            raise

    def start_stream(self, fps: float | None = None) -> None:
        with self._lock:
            self._guard(self._start_stream, fps)

    def _start_stream(self, fps: float | None) -> None:
        f = self._session.features
        self._halt()
        if f.has("TriggerSelector"):
            f.set("TriggerSelector", "FrameStart")
        f.set("TriggerMode", "Off")
        f.set("AcquisitionMode", "Continuous")
        if f.has("AcquisitionFrameRate"):
            lo, hi = f.range("AcquisitionFrameRate")
            if fps is not None and not (math.isfinite(fps) and fps > 0):
                raise CameraError(f"frame rate {fps!r} is not positive", device=self.name)
            self._stream_fps = min(max(fps or hi, lo), hi)
            f.set("AcquisitionFrameRate", self._stream_fps)
        else:
            self._stream_fps = fps
        self._enable_stream()
        f.execute("AcquisitionStart")
        self.settings.mode = "streaming"
        self.settings.fps = fps

    def read_frame(self, timeout: float | None = None) -> Frame:
        with self._lock:
            if self.settings.mode != "streaming":
                raise CameraError("read_frame() without start_stream()", device=self.name)
            return self._guard(self._read, timeout, in_read=True)

    def restart_stream(self) -> None:
        """Stop and start acquisition again (the way out of a stalled stream)."""
        with self._lock:
            mode = self.settings.mode
            self._guard(self._halt)
            self._guard(self._resume, mode)

    def stop_stream(self) -> None:
        with self._lock:
            if self.settings.mode == "streaming":
                self._guard(self._halt)

    def _frame_timeout(self) -> float:
        exposure = self.settings.exposure_s
        if exposure is None:
            exposure = float(self._session.features.get("ExposureTime")) * 1e-6
        period = 1.0 / self.settings.fps if self.settings.fps else 0.0
        return exposure + period + self.timeout_s

    def _read(self, timeout: float | None) -> Frame:
        s = self._session
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
        self._last_frame_at = now
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
            temperature_c=self._temperature_c(max_age=TEMPERATURE_MAX_AGE_S),
            host_time_s=now,
        )

    # -- temperature --------------------------------------------------------------------
    def temperature_c(self) -> float:
        with self._lock:
            return self._guard(self._temperature_c, max_age=0.0)

    def _temperature_c(self, max_age: float) -> float:
        now = self.clock.monotonic()
        if max_age > 0 and self._temperature is not None and now - self._temperature[0] <= max_age:
            return self._temperature[1]
        value = float(self._session.features.get("DeviceTemperature"))
        self._temperature = (now, value)
        return value

    # -- recovery -----------------------------------------------------------------------
    def reconnect(self, timeout_s: float | None = None) -> ReconnectReport:
        """Find the same camera again, re-apply the last settings, report what was lost."""
        with self._lock:
            gone_at = self._gone_at if self._gone_at is not None else self.clock.monotonic()
            if self._pending_lost is None:  # kept across failed attempts
                self._pending_lost = self._lost_block_ids(gone_at)
            self._gone_at = gone_at  # gone until a connect succeeds
            self._drop_session()
            deadline = self.clock.monotonic() + (
                timeout_s if timeout_s is not None else max(10.0, 5 * self.timeout_s)
            )
            while True:
                try:
                    self._connect()
                    break
                except (DeviceGone, DeviceTimeout) as exc:
                    if self.clock.monotonic() >= deadline:
                        raise DeviceGone(
                            f"did not come back within the reconnect timeout: {exc.detail}",
                            device=self.name,
                            command="reconnect",
                        ) from exc
                    self.clock.sleep(RECONNECT_POLL_S)
            lost, self._pending_lost = self._pending_lost, None
            reapplied = self._guard(self._reapply)
            report = ReconnectReport(
                serial=self._serial,
                downtime_s=self.clock.monotonic() - gone_at,
                lost_block_ids=tuple(lost),
                reapplied=reapplied,
                resumed_mode=self.settings.mode,
            )
            self._missing_before += lost
            self.reconnects.append(report)
            self.last_reconnect = report
            log.warning(
                "%s: reconnected after %.3g s; lost block ids %s; re-applied %s",
                self.name,
                report.downtime_s,
                list(lost),
                reapplied,
            )
            return report

    def _lost_block_ids(self, gone_at: float) -> list[int]:
        if self._s is None or not self._gone_in_read or self._gone_at is None:
            return []
        last = self._s.stream.last_block_id or 0
        n = 1
        fps = self._stream_fps
        if self.settings.mode == "streaming" and self._last_frame_at is not None and fps:
            # frames the host should have had between its last frame and the loss
            n = max(1, math.floor((gone_at - self._last_frame_at) * fps + 1e-9))
        return list(range(last + 1, last + 1 + n))

    def _reapply(self) -> dict[str, Any]:
        wanted = self.settings
        mode = wanted.mode
        wanted.mode = "idle"  # the device came back powered on: nothing is running
        done: dict[str, Any] = {}
        if wanted.pixel_format is not None:
            self._session.features.set("PixelFormat", wanted.pixel_format)
            done["PixelFormat"] = wanted.pixel_format
        if wanted.exposure_s is not None or wanted.gain is not None:
            self._configure(wanted.exposure_s, wanted.gain)
            if wanted.exposure_s is not None:
                done["ExposureTime"] = wanted.exposure_s * 1e6
            if wanted.gain is not None:
                done["Gain"] = wanted.gain
        self._resume(mode)
        if mode != "idle":
            done["mode"] = mode
            done["TriggerMode"] = "On" if mode == "triggered" else "Off"
            if mode == "streaming":
                done["AcquisitionFrameRate"] = self._stream_fps
            done["stream"] = self._session.stream.plan
        return done

    def _drop_session(self) -> None:
        s, self._s = self._s, None
        if s is None:
            return
        self._missing_before += s.stream.missing_block_ids  # keep the record past the session
        try:
            s.features.close()
        finally:
            s.link.close()

    # -- shutdown -----------------------------------------------------------------------
    def close(self) -> None:
        with self._lock:
            if self._s is None:
                return
            if self._gone_at is None:
                try:
                    self._halt()
                except DeviceError as exc:  # closing must not fail on a sick camera
                    log.warning("%s: could not stop acquisition on close: %s", self.name, exc)
            self._drop_session()

    def __enter__(self) -> U3VCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
