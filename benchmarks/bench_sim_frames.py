"""Speed of the simulated TOUCAN's image content at full resolution (2048 x 2048).

    .venv/bin/python benchmarks/bench_sim_frames.py [--size 2048] [--repeat 5]

Reports, in ms per frame (median of the repeats):
  render new pose   rasterise + shade a pose not seen before (per satellite and lighting)
  capture, cached   SimFrameSource.capture at an unchanged pose (= sensor noise + ADC only)
  noise + ADC       Sensor.expose alone
  truth cube        FrameTruth.radiance(): the 10-band float32 cube
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import numpy as np
from m2s2hil.simulators.clock import VirtualClock

from m2s2hil.catalog import load_catalog
from m2s2hil.config import load_rig
from m2s2hil.sim_config import build_frame_source, build_world


def ms(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=2048)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    cfg = load_rig(None)
    cat = load_catalog()
    model = cfg.camera.model.model_copy(update={"width": args.size, "height": args.size})
    clock = VirtualClock()
    world = build_world(cfg, clock)  # the simulated rig's own world and frame source
    info = world.lamp_info
    pose = {"az": 0.0}
    world.attach_axis("turntable", lambda: pose["az"])
    world.attach_axis("tilt", lambda: 15.0)
    src = build_frame_source(cfg, world, model=model)
    src.capture(0.005)  # compile / warm up
    print(f"{platform.node()} {platform.processor() or platform.machine()}, numpy {np.__version__}, "
          f"{args.size}x{args.size}")
    for light in ("strong", "directional"):
        for ch in range(8):
            world.set_lamp(ch, False)
        for ch in cfg.lamp_channels(light):
            world.set_lamp(ch, True)
        clock.advance(5.0)
        for sat in ("voyager", "iss", "hubble"):
            world.mount(sat, "B3")
            az = iter(np.arange(3.0, 360.0, 7.0))

            def new_pose(az=az, sat=sat) -> None:
                pose["az"] = float(next(az))
                src.scene.render(sat, cat.build(sat, "B3").materials, pose["az"], 15.0, world.lamp_output(),
                                 info, world.spot_angle_deg, band_gain=src.sensor.band_gain)

            print(f"render new pose   {sat:8s} {light:12s} {ms(new_pose, args.repeat):7.1f} ms")
    src.capture(0.005)
    print(f"capture, cached   {ms(lambda: src.capture(0.005), max(20, args.repeat)):7.2f} ms")
    rate = src.truth()._shaded.rate
    out = np.empty((args.size, args.size), np.uint16)
    for threads in (1, 2):
        src.sensor.threads = threads
        t = ms(lambda: src.sensor.expose(rate, 0.005, 1.0, 35.0, out=out), max(20, args.repeat))
        print(f"noise + ADC       {threads} thread{'s' if threads > 1 else ' '}       {t:7.2f} ms")
    src.sensor.threads = None

    def cube() -> None:
        src.capture(0.005)
        src.truth().radiance()

    print(f"capture + truth cube          {ms(cube, args.repeat):7.1f} ms")


if __name__ == "__main__":
    main()
