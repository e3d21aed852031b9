"""Keep a local simulated world in step with devices it does not simulate.

When the camera is simulated in this process but the stage or the relays are not
(ptys from ``m2s2hil sim serve``, or real hardware), the simulated camera must still
see the pose and the lamps. These proxies forward every call to the real driver and
copy what it read back into the world.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterable
from typing import Any


class MirroredAxis:
    def __init__(self, axis: Any, world: Any, role: str) -> None:
        self._axis = axis
        self._world = world
        self._last = 0.0
        world.attach_axis(role, lambda: self._last)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._axis, name)

    @property
    def wrapped(self) -> Any:
        """The real driver (to change its state: attribute writes stay on the proxy)."""
        return self._axis

    def move_to(self, degrees: float, *, wait: bool = True) -> float:
        got = self._axis.move_to(degrees, wait=wait)
        self._last = got if wait else self._axis.position()
        return got

    def home(self) -> None:
        self._axis.home()
        self._last = self._axis.position()

    def position(self) -> float:
        self._last = self._axis.position()
        return self._last

    def motion(self) -> tuple[bool, float]:
        moving, self._last = self._axis.motion()
        return moving, self._last


class MirroredLights:
    def __init__(self, lights: Any, world: Any) -> None:
        self._lights = lights
        self._world = world

    def __getattr__(self, name: str) -> Any:
        return getattr(self._lights, name)

    def set(self, on_channels: Iterable[int]) -> None:
        on = frozenset(on_channels)
        try:
            self._lights.set(on)
        finally:
            # Mirror what the board reads back, even after a failed set; if the board cannot
            # be read either, keep the original error rather than this one.
            with contextlib.suppress(Exception):
                state = self._lights.state()
                for ch in self._world.lamp_info:
                    self._world.set_lamp(ch, ch in state)
