"""Why a rig did not open, in one line: the device, its port, the cause and a hint.

Opening a rig meets the bench's everyday problems: an adapter not plugged in, a user not
in the ``dialout`` group, another program holding the port, two USB adapters enumerated
in the other order (a Zaber answering where the GRBL was expected), a controller in
alarm, no libusb, no camera. :func:`explain` turns whatever a driver raised while a
device was being opened into a :class:`RigOpenError` that says which of these it is;
:func:`opening` does it around one device's opening. Exit codes (docs/rig-setup.md):

- 6 (``EXIT_UNREACHABLE``): the device could not be reached: the port is missing, not
  permitted or busy; nothing answers; no USB backend; no camera.
- 7 (``EXIT_UNUSABLE``): the device answered but cannot be used as the rig file says: the
  wrong device on the port, a controller in alarm, an axis without switches whose origin
  was never set or is no longer known.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
from collections.abc import Iterator
from typing import Literal

from m2s2hil.drivers.errors import (
    CameraError,
    DeviceError,
    DeviceGone,
    DeviceTimeout,
    ProtocolError,
    StageAlarm,
)
from m2s2hil.protocols.errors import M2S2Error

log = logging.getLogger(__name__)

EXIT_UNREACHABLE = 6
EXIT_UNUSABLE = 7

Cause = Literal[
    "missing port", "permission denied", "port busy", "no answer", "no USB backend", "no camera",
    "wrong device", "alarm", "no origin", "position unknown", "homing disabled", "device error",
]
_UNREACHABLE = frozenset({"missing port", "permission denied", "port busy", "no answer", "no USB backend",
                          "no camera"})

#: What the operator can do about each cause (a port path is filled in where it helps).
HINTS: dict[str, str] = {
    "missing port": "is the adapter plugged in? `ls /dev/serial/by-id/` lists the serial adapters; "
                    "put the stable by-id path in the rig file",
    "permission denied": "add yourself to the dialout group (`sudo usermod -aG dialout $USER`, then log in "
                         "again); for the camera install the udev rule of docs/rig-setup.md",
    "port busy": "another program holds the port (a running `m2s2hil serve`, a terminal program): "
                 "`fuser -v {port}` names it",
    "no answer": "is the controller powered, and is the baud rate in the rig file the controller's?",
    "no USB backend": "install libusb (`sudo apt-get install libusb-1.0-0`)",
    "no camera": "is the camera plugged into a USB 3 port? `lsusb` should list it; check vendor_id, "
                 "product_id and serial in the [camera] table",
    "wrong device": "two adapters may have swapped names: use /dev/serial/by-id/ paths in the rig file",
    "alarm": "check the axis can move freely, then `m2s2hil rig origin AXIS --rig FILE` (no switches) or "
             "home it (switches)",
    "no origin": "turn the axis to its zero mark and run `m2s2hil rig origin {axis} --rig FILE`",
    "position unknown": "turn the axis to its zero mark and run `m2s2hil rig origin {axis} --rig FILE` again",
    "homing disabled": "the rig file says homing = \"switches\" but the controller has homing off ($22=0): "
                       "`m2s2hil rig probe FILE --apply`, or homing = \"none\" and `m2s2hil rig origin`",
    "device error": "run `m2s2hil rig probe FILE` to see what the device reports",
}


class RigOpenError(M2S2Error):
    """A device of the rig could not be opened; ``str()`` is the one line the operator sees."""

    def __init__(self, device: str, port: str, cause: Cause, detail: str, hint: str | None = None) -> None:
        self.device = device
        self.port = port
        self.cause = cause
        self.detail = detail
        self.hint = hint if hint is not None else HINTS.get(cause, "").format(port=port, axis=device)
        self.exit_code = EXIT_UNREACHABLE if cause in _UNREACHABLE else EXIT_UNUSABLE
        line = f"cannot open {device} ({port}): {cause}: {detail}"
        super().__init__(f"{line}; hint: {self.hint}" if self.hint else line)


def detail_of(exc: BaseException) -> str:
    """What a driver said went wrong: its ``detail`` when it has one, else its message."""
    return getattr(exc, "detail", None) or str(exc)


def errno_of(exc: BaseException | None) -> int | None:
    """The OS error number somewhere in the chain of ``exc`` (pyserial keeps it on its own
    SerialException, an IOError; pyusb on USBError.errno)."""
    seen = 0
    while exc is not None and seen < 8:
        code = getattr(exc, "errno", None)
        if isinstance(code, int):
            return code
        exc = exc.__cause__ or exc.__context__
        seen += 1
    return None


def _serial_cause(exc: BaseException) -> Cause | None:
    code = errno_of(exc)
    text = str(exc).lower()
    if code in (errno.ENOENT, errno.ENODEV, errno.ENXIO) or "no such file" in text:
        return "missing port"
    if code in (errno.EACCES, errno.EPERM) or "permission denied" in text:
        return "permission denied"
    if code in (errno.EBUSY, errno.EAGAIN) or "exclusively lock" in text or "resource busy" in text:
        return "port busy"
    if "not present" in text or "no simulated device" in text or "unknown" in text:
        return "missing port"
    return None


def identify_port(url: str, baudrate: int, *, timeout_s: float = 0.5) -> str | None:
    """What answers on ``url``: the title of a device kind (``"GRBL"``, ``"Zaber ASCII"``,
    ``"ASCII relay"``) or None.

    Sends each kind's probe (its registry entry's :class:`~m2s2hil.rig.devices.kind.Signature`,
    chosen so that it answers and the others ignore or reject it: a Zaber status poll, a GRBL
    soft reset, a Numato-style ``ver``) and holds each reply against every kind's signature.
    Never raises: None when nothing is recognised.
    """
    import serial

    from m2s2hil.rig.devices import KINDS  # as in explain()

    signed = [(kind.title, kind.signature) for kind in KINDS.values() if kind.signature is not None]
    try:
        port = serial.serial_for_url(url, baudrate=baudrate, timeout=timeout_s)
    except (serial.SerialException, OSError, ValueError):
        return None
    try:
        for title, signature in signed:
            with contextlib.suppress(serial.SerialException, OSError):
                port.reset_input_buffer()
                port.write(signature.probe)
                got = port.read(256)
                for other, sig in signed:
                    if (other == title or not sig.own_probe_only) and sig.reply.search(got):
                        return other
        return None
    finally:
        with contextlib.suppress(serial.SerialException, OSError):
            port.close()


def explain(exc: BaseException, *, device: str, port: str, protocol: str, baudrate: int = 115200,
            identify: bool = True) -> RigOpenError:
    """The :class:`RigOpenError` for ``exc``, raised while ``device`` was being opened."""
    if isinstance(exc, RigOpenError):
        return exc
    # The registry's entries open their devices inside opening() (below): imported here, when
    # an error is to be explained, so that this module stays below them.
    from m2s2hil.rig.devices import KINDS

    kind = KINDS.get(protocol)
    if kind is not None and kind.explain is not None:  # what this kind's own errors mean, first
        own = kind.explain(exc, device, port)
        if own is not None:
            return own
    detail = detail_of(exc)
    if isinstance(exc, DeviceGone):
        cause = _serial_cause(exc)
        if cause is not None:
            # The OS's own words, not pyserial's nested repetition of the path.
            code = errno_of(exc)
            if cause == "port busy":
                detail = "another program holds an exclusive lock on it"
            elif code is not None:
                detail = os.strerror(code)
            return RigOpenError(device, port, cause, detail)
    if isinstance(exc, StageAlarm):
        return RigOpenError(device, port, "alarm", detail)
    if isinstance(exc, DeviceTimeout | ProtocolError):
        found = identify_port(port, baudrate) if identify else None
        expected = kind.title if kind is not None else protocol
        if found is not None and found != expected:
            return RigOpenError(device, port, "wrong device",
                                f"a {found} device answers where the rig file expects {expected}")
        return RigOpenError(device, port, "no answer" if isinstance(exc, DeviceTimeout) else "device error",
                            detail)
    if isinstance(exc, DeviceError | OSError):
        cause = _serial_cause(exc)
        return RigOpenError(device, port, cause or "device error", detail)
    raise exc  # not a device's problem: a bug, let it show


@contextlib.contextmanager
def opening(device: str, port: str, protocol: str, baudrate: int = 115200) -> Iterator[None]:
    """Turn a failure while opening ``device`` into a :class:`RigOpenError` (one line, no traceback).

    Errors of the application (a bad configuration, :class:`M2S2Error` that is not a device
    error) pass unchanged; so does anything that is not a device's problem.
    """
    try:
        yield
    except RigOpenError:
        raise
    except (DeviceError, OSError, CameraError) as exc:
        raise explain(exc, device=device, port=port, protocol=protocol, baudrate=baudrate) from exc
    except Exception as exc:
        if type(exc).__name__ == "NoBackendError":  # pyusb's, when libusb is missing
            raise RigOpenError(device, port, "no USB backend", str(exc)) from exc
        raise
