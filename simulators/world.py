"""The simulated world the devices share: stage pose, lamps, lens cap, mockup.

Motion simulators attach their axes (a function returning degrees at the current
clock time, or, attached ``timed``, at a given clock time, so the camera can ask where
the stage was during an exposure that is already over); relay simulators set lamp
channels; the camera simulator reads all of it to render a frame. Nothing here knows
about bytes.

The bench can also be set up wrong, as a real one is (``[simulation.mount]`` and
``[simulation.lamps]`` of the rig file): a :class:`Placement` puts the mockup off the
turntable axis, turned at azimuth 0, on a tilt stage whose zero is off, or has another
satellite or build on the turntable than the session asked for; a lamp factor dims a lamp
(0: dead). The capture-time checks of the twin (``m2s2hil.twin.checks``) are tested on them.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class LampInfo:
    name: str
    kind: str  # "led_bar" | "spotlight"
    warmup_s: float


@dataclass(frozen=True)
class Placement:
    """How the mockup really sits on the rig, where it differs from the nominal mount.

    ``offset_x_mm``/``offset_y_mm``: the mockup's centre from the turntable axis, in the
    turntable's frame at azimuth 0 (x to the camera's right, y away from the camera);
    ``yaw_deg``: the mockup turned about its own vertical axis at azimuth 0;
    ``tilt_bias_deg``: the tilt stage's true angle minus its read-back; ``satellite`` and
    ``build``: what is really mounted (None: what the session mounted). ``diameter_mm`` is
    the mockup's bounding-sphere diameter, which turns millimetres into the scene's units.
    """

    offset_x_mm: float = 0.0
    offset_y_mm: float = 0.0
    yaw_deg: float = 0.0
    tilt_bias_deg: float = 0.0
    satellite: str | None = None
    build: str | None = None
    diameter_mm: float = 160.0

    @property
    def nominal(self) -> bool:
        """No displacement (another mockup mounted is a separate matter: ``satellite``/``build``)."""
        return not (self.offset_x_mm or self.offset_y_mm or self.yaw_deg or self.tilt_bias_deg)

    def offset_units(self, radius: float) -> tuple[float, float, float]:
        """The offset in the mockup's object frame (scene units, bounding radius ``radius``),
        undoing the yaw: a mockup at ``d`` turned by ``yaw`` and viewed at azimuth ``az`` is
        the same mockup at ``rot_z(-yaw)·d`` viewed at ``az + yaw``."""
        k = 2.0 * radius / self.diameter_mm
        c, s = math.cos(math.radians(self.yaw_deg)), math.sin(math.radians(self.yaw_deg))
        x, y = self.offset_x_mm * k, self.offset_y_mm * k
        return (c * x + s * y, -s * x + c * y, 0.0)


@dataclass(frozen=True)
class Pose:
    azimuth_deg: float
    tilt_deg: float


@dataclass
class World:
    clock: Any
    lamp_info: dict[int, LampInfo] = field(default_factory=dict)  # relay channel -> lamp
    satellite: str = "voyager"
    build: str = "B3"
    lens_cap: bool = False
    #: What is in front of the camera: the mounted mockup or a calibration target
    #: (see :mod:`m2s2hil.simulators.targets`).
    target: str = "mockup"
    sensor_temperature_c: float = 35.0
    spot_angle_deg: float = 45.0  # spotlight incidence, from the camera axis, about vertical
    placement: Placement = field(default_factory=Placement)
    lamp_factor: dict[int, float] = field(default_factory=dict)  # relay channel -> output factor (0: dead)

    def __post_init__(self) -> None:
        self._lock = threading.RLock()
        self._axes: dict[str, tuple[Callable[..., float], bool]] = {}
        self._lamp_on_since: dict[int, float] = {}
        self.version = 0  # bumped on every change a renderer may cache on

    # -- stage -----------------------------------------------------------------------
    def attach_axis(self, role: str, degrees: Callable[..., float], *, timed: bool = False) -> None:
        """``degrees()`` gives the axis angle now; with ``timed``, ``degrees(t)`` gives it at
        clock time ``t`` (a moment just past included). An axis attached without ``timed``
        (a mirrored real axis) only knows where it is now, and answers that for any ``t``."""
        with self._lock:
            self._axes[role] = (degrees, bool(timed))

    def _angle(self, role: str, t: float | None) -> float:
        fn, timed = self._axes.get(role, (None, False))
        if fn is None:
            return 0.0
        if timed:
            return float(fn(self.clock.monotonic() if t is None else t))
        return float(fn())

    def pose(self) -> Pose:
        """The stage pose now."""
        return self.pose_at(None)

    def pose_at(self, t: float | None) -> Pose:
        """The stage pose at clock time ``t`` (None: now)."""
        with self._lock:
            az = self._angle("turntable", t)
            tilt = self._angle("tilt", t)
        return Pose(azimuth_deg=az, tilt_deg=tilt)

    # -- lamps -----------------------------------------------------------------------
    def set_lamp(self, channel: int, on: bool) -> None:
        with self._lock:
            was = channel in self._lamp_on_since
            if on and not was:
                self._lamp_on_since[channel] = self.clock.monotonic()
                self.version += 1
            elif not on and was:
                del self._lamp_on_since[channel]
                self.version += 1

    def lamps_on(self) -> frozenset[int]:
        with self._lock:
            return frozenset(self._lamp_on_since)

    def lamp_output(self) -> dict[int, float]:
        """Relative output of every lit channel, 0..1; LEDs ramp up over their warm-up."""
        now = self.clock.monotonic()
        out: dict[int, float] = {}
        with self._lock:
            for ch, since in self._lamp_on_since.items():
                info = self.lamp_info.get(ch)
                warm = info.warmup_s if info else 0.0
                out[ch] = 1.0 if warm <= 0 else min(1.0, 0.5 + 0.5 * (now - since) / warm)
                out[ch] *= self.lamp_factor.get(ch, 1.0)
        return out

    # -- scene -----------------------------------------------------------------------
    def mount(self, satellite: str, build: str) -> None:
        """Put a mockup on the turntable (the operator's job on the bench); a placement that
        names another satellite or build mounts that one instead (the operator's mistake)."""
        with self._lock:
            self.satellite = self.placement.satellite or satellite
            self.build = self.placement.build or build
            self.version += 1

    def set_target(self, target: str) -> None:
        """Hold a calibration target in view (``"white_panel"``) or go back to the ``"mockup"``."""
        from m2s2hil.simulators.targets import TARGETS

        if target not in TARGETS:
            raise ValueError(f"unknown target {target!r}; known: {', '.join(TARGETS)}")
        with self._lock:
            self.target = target
            self.version += 1

    def set_lens_cap(self, on: bool) -> None:
        with self._lock:
            self.lens_cap = on
            self.version += 1
