"""What merging an exposure bracket costs beside making its cubes (``processing.bracket``).

One pose of the simulated rig under the spotlight at 80° (Voyager B3), taken at the exposure that
puts the object's brightest band at 60 % of full scale and again at 16 ×, each with its master dark;
per repeat, timed in turn: ``FrameProcessor.process`` of one raw frame (the reference: what every
frame costs already), ``band_saturation`` of one raw frame (each frame's per-band mask, which the
merge needs), and ``merge_bracket`` of the two cubes. Reported as medians and as ratios to the
reference taken repeat by repeat, so the figure holds on another machine better than the times do.

    .venv/bin/python benchmarks/bench_bracket.py [--size 2048] [--repeat 30]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time
from datetime import UTC, datetime

import numpy as np
from m2s2hil.simulators.clock import VirtualClock

from m2s2hil.config import load_rig
from m2s2hil.processing.bracket import merge_bracket
from m2s2hil.processing.chain import FrameProcessor
from m2s2hil.processing.dark import build_master_dark
from m2s2hil.processing.mosaic import MosaicLayout
from m2s2hil.processing.stability import band_saturation
from m2s2hil.sim_config import build_frame_source, build_world


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=2048)
    ap.add_argument("--repeat", type=int, default=30)
    ap.add_argument("--factor", type=float, default=16.0)
    args = ap.parse_args()
    cfg = load_rig(None)
    model = cfg.camera.model.model_copy(update={"width": args.size, "height": args.size})
    clock = VirtualClock()
    world = build_world(cfg, clock, spot_angle_deg=80.0)
    pose = {"az": 120.0, "tilt": float(cfg.elevations["E1"])}
    world.attach_axis("turntable", lambda: pose["az"])
    world.attach_axis("tilt", lambda: pose["tilt"])
    for ch in cfg.lamp_channels("directional"):
        world.set_lamp(ch, True)
    clock.advance(cfg.warmup_s("directional") + 5.0)
    world.mount("voyager", "B3")
    src = build_frame_source(cfg, world, seed=0, model=model)
    layout = MosaicLayout.from_camera(model)
    src.capture(0.005)
    peak = float(np.percentile(src.truth().signal()[src.truth().labels > 0], 99.5))
    short = 0.005 * 0.6 * model.full_scale / peak
    frames = []
    for exposure in (short, short * args.factor):
        raw = src.capture(exposure)
        world.set_lens_cap(True)
        dark = build_master_dark([src.capture(exposure) for _ in range(2)], exposure_s=exposure, gain=1.0,
                                 temperature_c=world.sensor_temperature_c)
        world.set_lens_cap(False)
        proc = FrameProcessor("superpixel", model, dark=dark, threads=1)
        frames.append((raw, proc, exposure))
    cubes = [np.array(p.process(r).cube, copy=True) for r, p, _ in frames]
    masks = [band_saturation(r >= model.full_scale, "superpixel", layout) for r, _, _ in frames]
    scales = [e for _, _, e in frames]
    raw0, proc0, _ = frames[0]
    raw1 = frames[1][0]
    times: dict[str, list[float]] = {"process": [], "mask": [], "merge": []}
    for _ in range(args.repeat):
        for key, fn in (("process", lambda: proc0.process(raw0)),
                        ("mask", lambda: band_saturation(raw1 >= model.full_scale, "superpixel", layout)),
                        ("merge", lambda: merge_bracket(cubes, scales, masks))):
            t = time.perf_counter()
            fn()
            times[key].append(time.perf_counter() - t)
    clipped = float(np.mean(masks[1]))
    print(f"{platform.processor() or platform.machine()}, Python {platform.python_version()}, "
          f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC; {args.size}² sensor, ×{args.factor:g}, long frame's "
          f"cube {clipped:.1%} clipped (band-values)")
    for key, vals in times.items():
        ratio = [v / p for v, p in zip(vals, times["process"], strict=True)]
        print(f"{key:8s} median {statistics.median(vals) * 1e3:6.1f} ms   / process: median "
              f"{statistics.median(ratio):.2f} (range {min(ratio):.2f}–{max(ratio):.2f})")


if __name__ == "__main__":
    main()
