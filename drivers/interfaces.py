"""The device interfaces the application programs against."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Protocol, runtime_checkable


@runtime_checkable
class RotaryAxis(Protocol):
    """One rotary axis in degrees: the turntable or the tilt stage."""

    name: str

    def home(self) -> None: ...

    def move_to(self, degrees: float, *, wait: bool = True) -> float:
        """Move to ``degrees``; with ``wait`` block until idle and return the verified
        read-back position (MoveNotVerified if it is off by more than the tolerance)."""
        ...

    def position(self) -> float: ...

    def stop(self) -> None: ...

    def is_moving(self) -> bool: ...

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
