"""A pyusb backend that puts simulated USB3 Vision devices behind the real pyusb API.

``usb.core.find(backend=SimUsbBackend(camera))`` enumerates the simulated camera with
the descriptors a U3V device presents (class 0xEF/0x02/0x01, an interface association,
control / event / streaming interfaces of class 0xEF subclass 0x05, string descriptors
and the U3V device-info descriptor), and pyusb's ``Device.read``/``write`` reach the
device's endpoints. Errors are the ones libusb gives: ``USBError`` with errno ENODEV
for a vanished device, ``USBTimeoutError`` (ETIMEDOUT) for a transfer that timed out,
EOVERFLOW for a buffer smaller than the transfer, EPIPE for a stalled request, EBUSY
for an interface claimed through another handle.

Transfers wait on the device's clock, so with a virtual clock a timeout costs no wall
time. The backend is generic: any object with the :class:`SimU3VDevice` shape works.
"""

from __future__ import annotations

import array
import errno
import struct
import threading
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any, Protocol

import usb.backend
import usb.util
from m2s2hil.protocols.u3v_bootstrap import (
    DEVICE_CLASS,
    INTERFACE_CLASS,
    INTERFACE_SUBCLASS,
    DeviceInfoDescriptor,
    InterfaceProtocol,
)
from usb.core import USBError, USBTimeoutError

# Endpoint addresses of the simulated device.
EP_CONTROL_OUT = 0x01
EP_CONTROL_IN = 0x81
EP_EVENT_IN = 0x82
EP_STREAM_IN = 0x83

# libusb error codes (negative) as pyusb's libusb1 backend reports them.
_LIBUSB = {
    errno.ENODEV: (-4, "No such device (it may have been disconnected)"),
    errno.EBUSY: (-6, "Resource busy"),
    errno.ETIMEDOUT: (-7, "Operation timed out"),
    errno.EOVERFLOW: (-8, "Overflow"),
    errno.EPIPE: (-9, "Pipe error"),
    errno.EINVAL: (-2, "Invalid parameter"),
    errno.ENOENT: (-5, "Entity not found"),
}


def usb_error(code: int, detail: str = "") -> USBError:
    """The USBError libusb would raise for ``errno`` ``code``."""
    backend_code, text = _LIBUSB[code]
    cls = USBTimeoutError if code == errno.ETIMEDOUT else USBError
    return cls(f"{text}{': ' + detail if detail else ''}", backend_code, code)


# -- what a simulated device raises from its endpoint methods ---------------------------


class NoDevice(Exception):
    """The device is unplugged (or this handle belongs to a previous plug-in)."""


class Overflow(Exception):
    """The host's buffer is smaller than the transfer the device has ready."""


class Halted(Exception):
    """The endpoint is halted (STALL)."""


@dataclass(frozen=True)
class UsbIdentity:
    """What a device says about itself in its USB descriptors and strings."""

    vendor_id: int
    product_id: int
    manufacturer: str
    model: str
    serial: str
    family: str = ""
    device_version: str = ""
    manufacturer_info: str = ""
    guid: str = ""
    bcd_device: int = 0x0100


class SimU3VDevice(Protocol):
    """The device side the backend talks to."""

    clock: Any
    identity: UsbIdentity

    @property
    def present(self) -> bool: ...

    @property
    def epoch(self) -> int:
        """Increments on every re-enumeration; handles from an older epoch are dead."""
        ...

    def write_endpoint(self, ep: int, data: bytes) -> None: ...

    def take_endpoint(self, ep: int, max_len: int) -> bytes | memoryview | None:
        """The next transfer due now on IN endpoint ``ep`` (None if nothing is due)."""
        ...

    def next_due(self, ep: int) -> float | None:
        """Clock time at which ``ep`` will next have data, if known."""
        ...

    def clear_halt(self, ep: int) -> None: ...

    def usb_reset(self) -> None: ...


# -- descriptors ------------------------------------------------------------------------

