"""The opened rig: the devices the engine drives, and the way back to a safe state."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from m2s2hil.config import RigConfig
from m2s2hil.drivers.clock import Clock
from m2s2hil.drivers.interfaces import Camera, LightBank, RotaryAxis

log = logging.getLogger(__name__)


@dataclass
class Rig:
    config: RigConfig
    clock: Clock
    turntable: RotaryAxis
    tilt: RotaryAxis
    lights: LightBank
    camera: Camera
    world: Any = None  # the simulated world when the rig is simulated, else None
    simulated: bool = False
    extras: dict[str, Any] = field(default_factory=dict)
    #: The camera's calibration (``processing.calibration.CameraCalibration``) when the
    #: rig file names one: the real mosaic layout, crosstalk matrix, white reference.
    calibration: Any = None
    #: Called to cap/uncap the lens for dark frames. A simulated rig caps its world's
    #: lens; a real rig asks the operator (the CLI prompts, the API suspends).
    lens_cap_hook: Callable[[bool], None] | None = None

    def cap_lens(self, on: bool) -> None:
        if self.lens_cap_hook is not None:
            self.lens_cap_hook(on)
        elif self.world is not None:
            self.world.set_lens_cap(on)

    def mount(self, satellite: str, build: str) -> None:
        """Tell the simulated world which mockup is on the turntable (a no-op on the bench)."""
        if self.world is not None:
            self.world.mount(satellite, build)

    def safe(self) -> list[Exception]:
        """Lamps off and motion stopped; every step is tried even if another fails.

        Returns the errors met on the way (empty when the rig is safe) so a caller in
        teardown can record them without losing the original exception.
        """
        errors: list[Exception] = []
        for step in (
            lambda: self.lights.set(()),
            self.turntable.stop,
            self.tilt.stop,
        ):
            try:
                step()
            except Exception as exc:  # teardown must try every step
                log.error("safe state step failed: %s", exc)
                errors.append(exc)
        return errors

    def close(self) -> None:
        for dev in (self.camera, self.lights, self.turntable, self.tilt):
            try:
                dev.close()
            except Exception as exc:
                log.warning("closing %s failed: %s", getattr(dev, "name", dev), exc)
