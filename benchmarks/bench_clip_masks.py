"""What the clipping masks cost: in the processor, and rebuilt per band for the evaluation (issue 23).

    .venv/bin/python benchmarks/bench_clip_masks.py [--frames 40] [--size 2048]

Per method, on a ``size``² 10-bit frame with a dark: ``FrameProcessor.process`` on a frame whose
highlights clip (about 15 % of the raw pixels at full scale) against the same scene under the clip
(the floor: no mask is built), timed in turn frame by frame so both see the same machine; then
``band_saturation`` (the evaluation's per-band mask from the raw frame) against ``process`` on the
clipped frame, and on the frame that does not clip against ``process`` on it. Prints medians and
the ratios, which hold from one machine to the next where the milliseconds do not.
"""

from __future__ import annotations

import argparse
import datetime as dt
import platform
import time

import numpy as np

from m2s2hil.config import CameraModel
from m2s2hil.processing.chain import FrameProcessor
from m2s2hil.processing.dark import build_master_dark
from m2s2hil.processing.groundtruth import mosaic_of, synthetic_scene
from m2s2hil.processing.mosaic import MosaicLayout
from m2s2hil.processing.stability import band_saturation


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--size", type=int, default=2048)
    ap.add_argument("--methods", default="superpixel,wb")
    args = ap.parse_args()
    cam = CameraModel(width=args.size, height=args.size)
    layout = MosaicLayout.from_camera(cam)
    scene = synthetic_scene(cam, args.size, seed=3)
    dark_frame = np.full((args.size, args.size), 40, np.uint16)
    dark = build_master_dark(np.stack([dark_frame, dark_frame]), exposure_s=0.01, gain=1.0,
                             temperature_c=25.0)
    # the same scene: under full scale everywhere (the floor), and with its highlights clipped
    clean = mosaic_of(scene.cube * 0.5, layout, cam.full_scale) + dark_frame
    clipped = np.minimum(mosaic_of(scene.cube * 1.6, layout, 4 * cam.full_scale) + dark_frame, cam.full_scale)
    clipped = clipped.astype(np.uint16)
    share = float((clipped >= cam.full_scale).mean())
    print(f"{dt.datetime.now(dt.UTC):%Y-%m-%d %H:%M} UTC, {platform.processor() or platform.machine()}, "
          f"{args.size}² frame, {100 * share:.1f} % of raw pixels at full scale, {args.frames} frames")
    print("| method | process, no clip (ms) | process, clipped (ms) | clipped / no clip | "
          "per-band mask (ms) | mask / process | mask, no clip / process, no clip |")
    print("|---|---|---|---|---|---|---|")
    for method in args.methods.split(","):
        proc = FrameProcessor(method, cam, dark=dark)
        for raw in (clean, clipped, clean):  # warm-up: compiled kernels, touched buffers
            proc.process(raw)
        t_clean, t_clip, t_mask, t_none = [], [], [], []
        for _ in range(args.frames):
            t0 = time.perf_counter()
            proc.process(clean)
            t1 = time.perf_counter()
            proc.process(clipped)
            t2 = time.perf_counter()
            band_saturation(clipped >= cam.full_scale, method, layout)
            t3 = time.perf_counter()
            band_saturation(clean >= cam.full_scale, method, layout)
            t4 = time.perf_counter()
            t_clean.append(t1 - t0)
            t_clip.append(t2 - t1)
            t_mask.append(t3 - t2)
            t_none.append(t4 - t3)
        a, b, m = (1e3 * float(np.median(t)) for t in (t_clean, t_clip, t_mask))
        # pair by pair: the ratio of each frame's two timings, then the median
        r_clip = float(np.median(np.array(t_clip) / np.array(t_clean)))
        r_mask = float(np.median(np.array(t_mask) / np.array(t_clip)))
        r_none = float(np.median(np.array(t_none) / np.array(t_clean)))
        print(f"| {method} | {a:.1f} | {b:.1f} | {r_clip:.2f} | {m:.1f} | {r_mask:.2f} | {r_none:.2f} |")


if __name__ == "__main__":
    main()