# String indices: the device-info descriptor points at them.
_S_MANUFACTURER, _S_PRODUCT, _S_SERIAL, _S_GUID, _S_FAMILY, _S_VERSION, _S_INFO = range(1, 8)
_S_IF_CONTROL, _S_IF_EVENT, _S_IF_STREAM = 8, 9, 10


def _strings(ident: UsbIdentity) -> dict[int, str]:
    return {
        _S_MANUFACTURER: ident.manufacturer,
        _S_PRODUCT: ident.model,
        _S_SERIAL: ident.serial,
        _S_GUID: ident.guid,
        _S_FAMILY: ident.family,
        _S_VERSION: ident.device_version,
        _S_INFO: ident.manufacturer_info,
        _S_IF_CONTROL: "USB3 Vision Control",
        _S_IF_EVENT: "USB3 Vision Event",
        _S_IF_STREAM: "USB3 Vision Data",
    }


@dataclass
class _Endpoint:
    address: int
    attributes: int = usb.util.ENDPOINT_TYPE_BULK
    max_packet: int = 1024

    def raw(self) -> bytes:
        return struct.pack(
            "<BBBBHB", 7, usb.util.DESC_TYPE_ENDPOINT, self.address, self.attributes, self.max_packet, 0
        )

    def desc(self) -> SimpleNamespace:
        return SimpleNamespace(
            bLength=7, bDescriptorType=usb.util.DESC_TYPE_ENDPOINT, bEndpointAddress=self.address,
            bmAttributes=self.attributes, wMaxPacketSize=self.max_packet, bInterval=0, bRefresh=0,
            bSynchAddress=0, extra_descriptors=[],
        )  # fmt: skip


@dataclass
class _Interface:
    number: int
    protocol: int
    string: int
    endpoints: list[_Endpoint]
    extra: bytes = b""

    def raw(self) -> bytes:
        head = struct.pack("<BBBBBBBBB", 9, usb.util.DESC_TYPE_INTERFACE, self.number, 0,
                           len(self.endpoints), INTERFACE_CLASS, INTERFACE_SUBCLASS, self.protocol,
                           self.string)  # fmt: skip
        return head + self.extra + b"".join(e.raw() for e in self.endpoints)

    def desc(self) -> SimpleNamespace:
        return SimpleNamespace(
            bLength=9, bDescriptorType=usb.util.DESC_TYPE_INTERFACE, bInterfaceNumber=self.number,
            bAlternateSetting=0, bNumEndpoints=len(self.endpoints), bInterfaceClass=INTERFACE_CLASS,
            bInterfaceSubClass=INTERFACE_SUBCLASS, bInterfaceProtocol=self.protocol,
            iInterface=self.string, extra_descriptors=list(self.extra),
        )  # fmt: skip


