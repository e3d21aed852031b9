"""A USB3 Vision camera (the TOUCAN, or any U3V camera with SFNC features) over pyusb.

::

    cam = U3VCamera.open(serial="TOUCAN-0001")             # a real camera (libusb)
    cam = U3VCamera.open(backend=SimUsbBackend(toucan), clock=vclock)   # the simulator
    cam.configure(exposure_s=0.02, gain=1.0)
    frame = cam.snap()                                      # one frame on a software trigger
    cam.start_stream(fps=30); frame = cam.read_frame(); cam.stop_stream()

The camera is put together from parts: finding and bootstrapping a device
(:mod:`~m2s2hil.drivers.u3v_session`), GenCP register access
(:mod:`~m2s2hil.drivers.u3v_control`), features by their SFNC names through
``genicam.genapi`` (:mod:`~m2s2hil.drivers.genicam_port`), the stream channel
(:mod:`~m2s2hil.drivers.u3v_stream`) and acquisition modes and frames
(:mod:`~m2s2hil.drivers.u3v_acquisition`). This class serialises calls and handles
unplugs: after one every call raises DeviceGone
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
from m2s2hil.drivers.errors import CameraError, DeviceError, DeviceGone, DeviceTimeout
from m2s2hil.drivers.genicam_port import Features
from m2s2hil.drivers.interfaces import Frame
from m2s2hil.drivers.u3v_acquisition import Acquisition, CameraSettings
from m2s2hil.drivers.u3v_control import GenCPControl
from m2s2hil.drivers.u3v_session import DeviceFilter, U3VSession, open_session
from m2s2hil.drivers.u3v_stream import StreamPlan
from m2s2hil.protocols import u3v

log = logging.getLogger(__name__)

RECONNECT_POLL_S = 0.1


@dataclass(frozen=True)
class ReconnectReport:
    serial: str | None
    downtime_s: float
    lost_block_ids: tuple[int, ...]  # block ids of the old session that never arrived
    reapplied: dict[str, Any] = field(default_factory=dict)
    resumed_mode: str = "idle"


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
    """drivers.interfaces.Camera over USB3 Vision. Build it with :meth:`open`.

    The facade: it serialises calls, owns the session of the current plug-in
    (:mod:`~m2s2hil.drivers.u3v_session`), hands acquisition to
    :class:`~m2s2hil.drivers.u3v_acquisition.Acquisition` and handles unplugs.
    """

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
        self._s: U3VSession | None = None
        self._acq = Acquisition(lambda: self._session, clock, name=name, timeout_s=self.timeout_s)
        self._gone_at: float | None = None
        self._gone_in_read = False
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
        which = DeviceFilter(self._backend, self._vendor_id, self._product_id, self._serial)
        self._s = open_session(which, self.clock, name=self.name, timeout_s=self.timeout_s)
        self._serial = self._serial or self._s.serial
        self._gone_at = None
        self._acq.rearm = False

    @property
    def _session(self) -> U3VSession:
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
    def settings(self) -> CameraSettings:
        """What the host asked for last (re-applied after a reconnect)."""
        return self._acq.settings

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

    # -- settings and acquisition -------------------------------------------------------
    def configure(self, *, exposure_s: float | None = None, gain: float | None = None) -> None:
        with self._lock:
            self._guard(self._acq.configure, exposure_s, gain)

    def set_pixel_format(self, name: str) -> None:
        """Switch the pixel format (stops acquisition and re-plans the stream)."""
        with self._lock:
            self._guard(self._acq.set_pixel_format, name)

    def snap(self, timeout: float | None = None) -> Frame:
        with self._lock:
            return self._guard(self._acq.snap, timeout, in_read=True)

    def trigger(self) -> None:
        """Start one triggered exposure; :meth:`read_triggered` returns its frame
        (:class:`~m2s2hil.drivers.interfaces.SplitSnap`: the stage may move during readout)."""
        with self._lock:
            self._guard(self._acq.trigger, in_read=True)

    def read_triggered(self, timeout: float | None = None) -> Frame:
        with self._lock:
            return self._guard(self._acq.read_triggered, timeout, in_read=True)

    def start_stream(self, fps: float | None = None) -> None:
        with self._lock:
            self._guard(self._acq.start_stream, fps)

    def read_frame(self, timeout: float | None = None) -> Frame:
        with self._lock:
            if self.settings.mode != "streaming":
                raise CameraError("read_frame() without start_stream()", device=self.name)
            return self._guard(self._acq.read, timeout, in_read=True)

    def restart_stream(self) -> None:
        """Stop and start acquisition again (the way out of a stalled stream)."""
        with self._lock:
            mode = self.settings.mode
            self._guard(self._acq.halt)
            self._guard(self._acq.resume, mode)

    def stop_stream(self) -> None:
        with self._lock:
            if self.settings.mode == "streaming":
                self._guard(self._acq.halt)

    def temperature_c(self) -> float:
        with self._lock:
            return self._guard(self._acq.temperature_c, max_age=0.0)

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
            reapplied = self._guard(self._acq.reapply)
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
        fps = self._acq.stream_fps
        if self.settings.mode == "streaming" and self._acq.last_frame_at is not None and fps:
            # frames the host should have had between its last frame and the loss
            n = max(1, math.floor((gone_at - self._acq.last_frame_at) * fps + 1e-9))
        return list(range(last + 1, last + 1 + n))

    def _drop_session(self) -> None:
        s, self._s = self._s, None
        if s is None:
            return
        self._missing_before += s.stream.missing_block_ids  # keep the record past the session
        s.close()

    # -- shutdown -----------------------------------------------------------------------
    def close(self) -> None:
        with self._lock:
            if self._s is None:
                return
            if self._gone_at is None:
                try:
                    self._acq.halt()
                except DeviceError as exc:  # closing must not fail on a sick camera
                    log.warning("%s: could not stop acquisition on close: %s", self.name, exc)
            self._drop_session()

    def __enter__(self) -> U3VCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
