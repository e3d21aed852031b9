"""Model selection of the spectral segmenter: how many materials each candidate finds, how well
it segments, and what it costs (results: docs/evaluation.md, "How many materials").

    .venv/bin/python benchmarks/bench_segmenters.py frames   # simulate the frames (cached as .npz)
    .venv/bin/python benchmarks/bench_segmenters.py run      # evaluate every candidate, write table + chart

Frames: the simulator's frame source with its ground truth (``simulators/frames.py``), for every
satellite × build × lighting × tilt of the catalog (3 × 3 × 3 × 3 = 81 scenes) at ``--azimuths``
turntable angles each, a ``--size``² sensor (default 512: 128² super-pixel cubes), exposed so the
object's brightest band peaks near 60 % of full scale, a two-frame master dark subtracted and the
super-pixel cube extracted by ``processing.FrameProcessor`` — the engine's own path. Ground truth
is the frame's label map reduced to the cube grid (``analysis.loading.labels_to_cube``).

"Materials visible" = ground-truth materials holding at least ``VISIBLE_FRACTION`` of the
object's pixels and at least ``VISIBLE_PIXELS`` pixels of the cube (a material hidden behind
the body or a few pixels at the rim cannot be found by anything looking at the image).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

VISIBLE_FRACTION = 0.005
VISIBLE_PIXELS = 20
DEFAULT_CACHE = Path("bench-out/segmenter-frames")


def visible_materials(gt: np.ndarray) -> int:
    """Materials (ids > 0) covering ≥ VISIBLE_FRACTION of the object and ≥ VISIBLE_PIXELS pixels."""
    counts = np.bincount(gt.ravel())[1:]
    total = counts.sum()
    if total == 0:
        return 0
    return int(np.count_nonzero((counts >= VISIBLE_PIXELS) & (counts >= VISIBLE_FRACTION * total)))


def simulate_frames(out: Path, *, size: int = 512, azimuths: tuple[float, ...] = (30.0, 200.0),
                    seed: int = 0) -> list[Path]:
    """Simulate and store one ``.npz`` per (satellite, build, lighting, tilt, azimuth)."""
    from m2s2hil.analysis.loading import labels_to_cube
    from m2s2hil.catalog import load_catalog
    from m2s2hil.config import load_rig
    from m2s2hil.processing import FrameProcessor, build_master_dark
    from m2s2hil.simulators.clock import VirtualClock
    from m2s2hil.simulators.frames import SimFrameSource
    from m2s2hil.simulators.world import LampInfo, World

    cfg = load_rig(None)
    cat = load_catalog()
    model = cfg.camera.model.model_copy(update={"width": size, "height": size})
    clock = VirtualClock()
    info = {lc.channel: LampInfo(n, lc.kind, lc.warmup_s) for n, lc in cfg.lamps.items()}
    world = World(clock, lamp_info=info)
    pose = {"az": 0.0, "tilt": 0.0}
    world.attach_axis("turntable", lambda: pose["az"])
    world.attach_axis("tilt", lambda: pose["tilt"])
    src = SimFrameSource(world, model, lambda s, b: cat.build(s, b).materials, seed=seed)
    full = float(model.full_scale)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for light in ("weak", "strong", "directional"):
        for ch in range(8):
            world.set_lamp(ch, False)
        for ch in cfg.lamp_channels(light):
            world.set_lamp(ch, True)
        clock.advance(cfg.warmup_s(light) + 5.0)
        for sat in cat.satellites:
            for build in ("B1", "B2", "B3"):
                world.mount(sat, build)
                for elev in ("E0", "E1", "E2"):
                    pose["tilt"] = float(cfg.elevations[elev])
                    for az in azimuths:
                        path = out / f"{sat}_{build}_{light}_{elev}_{az:g}.npz"
                        written.append(path)
                        if path.exists():
                            continue
                        pose["az"] = az
                        world.set_lens_cap(False)
                        src.capture(0.005)
                        truth = src.truth()
                        peak = float(np.percentile(truth.signal()[truth.labels > 0], 99.5))
                        exp = min(2.0, 0.005 * 0.6 * full / max(peak, 1e-6))
                        raw = src.capture(exp)
                        labels = src.truth().labels.copy()
                        world.set_lens_cap(True)
                        darks = [src.capture(exp) for _ in range(2)]
                        world.set_lens_cap(False)
                        dark = build_master_dark(darks, exposure_s=exp, gain=1.0,
                                                 temperature_c=world.sensor_temperature_c)
                        cube = FrameProcessor("superpixel", model, dark=dark).process(raw).cube.copy()
                        gt = labels_to_cube(labels, cube.shape[1:]).astype(np.uint8)
                        np.savez_compressed(path, cube=cube.astype(np.float32), gt=gt,
                                            materials=np.array(cat.build(sat, build).materials),
                                            exposure_s=exp)
                        print(f"{path.name}: exposure {exp * 1e3:.2f} ms, visible {visible_materials(gt)}",
                              flush=True)
    return written


def load_frames(folder: Path) -> list[dict[str, Any]]:
    frames = []
    for p in sorted(folder.glob("*.npz")):
        with np.load(p) as z:
            sat, build, light, elev, az = p.stem.split("_")
            frames.append({"name": p.stem, "satellite": sat, "build": build, "lighting": light,
                           "elevation": elev, "azimuth": float(az), "cube": z["cube"], "gt": z["gt"].astype(np.int64),
                           "materials": [str(m) for m in z["materials"]]})
    return frames


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("what", choices=("frames", "run"))
    ap.add_argument("--cache", type=Path, default=DEFAULT_CACHE)
    ap.add_argument("--size", type=int, default=512)
    args = ap.parse_args()
    if args.what == "frames":
        t0 = time.perf_counter()
        paths = simulate_frames(args.cache, size=args.size)
        print(f"{len(paths)} frames in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