@dataclass
class _Layout:
    """All descriptors of one simulated device, as pyusb objects and as raw bytes."""

    ident: UsbIdentity
    interfaces: list[_Interface] = field(default_factory=list)

    def __post_init__(self) -> None:
        info = DeviceInfoDescriptor(
            i_guid=_S_GUID, i_vendor=_S_MANUFACTURER, i_model=_S_PRODUCT, i_family=_S_FAMILY,
            i_device_version=_S_VERSION, i_manufacturer_info=_S_INFO, i_serial=_S_SERIAL,
        )  # fmt: skip
        self.interfaces = [
            _Interface(0, InterfaceProtocol.CONTROL, _S_IF_CONTROL,
                       [_Endpoint(EP_CONTROL_OUT), _Endpoint(EP_CONTROL_IN)], info.encode()),
            _Interface(1, InterfaceProtocol.EVENT, _S_IF_EVENT, [_Endpoint(EP_EVENT_IN)]),
            _Interface(2, InterfaceProtocol.STREAM, _S_IF_STREAM, [_Endpoint(EP_STREAM_IN)]),
        ]  # fmt: skip
        # Interface association: one function, three interfaces.
        self.iad = struct.pack("<BBBBBBBB", 8, 0x0B, 0, len(self.interfaces), INTERFACE_CLASS,
                               INTERFACE_SUBCLASS, 0, _S_PRODUCT)  # fmt: skip

    def device_raw(self) -> bytes:
        cls, sub, proto = DEVICE_CLASS
        i = self.ident
        return struct.pack("<BBHBBBBHHHBBBB", 18, usb.util.DESC_TYPE_DEVICE, 0x0320, cls, sub, proto, 9,
                           i.vendor_id, i.product_id, i.bcd_device, _S_MANUFACTURER, _S_PRODUCT,
                           _S_SERIAL, 1)  # fmt: skip

    def config_raw(self) -> bytes:
        body = self.iad + b"".join(intf.raw() for intf in self.interfaces)
        head = struct.pack("<BBHBBBBB", 9, usb.util.DESC_TYPE_CONFIG, 9 + len(body), len(self.interfaces),
                           1, 0, 0x80, 112)  # fmt: skip
        return head + body

    def device_desc(self, address: int) -> SimpleNamespace:
        cls, sub, proto = DEVICE_CLASS
        i = self.ident
        return SimpleNamespace(
            bLength=18, bDescriptorType=usb.util.DESC_TYPE_DEVICE, bcdUSB=0x0320, bDeviceClass=cls,
            bDeviceSubClass=sub, bDeviceProtocol=proto, bMaxPacketSize0=9, idVendor=i.vendor_id,
            idProduct=i.product_id, bcdDevice=i.bcd_device, iManufacturer=_S_MANUFACTURER,
            iProduct=_S_PRODUCT, iSerialNumber=_S_SERIAL, bNumConfigurations=1, address=address, bus=1,
            port_number=1, port_numbers=(1,), speed=usb.util.SPEED_SUPER,
        )  # fmt: skip

    def config_desc(self) -> SimpleNamespace:
        return SimpleNamespace(
            bLength=9, bDescriptorType=usb.util.DESC_TYPE_CONFIG, wTotalLength=len(self.config_raw()),
            bNumInterfaces=len(self.interfaces), bConfigurationValue=1, iConfiguration=0,
            bmAttributes=0x80, bMaxPower=112, extra_descriptors=list(self.iad),
        )  # fmt: skip


# -- the backend ------------------------------------------------------------------------


@dataclass(frozen=True)
class _DeviceRef:
    """What enumerate_devices yields: a device in one plug-in epoch."""

    device: Any
    epoch: int
    address: int


@dataclass(eq=False)
class _Handle:
    ref: _DeviceRef
    claimed: set[int] = field(default_factory=set)
    open: bool = True


