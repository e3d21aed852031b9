"""The device interfaces the application programs against."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class RotaryAxis(Protocol):
    """One rotary axis in degrees: the turntable or the tilt stage."""

    name: str

    def home(self) -> None: ...

    def move_to(self, degrees: float, *, wait: bool = True) -> float:
        """Move to ``degrees``; with ``wait`` block until idle and return the verified
        read-back position (MoveNotVerified if it is off by more than the tolerance). The
        wait follows the move (planned duration, extended while it progresses); an axis
        that stops progressing while still said to move is stopped: MoveStalled."""
        ...

    def position(self) -> float: ...

    def stop(self) -> None: ...

    def is_moving(self) -> bool: ...

    def motion(self) -> tuple[bool, float]:
        """(moving, position in degrees) from a single poll of the controller."""
        ...

    def wait_until_idle(self, timeout: float) -> None: ...

    def close(self) -> None: ...


@runtime_checkable
class LightBank(Protocol):
    """Relay-switched lamps, addressed by channel."""

    name: str

    def set(self, on_channels: Iterable[int]) -> None:
        """Switch exactly these channels on and every other one off; verified by read-back."""
        ...

    def state(self) -> frozenset[int]: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class Frame:
    """One validated camera frame: the raw mosaic and what the camera said about it."""

    data: np.ndarray  # uint16, (height, width), values in 0..2**bit_depth-1
    block_id: int
    timestamp_s: float  # device timestamp, seconds
    exposure_s: float
    gain: float
    pixel_format: str  # "Mono10", "Mono10p", "Mono12", "Mono16"
    temperature_c: float
    host_time_s: float = 0.0  # the host clock's monotonic time at arrival


@runtime_checkable
class Camera(Protocol):
    """A snapshot mosaic camera (a U3V camera through GenICam features)."""

    name: str

    @property
    def serial(self) -> str | None:
        """The device's serial number, when it reports one (recorded with the darks)."""

    def configure(self, *, exposure_s: float | None = None, gain: float | None = None) -> None: ...

    def snap(self, timeout: float | None = None) -> Frame:
        """One frame on a software trigger."""
        ...

    def start_stream(self, fps: float | None = None) -> None:
        """Continuous acquisition (free-running at ``fps`` or the maximum rate)."""
        ...

    def read_frame(self, timeout: float | None = None) -> Frame: ...

    def stop_stream(self) -> None: ...

    def temperature_c(self) -> float: ...

    def close(self) -> None: ...


# -- capabilities only some devices have --------------------------------------------------
# The rig checks these once, when it opens (m2s2hil.rig.factory), and records what each
# device can do (m2s2hil.rig.opened.DeviceLink); nothing probes a device for them later.


@runtime_checkable
class SplitSnap(Protocol):
    """A snap in two halves (U3V): ``trigger()`` starts the exposure, ``read_triggered()``
    returns the frame after its readout, so the stage can move during the readout."""

    def trigger(self) -> None: ...

    def read_triggered(self, timeout: float | None = None) -> Frame: ...


@runtime_checkable
class Homing(Protocol):
    """Finds its reference position (a motion controller, or an axis homed on its own)."""

    def home(self) -> object: ...


@runtime_checkable
class Reconnecting(Protocol):
    """Reopens its link after a fault and restores its settings (GRBL, Zaber, U3V)."""

    def reconnect(self) -> object: ...


@runtime_checkable
class Connecting(Protocol):
    """Opens (or reopens) its link; a device without :class:`Reconnecting` is reconnected so."""

    def connect(self) -> object: ...


@runtime_checkable
class RestartReport(Protocol):
    """What a reconnect may report: ``reset`` when the controller restarted meanwhile and so
    lost its position (GRBL after a power cycle); its axes must be homed again."""

    reset: bool


@runtime_checkable
class AlarmClearing(Protocol):
    """A controller that locks itself after an alarm until cleared (GRBL: soft reset, then
    ``$H`` with ``home``, or ``$X``)."""

    def clear_alarm(self, *, home: bool = False) -> object: ...


@runtime_checkable
class ContinuousRotation(Protocol):
    """An axis that can turn at a constant speed until stopped (continuous capture)."""

    def rotate(self, speed_dps: float, direction: int = +1) -> None: ...
