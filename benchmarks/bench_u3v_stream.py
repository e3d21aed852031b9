"""Streaming throughput of the U3V driver against the simulated TOUCAN, through pyusb.

Two figures, both for full 2048x2048 frames:

- ``virtual``: frames per wall-clock second with a virtual clock (no waiting), i.e.
  the CPU cost of simulator + pyusb + driver (leader, payload transfers, trailer,
  validation, decoding into uint16);
- ``realtime``: streaming at the camera's 65 fps on the real clock, counting the
  frames delivered and the block ids lost.

Run: ``.venv/bin/python benchmarks/bench_u3v_stream.py [--frames N] [--format Mono10]``
"""

from __future__ import annotations

import argparse
import time

from m2s2hil.drivers.clock import SystemClock
from m2s2hil.drivers.u3v import U3VCamera
from m2s2hil.simulators.clock import VirtualClock
from m2s2hil.simulators.toucan import ToucanCamera
from m2s2hil.simulators.u3v_backend import SimUsbBackend

from m2s2hil.hostinfo import describe_machine


def run(clock, frames: int, fmt: str, fps: float) -> tuple[float, int, int]:
    """(wall seconds, block-id gaps seen in the frames read, block ids the driver reports lost)."""
    sim = ToucanCamera(clock=clock, width=2048, height=2048)
    cam = U3VCamera.open(backend=SimUsbBackend(sim), clock=clock)
    cam.configure(exposure_s=0.005)
    cam.set_pixel_format(fmt)
    cam.start_stream(fps=fps)
    cam.read_frame()  # warm-up: acquisition start delay, first render
    t0 = time.perf_counter()
    ids = [cam.read_frame().block_id for _ in range(frames)]
    wall = time.perf_counter() - t0
    cam.stop_stream()
    cam.close()
    return wall, ids[-1] - ids[0] + 1 - len(ids), len(cam.missing_block_ids)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=130)
    ap.add_argument("--format", default="Mono10", choices=["Mono10", "Mono10p", "Mono12", "Mono16"])
    args = ap.parse_args()
    machine = describe_machine()
    print(f"# {machine}, {time.strftime('%Y-%m-%d')}")
    wall, _, _ = run(VirtualClock(), args.frames, args.format, 65.0)
    per_frame_ms = wall / args.frames * 1e3
    print(
        f"virtual  {args.format} 2048x2048: {args.frames / wall:7.1f} frames/s ({per_frame_ms:.1f} ms/frame)"
    )
    wall, _gaps, missing = run(SystemClock(), args.frames, args.format, 65.0)
    print(
        f"realtime {args.format} 2048x2048 at 65 fps: {args.frames / wall:7.1f} frames/s delivered,"
        f" {missing} block ids lost"
    )


if __name__ == "__main__":
    main()