class SimUsbBackend(usb.backend.IBackend):
    """pyusb backend serving simulated U3V devices (see the module docstring)."""

    def __init__(self, *devices: SimU3VDevice) -> None:
        super().__init__()
        self._devices: list[Any] = list(devices)
        self._layouts: dict[int, _Layout] = {}
        self._claims: dict[tuple[int, int], _Handle] = {}  # (id(device), interface) -> owner
        self._lock = threading.RLock()
        self.transfers = 0  # bulk transfers served, for tests and benchmarks

    # device list -----------------------------------------------------------------------
    def add(self, device: SimU3VDevice) -> None:
        with self._lock:
            self._devices.append(device)

    def remove(self, device: SimU3VDevice) -> None:
        with self._lock:
            self._devices = [d for d in self._devices if d is not device]

    def _layout(self, device: Any) -> _Layout:
        key = id(device)
        if key not in self._layouts:
            self._layouts[key] = _Layout(device.identity)
        return self._layouts[key]

    @staticmethod
    def _address(device: Any) -> int:
        return 2 + (int(device.epoch) % 120)  # a fresh address on every re-enumeration

    def _live(self, ref: _DeviceRef) -> Any:
        dev = ref.device
        if not dev.present or dev.epoch != ref.epoch:
            raise usb_error(errno.ENODEV)
        return dev

    def _check(self, handle: _Handle) -> Any:
        if not handle.open:
            raise usb_error(errno.EINVAL, "handle closed")
        return self._live(handle.ref)

    # enumeration and descriptors --------------------------------------------------------
    def enumerate_devices(self):
        with self._lock:
            devices = list(self._devices)
        return [_DeviceRef(d, d.epoch, self._address(d)) for d in devices if d.present]

    def get_parent(self, dev: _DeviceRef) -> None:
        return None

    def get_device_descriptor(self, dev: _DeviceRef) -> SimpleNamespace:
        return self._layout(dev.device).device_desc(dev.address)

    def get_configuration_descriptor(self, dev: _DeviceRef, config: int) -> SimpleNamespace:
        if config != 0:
            raise IndexError(f"invalid configuration index {config}")
        return self._layout(dev.device).config_desc()

    def get_interface_descriptor(self, dev: _DeviceRef, intf: int, alt: int, config: int) -> SimpleNamespace:
        interfaces = self._layout(dev.device).interfaces
        if config != 0 or not 0 <= intf < len(interfaces):
            raise IndexError(f"invalid interface index {intf}")
        if alt != 0:
            raise IndexError(f"invalid alternate setting index {alt}")
        return interfaces[intf].desc()

    def get_endpoint_descriptor(self, dev: _DeviceRef, ep: int, intf: int, alt: int, config: int):
        self.get_interface_descriptor(dev, intf, alt, config)
        endpoints = self._layout(dev.device).interfaces[intf].endpoints
        if not 0 <= ep < len(endpoints):
            raise IndexError(f"invalid endpoint index {ep}")
        return endpoints[ep].desc()

    # handles ----------------------------------------------------------------------------
    def open_device(self, dev: _DeviceRef) -> _Handle:
        self._live(dev)
        return _Handle(dev)

    def close_device(self, dev_handle: _Handle) -> None:
        with self._lock:
            for key, owner in list(self._claims.items()):
                if owner is dev_handle:
                    del self._claims[key]
        dev_handle.open = False

    def set_configuration(self, dev_handle: _Handle, config_value: int) -> None:
        self._check(dev_handle)
        if config_value not in (0, 1):
            raise usb_error(errno.EINVAL, f"no configuration {config_value}")

    def get_configuration(self, dev_handle: _Handle) -> int:
        self._check(dev_handle)
        return 1

    def set_interface_altsetting(self, dev_handle: _Handle, intf: int, altsetting: int) -> None:
        self._check(dev_handle)
        if altsetting != 0:
            raise usb_error(errno.EINVAL, f"interface {intf} has no alternate setting {altsetting}")

    def claim_interface(self, dev_handle: _Handle, intf: int) -> None:
        dev = self._check(dev_handle)
        if not 0 <= intf < len(self._layout(dev).interfaces):
            raise usb_error(errno.ENOENT, f"no interface {intf}")
        with self._lock:
            key = (id(dev), intf)
            owner = self._claims.get(key)
            if owner is not None and owner is not dev_handle and owner.open and owner.ref.epoch == dev.epoch:
                raise usb_error(errno.EBUSY, f"interface {intf} is claimed by another handle")
            self._claims[key] = dev_handle
            dev_handle.claimed.add(intf)

    def release_interface(self, dev_handle: _Handle, intf: int) -> None:
        with self._lock:
            dev_handle.claimed.discard(intf)
            key = (id(dev_handle.ref.device), intf)
            if self._claims.get(key) is dev_handle:
                del self._claims[key]
        self._check(dev_handle)

    # transfers --------------------------------------------------------------------------
    def bulk_write(self, dev_handle: _Handle, ep: int, intf: int, data: array.array, timeout: int) -> int:
        dev = self._check(dev_handle)
        payload = data.tobytes()
        try:
            dev.write_endpoint(ep, payload)
        except NoDevice:
            raise usb_error(errno.ENODEV) from None
        except Halted:
            raise usb_error(errno.EPIPE, f"endpoint 0x{ep:02X} halted") from None
        self.transfers += 1
        return len(payload)

    def bulk_read(self, dev_handle: _Handle, ep: int, intf: int, buff: array.array, timeout: int) -> int:
        dev = self._check(dev_handle)
        size = len(buff) * buff.itemsize
        clock = dev.clock
        deadline = None if timeout == 0 else clock.monotonic() + timeout / 1000.0
        while True:
            try:
                chunk = dev.take_endpoint(ep, size)
            except NoDevice:
                raise usb_error(errno.ENODEV) from None
            except Overflow as exc:
                raise usb_error(errno.EOVERFLOW, str(exc)) from None
            except Halted:
                raise usb_error(errno.EPIPE, f"endpoint 0x{ep:02X} halted") from None
            if chunk is not None:
                n = len(chunk)
                memoryview(buff).cast("B")[:n] = chunk
                self.transfers += 1
                return n
            now = clock.monotonic()
            due = dev.next_due(ep)
            if deadline is not None and now >= deadline:
                raise usb_error(errno.ETIMEDOUT, f"bulk read on endpoint 0x{ep:02X}")
            if due is None and deadline is None:
                raise usb_error(errno.ETIMEDOUT, f"endless read on endpoint 0x{ep:02X} with nothing to come")
            wait = (deadline if due is None else due if deadline is None else min(due, deadline)) - now
            # + 1 ns: on a virtual clock ``now + (due - now)`` can round to just below ``due``,
            # and a wait that never gets there would spin without time passing.
            clock.sleep(max(wait, 0.0) + 1e-9)
            self._check(dev_handle)

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout) -> int:
        dev = self._check(dev_handle)
        layout = self._layout(dev)
        if bmRequestType == 0x80 and bRequest == 0x06:  # GET_DESCRIPTOR
            kind, index = wValue >> 8, wValue & 0xFF
            if kind == usb.util.DESC_TYPE_DEVICE:
                reply = layout.device_raw()
            elif kind == usb.util.DESC_TYPE_CONFIG and index == 0:
                reply = layout.config_raw()
            elif kind == usb.util.DESC_TYPE_STRING:
                reply = self._string(dev, index)
            else:
                raise usb_error(errno.EPIPE, f"no descriptor type {kind} index {index}")
            n = min(len(reply), len(data) * data.itemsize)
            memoryview(data).cast("B")[:n] = reply[:n]
            return n
        if bmRequestType == 0x80 and bRequest == 0x00:  # GET_STATUS (device)
            memoryview(data).cast("B")[:2] = b"\0\0"
            return 2
        if bmRequestType == 0x02 and bRequest == 0x01 and wValue == 0:  # CLEAR_FEATURE(ENDPOINT_HALT)
            dev.clear_halt(wIndex & 0xFF)
            return 0
        raise usb_error(errno.EPIPE, f"request 0x{bmRequestType:02X}/0x{bRequest:02X} not supported")

    def _string(self, dev: Any, index: int) -> bytes:
        if index == 0:
            return bytes([4, usb.util.DESC_TYPE_STRING]) + struct.pack("<H", 0x0409)
        text = _strings(dev.identity).get(index)
        if text is None:
            raise usb_error(errno.EPIPE, f"no string {index}")
        raw = text.encode("utf-16-le")[:252]
        return bytes([2 + len(raw), usb.util.DESC_TYPE_STRING]) + raw

    def clear_halt(self, dev_handle: _Handle, ep: int) -> None:
        self._check(dev_handle).clear_halt(ep)

    def reset_device(self, dev_handle: _Handle) -> None:
        self._check(dev_handle).usb_reset()

    def is_kernel_driver_active(self, dev_handle: _Handle, intf: int) -> bool:
        return False

    def detach_kernel_driver(self, dev_handle: _Handle, intf: int) -> None:
        pass

    def attach_kernel_driver(self, dev_handle: _Handle, intf: int) -> None:
        pass
