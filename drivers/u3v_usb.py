"""Finding and opening USB3 Vision devices with pyusb, and their three bulk pipes.

Discovery goes through ``usb.core.find``: with ``backend=None`` pyusb picks libusb and
finds real cameras; with a simulated backend the same code finds simulated ones.
USB errors become typed device errors: ENODEV -> DeviceGone, a timed-out transfer ->
DeviceTimeout, anything else -> CameraError.
"""

from __future__ import annotations

import array
import errno
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import usb.core
import usb.util
from m2s2hil.drivers.errors import CameraError, DeviceGone, DeviceTimeout
from m2s2hil.protocols import u3v
from m2s2hil.protocols.errors import CodecError

log = logging.getLogger(__name__)

_NO_DEVICE_CODES = {-4}  # LIBUSB_ERROR_NO_DEVICE


def is_gone(exc: usb.core.USBError) -> bool:
    return exc.errno == errno.ENODEV or exc.backend_error_code in _NO_DEVICE_CODES


def _u3v_interface(cfg: Any, protocol: int) -> Any:
    return usb.util.find_descriptor(
        cfg,
        bInterfaceClass=u3v.INTERFACE_CLASS,
        bInterfaceSubClass=u3v.INTERFACE_SUBCLASS,
        bInterfaceProtocol=protocol,
    )


def is_u3v_device(dev: Any) -> bool:
    """A device with a U3V control interface (class 0xEF, subclass 0x05, protocol 0)."""
    try:
        return any(_u3v_interface(cfg, u3v.InterfaceProtocol.CONTROL) is not None for cfg in dev)
    except (usb.core.USBError, ValueError, IndexError) as exc:
        log.debug("cannot read descriptors of %s: %s", dev, exc)
        return False


def read_serial(dev: Any) -> str | None:
    """The iSerialNumber string, or None if it cannot be read (permissions, no strings)."""
    try:
        return dev.serial_number
    except (usb.core.USBError, ValueError, NotImplementedError) as exc:
        log.debug("cannot read the serial number of %s: %s", dev, exc)
        return None


def find_u3v_devices(
    *,
    backend: Any = None,
    vendor_id: int | None = None,
    product_id: int | None = None,
    serial: str | None = None,
) -> Iterator[tuple[Any, str | None]]:
    """(pyusb device, serial) of every U3V device that matches the filters."""
    kwargs: dict[str, int] = {}
    if vendor_id is not None:
        kwargs["idVendor"] = vendor_id
    if product_id is not None:
        kwargs["idProduct"] = product_id
    try:
        found = usb.core.find(find_all=True, backend=backend, custom_match=is_u3v_device, **kwargs)
        devices = list(found)
    except usb.core.NoBackendError as exc:
        raise CameraError(f"no USB backend (is libusb installed?): {exc}", device="usb") from exc
    for dev in devices:
        sn = read_serial(dev)
        if serial is not None and sn != serial:
            continue
        yield dev, sn


@dataclass
class U3VLink:
    """An opened U3V device: the control and stream pipes, interfaces claimed."""

    dev: Any
    serial: str | None
    device_info: u3v.DeviceInfoDescriptor | None
    control_out: Any
    control_in: Any
    stream_in: Any | None
    name: str = "camera"

    @classmethod
    def open(cls, dev: Any, serial: str | None, *, name: str = "camera") -> U3VLink:
        try:
            try:
                cfg = dev.get_active_configuration()
            except usb.core.USBError as exc:
                if is_gone(exc):
                    raise
                dev.set_configuration()
                cfg = dev.get_active_configuration()
            ctrl = _u3v_interface(cfg, u3v.InterfaceProtocol.CONTROL)
            stream = _u3v_interface(cfg, u3v.InterfaceProtocol.STREAM)
            if ctrl is None:
                raise CameraError("the device has no U3V control interface", device=name)
            out_ep = usb.util.find_descriptor(ctrl, custom_match=_direction(usb.util.ENDPOINT_OUT))
            in_ep = usb.util.find_descriptor(ctrl, custom_match=_direction(usb.util.ENDPOINT_IN))
            stream_ep = (
                None
                if stream is None
                else usb.util.find_descriptor(stream, custom_match=_direction(usb.util.ENDPOINT_IN))
            )
            if out_ep is None or in_ep is None:
                raise CameraError("the U3V control interface lacks a bulk IN/OUT pair", device=name)
            usb.util.claim_interface(dev, ctrl)
            if stream is not None:
                usb.util.claim_interface(dev, stream)
        except usb.core.USBError as exc:
            raise _translate(exc, name, "open") from exc
        info = None
        try:
            info = u3v.find_device_info(bytes(ctrl.extra_descriptors))
        except CodecError as exc:
            log.warning("%s: unreadable U3V device-info descriptor: %s", name, exc)
        return cls(dev, serial, info, out_ep, in_ep, stream_ep, name)

    def write_control(self, data: bytes, timeout_s: float) -> None:
        try:
            n = self.control_out.write(data, _ms(timeout_s))
        except usb.core.USBError as exc:
            raise _translate(exc, self.name, "control write") from exc
        if n != len(data):
            raise CameraError(f"control write sent {n} of {len(data)} bytes", device=self.name)

    def read_control(self, size: int, timeout_s: float) -> bytes:
        try:
            return bytes(self.control_in.read(size, _ms(timeout_s)))
        except usb.core.USBError as exc:
            raise _translate(exc, self.name, "control read") from exc

    def read_stream(self, buf: array.array, timeout_s: float) -> int:
        """One stream transfer into ``buf``; returns its length."""
        if self.stream_in is None:
            raise CameraError("the device has no U3V streaming interface", device=self.name)
        try:
            return self.stream_in.read(buf, _ms(timeout_s))
        except usb.core.USBError as exc:
            raise _translate(exc, self.name, "stream read") from exc

    def close(self) -> None:
        """Release the interfaces and the handle (never raises: the device may be gone)."""
        try:
            usb.util.dispose_resources(self.dev)
        except (usb.core.USBError, ValueError) as exc:
            log.debug("%s: dispose failed: %s", self.name, exc)


def _direction(direction: int):
    return lambda e: usb.util.endpoint_direction(e.bEndpointAddress) == direction


def _ms(timeout_s: float) -> int:
    # libusb treats 0 as "forever": never pass it.
    return max(1, round(timeout_s * 1000))


def _translate(exc: usb.core.USBError, device: str, what: str) -> Exception:
    if is_gone(exc):
        return DeviceGone(f"USB device vanished during {what}: {exc}", device=device, command=what)
    if isinstance(exc, usb.core.USBTimeoutError) or exc.errno == errno.ETIMEDOUT:
        return DeviceTimeout(f"{what} timed out", device=device, command=what)
    return CameraError(f"USB error during {what}: {exc}", device=device, command=what)
