"""One plug-in of a USB3 Vision camera: finding it, bootstrapping it, closing it.

:func:`open_session` finds the device with ``usb.core.find`` (U3V interface class,
optionally vendor/product id and serial number), claims its interfaces, reads the
bootstrap registers (SBRM limits, the SIRM address, the timestamp tick), fetches the
GenICam XML through the manifest and builds the feature map and the stream channel.
A camera left streaming by a previous session is stopped. Everything it opened is
held by one :class:`U3VSession`, so a reconnect replaces it whole.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

from m2s2hil.drivers.clock import Clock
from m2s2hil.drivers.errors import CameraError, DeviceGone
from m2s2hil.drivers.genicam_port import Features, fetch_device_xml
from m2s2hil.drivers.u3v_control import GenCPControl
from m2s2hil.drivers.u3v_stream import StreamChannel
from m2s2hil.drivers.u3v_usb import U3VLink, find_u3v_devices
from m2s2hil.protocols import u3v

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DeviceFilter:
    """Which camera to open: any field left None matches anything."""

    backend: Any = None
    vendor_id: int | None = None
    product_id: int | None = None
    serial: str | None = None

    def describe(self) -> str:
        parts = [
            f"{k}={v}"
            for k, v in (
                ("vendor_id", self.vendor_id),
                ("product_id", self.product_id),
                ("serial", self.serial),
            )
            if v is not None
        ]
        return ", ".join(parts) or "any"


@dataclass
class U3VSession:
    """Everything that belongs to one plug-in of the device."""

    link: U3VLink
    control: GenCPControl
    features: Features
    stream: StreamChannel
    manifest: u3v.ManifestEntry
    timestamp_ns_per_tick: float
    width: int
    height: int
    serial: str | None

    def close(self) -> None:
        try:
            self.features.close()
        finally:
            self.link.close()


def open_session(which: DeviceFilter, clock: Clock, *, name: str, timeout_s: float) -> U3VSession:
    """Find the first matching camera and bootstrap it; DeviceGone when none matches."""
    matches = list(
        find_u3v_devices(
            backend=which.backend, vendor_id=which.vendor_id, product_id=which.product_id, serial=which.serial
        )
    )
    if not matches:
        raise DeviceGone(f"no USB3 Vision camera found ({which.describe()})", device=name, command="open")
    if len(matches) > 1:
        log.warning(
            "%s: %d U3V cameras match (%s); using serial %s",
            name,
            len(matches),
            ", ".join(str(sn) for _, sn in matches),
            matches[0][1],
        )
    dev, serial = matches[0]
    link = U3VLink.open(dev, serial, name=name)
    try:
        return _bootstrap(link, serial, clock, name=name, timeout_s=timeout_s)
    except BaseException:
        link.close()
        raise


def _bootstrap(link: U3VLink, serial: str | None, clock: Clock, *, name: str, timeout_s: float) -> U3VSession:
    control = GenCPControl(link, clock, name=name, timeout_s=timeout_s)
    sbrm = control.read_u64(u3v.ABRM.SBRM_ADDRESS)
    control.set_limits(
        max_command=control.read_u32(sbrm + u3v.SBRM.MAX_COMMAND_TRANSFER_LENGTH),
        max_ack=control.read_u32(sbrm + u3v.SBRM.MAX_ACK_TRANSFER_LENGTH),
        response_time_ms=control.read_u32(u3v.ABRM.MAX_DEVICE_RESPONSE_TIME),
    )
    if control.read_u32(sbrm + u3v.SBRM.NUM_STREAM_CHANNELS) < 1:
        raise CameraError("the device has no stream channel", device=name)
    sirm = control.read_u64(sbrm + u3v.SBRM.SIRM_ADDRESS)
    tick = control.read_u64(u3v.ABRM.TIMESTAMP_INCREMENT) or 1
    xml, manifest = fetch_device_xml(control)
    features = Features(xml, control)
    stream = StreamChannel(link, control, sirm, clock, name=name)
    # A previous session may have left the camera streaming.
    if features.has("AcquisitionStop"):
        features.execute("AcquisitionStop")
    stream.disable()
    width, height = int(features.get("Width")), int(features.get("Height"))
    return U3VSession(link, control, features, stream, manifest, float(tick), width, height, serial)
