"""A simulated bench for the twin's tests and benchmarks: processed frames of the simulated
rig (its ``[simulation]`` perturbations included) at chosen poses, without an engine.

The frames are what the engine's processing thread hands the QC hook (dark-subtracted,
superpixel cubes), exposed so the mockup's brightest parts sit near ``peak`` of full scale,
with the simulator's truth beside them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from m2s2hil.config import RigConfig, default_rig
from m2s2hil.processing.chain import FrameProcessor
from m2s2hil.processing.dark import build_master_dark
from m2s2hil.sim_config import build_frame_source, build_world
from m2s2hil.simulators.clock import VirtualClock
from m2s2hil.simulators.frames import FrameTruth


def rig_with(size: int = 256, **simulation: Any) -> RigConfig:
    """The built-in rig with a ``size``² sensor and ``[simulation]`` keys set (validated)."""
    data = default_rig().model_dump(mode="json")
    data["camera"]["model"].update(width=int(size), height=int(size))
    data["simulation"].update(simulation)
    return RigConfig.model_validate(data)


@dataclass
class BenchFrame:
    cube: np.ndarray  # (bands, h, w) float32, dark subtracted
    truth: FrameTruth
    meta: dict[str, Any]  # what the engine records and the checks read: pose, lamps, exposure


class SimBench:
    """The simulated rig's world and camera, driven directly."""

    def __init__(self, rig: RigConfig, *, seed: int = 0, peak: float = 0.6) -> None:
        self.rig = rig
        self.model = rig.camera.model
        self.clock = VirtualClock()
        self.world = build_world(rig, self.clock)
        self._pose = {"az": 0.0, "tilt": 0.0}
        self.world.attach_axis("turntable", lambda: self._pose["az"])
        self.world.attach_axis("tilt", lambda: self._pose["tilt"])
        self.source = build_frame_source(rig, self.world, seed=seed, model=self.model)
        self.peak = float(peak)
        self._light: str | None = None
        self._darks: dict[float, Any] = {}

    def light(self, condition: str) -> None:
        if condition == self._light:
            return
        for lamp in self.rig.lamps.values():
            self.world.set_lamp(lamp.channel, False)
        for ch in self.rig.lamp_channels(condition):
            self.world.set_lamp(ch, True)
        self.clock.advance(self.rig.warmup_s(condition) + 5.0)
        self._light = condition

    def _dark(self, exposure: float) -> Any:
        key = round(exposure, 6)
        if key not in self._darks:
            self.world.set_lens_cap(True)
            darks = [self.source.capture(exposure) for _ in range(2)]
            self.world.set_lens_cap(False)
            self._darks[key] = build_master_dark(darks, exposure_s=exposure, gain=1.0,
                                                 temperature_c=self.world.sensor_temperature_c)
        return self._darks[key]

    def frame(self, satellite: str, build: str, lighting: str, azimuth_deg: float, tilt_deg: float,
              *, exposure_s: float | None = None, process: bool = True) -> BenchFrame:
        """A processed frame of the session's ``satellite``/``build`` (the world may mount
        another: ``[simulation.mount]``) at the stage pose read back as given (``process``
        False: the truth only, no dark and an empty cube)."""
        self.light(lighting)
        self.world.mount(satellite, build)
        self._pose.update(az=float(azimuth_deg), tilt=float(tilt_deg))
        full = float(self.model.full_scale)
        if exposure_s is None:  # as an auto exposure would: the mockup's highlights near ``peak``
            self.source.capture(0.005)
            tr = self.source.truth()
            sig = tr.signal()[tr.labels > 0]
            top = float(np.percentile(sig, 99.5)) if sig.size else 0.0
            exposure_s = float(min(2.0, 0.005 * self.peak * full / max(top, 1e-6)))
            exposure_s = float(f"{exposure_s:.3g}")  # a few exposures, so darks are reused
        raw = self.source.capture(exposure_s)
        truth = self.source.truth()
        if not process:
            return BenchFrame(np.zeros((0, 0, 0), np.float32), truth, {"exposure_s": exposure_s})
        cube = FrameProcessor("superpixel", self.model, dark=self._dark(exposure_s)).process(raw).cube
        lamps = {lamp.channel: lamp.channel in self.world.lamps_on() for lamp in self.rig.lamps.values()}
        meta = {
            "satellite": satellite, "build": build, "lighting": lighting, "exposure_s": exposure_s,
            "gain": 1.0,
            "pose": {"turntable_deg": float(azimuth_deg), "tilt_deg": float(tilt_deg)},
            "lamps_on": sorted(ch for ch, on in lamps.items() if on), "bit_depth": int(self.model.bit_depth),
        }
        return BenchFrame(np.array(cube, dtype=np.float32, copy=True), truth, meta)
