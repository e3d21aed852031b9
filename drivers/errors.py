"""Typed device errors.

Every error says which device, which command and which attempt; ``fault_class``
is the key the engine's fault policy dispatches on. ``DeviceError`` is an
:class:`~m2s2hil.protocols.errors.M2S2Error` (drivers import only protocols), so a front end
that turns our errors into one line turns a device's error into one line too.
"""

from __future__ import annotations

from m2s2hil.protocols.errors import M2S2Error


class DeviceError(M2S2Error):
    """A device that failed, refused or did not answer."""

    fault_class = "protocol"

    def __init__(
        self, message: str, *, device: str = "?", command: str | None = None, attempt: int = 1
    ) -> None:
        self.device = device
        self.command = command
        self.attempt = attempt
        self.detail = message
        where = f"{device}"
        if command is not None:
            where += f" [{command!r}]"
        if attempt > 1:
            where += f" (attempt {attempt})"
        super().__init__(f"{where}: {message}")


class DeviceTimeout(DeviceError):
    """No (complete) answer within the timeout."""

    fault_class = "timeout"


class ProtocolError(DeviceError):
    """Bytes that do not follow the protocol, or an answer that does not fit the question."""

    fault_class = "protocol"


class CommandRejected(DeviceError):
    """The device understood and refused (GRBL error:N, Zaber RJ, Modbus exception)."""

    fault_class = "protocol"

    def __init__(self, message: str, *, code: object = None, **kw) -> None:
        self.code = code
        super().__init__(message, **kw)


class ControllerLocked(CommandRejected):
    """A command refused because the controller is locked after an alarm (GRBL ``error:9``): its
    position is not trusted until the alarm is cleared, so the fault is an alarm, recovered as
    the axis's homing policy says (home on switches, or unlock and re-read)."""

    fault_class = "alarm"


class DeviceGone(DeviceError):
    """The port or the USB device vanished."""

    fault_class = "device_gone"


class StageAlarm(DeviceError):
    """The motion controller is in alarm (limit, homing failure, stall)."""

    fault_class = "alarm"

    def __init__(self, message: str, *, code: object = None, **kw) -> None:
        self.code = code
        super().__init__(message, **kw)


class MoveNotVerified(DeviceError):
    """The read-back position does not match the target within the tolerance."""

    fault_class = "alarm"

    def __init__(self, message: str, *, target: float, actual: float, **kw) -> None:
        self.target = target
        self.actual = actual
        super().__init__(message, **kw)


class MoveStalled(MoveNotVerified):
    """An axis that stopped progressing towards its target while its controller still said it
    was moving (or held): which axis, where it started, where it stood, where it should be."""

    def __init__(self, message: str, *, axis: str, start: float, target: float, actual: float, **kw) -> None:
        self.axis = axis
        self.start = start
        super().__init__(message, target=target, actual=actual, **kw)


class SoftLimitError(DeviceError):
    """A target outside the configured soft limits: refused before anything is sent."""

    fault_class = "protocol"


class RelayNotSwitched(DeviceError):
    """The relay board's read-back does not match what was commanded."""

    fault_class = "protocol"


class CameraError(DeviceError):
    """Camera-level failure (GenCP status, stream set-up)."""

    fault_class = "protocol"


class FrameIncomplete(CameraError):
    """A frame whose leader, payload or trailer is missing or short."""

    fault_class = "frame_incomplete"


class FrameCorrupt(CameraError):
    """A frame with bad magic, out-of-sequence block id or error status in its trailer."""

    fault_class = "frame_incomplete"
