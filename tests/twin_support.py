"""Frames of the simulated rig with a misplaced mockup, shared by the twin's tests (made once
per process: a 256² sensor, voyager B3 in weak light at E0, four azimuths)."""

from __future__ import annotations

from functools import cache

from m2s2hil.twin.projection import Placement
from m2s2hil.twin.registration import Observation, Registrar, Registration
from m2s2hil.twin.simulated import BenchFrame, SimBench, rig_with

TRUE = Placement(dx_mm=5.0, dy_mm=-4.0, yaw_deg=6.0, tilt_bias_deg=2.0)
AZIMUTHS = (0.0, 90.0, 180.0, 270.0)
SAT, BUILD = "voyager", "B3"
TILT = 15.0  # E0: at a tilt of 0 a small tilt bias barely changes the silhouette (docs/twin.md)


@cache
def misplaced_frames() -> tuple[BenchFrame, ...]:
    rig = rig_with(256, mount={"offset_mm": [TRUE.dx_mm, TRUE.dy_mm], "yaw_deg": TRUE.yaw_deg,
                               "tilt_bias_deg": TRUE.tilt_bias_deg})
    bench = SimBench(rig)
    return tuple(bench.frame(SAT, BUILD, "weak", az, TILT) for az in AZIMUTHS)


def observations() -> list[Observation]:
    return [Observation.from_cube(SAT, BUILD, az, TILT, f.cube)
            for az, f in zip(AZIMUTHS, misplaced_frames(), strict=True)]


@cache
def registered() -> Registration:
    return Registrar(rig_with(256).camera.model, levels=((32, 1.2), (64, 0.7))).register(observations())
