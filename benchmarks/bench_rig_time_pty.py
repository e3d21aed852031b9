"""One pass on the virtual clock and the same pass in real time over pseudo-terminals: the figures agree.

    nice -n 10 .venv/bin/python benchmarks/bench_rig_time_pty.py [--mode sg|continuous|both]
                                                                 [--azimuth-step 10] [--size 256]

The virtual-clock figure is what ``bench_rig_time.py`` reports: the simulators' motion
(``m2s2hil.simulators.motion_kit``: GRBL's planner, Zaber's trajectory) timed on a clock that
jumps. Here the same simulators run on the system clock behind ``/dev/pts/N`` (``m2s2hil.rig.pty_serve``,
as ``m2s2hil sim serve`` serves them), the drivers open the ptys as serial ports and the
engine runs the same sweep: the motion, the drivers' polling and the camera's frame timing
then take real seconds, and the run's rig time (the engine's own clock) is compared with the
virtual one. One pass: one lighting (weak), one tilt (E1), azimuths every ``--azimuth-step``
degrees, stop-and-go (overlapped, the default) and/or one continuous pass at the plan's ω.
The darks at the start are part of both runs. Also timed: ``--moves`` turntable moves of 10°
through the driver alone (motion, polling and the serial round trips, no camera).

In real time the simulators' own CPU work counts too (the camera renders each frame, which a
real camera does not cost the host), so on a loaded machine the real-time figure of a whole pass
grows with the load (printed: the 1-minute load average and the run's CPU seconds); the moves
alone show whether the motion model holds. A continuous pass streams frames at the sensor's rate:
in real time the simulated camera must render them as fast, which a loaded 2-core machine cannot
(frames are dropped and marks missed: the run retries), so it is off by default; at ``--size 64``
the rendering is cheap enough for it to run in real time there too.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from bench_engine import rig_config, run_session

from m2s2hil.config import RigConfig, load_rig
from m2s2hil.engine.build import build_run
from m2s2hil.engine.options import EngineOptions
from m2s2hil.hostinfo import describe_machine
from m2s2hil.plan import Sweep
from m2s2hil.plan.estimate import move_time_s
from m2s2hil.rig.factory import open_rig
from m2s2hil.rig.pty_serve import SimServer


def served_run(cfg: RigConfig, sweep: Sweep, root: Path, options: EngineOptions) -> tuple[float, float, int]:
    """(rig time s, wall s, frames stored) of ``sweep`` with the serial simulators on ptys."""
    root.mkdir(parents=True, exist_ok=True)
    with SimServer(cfg) as srv:
        path = root / "served.toml"
        path.write_text(srv.rig_toml())
        rig = open_rig(load_rig(path))
        try:
            engine = build_run(rig, root / "sessions", sweep=sweep, options=options)
            t = time.perf_counter()
            st = engine.run()
            wall = time.perf_counter() - t
            engine.store.close()
        finally:
            rig.close()
    assert st.state.value == "completed", st.state
    return st.elapsed_s, wall, st.done


def moves(cfg: RigConfig, n: int, root: Path) -> tuple[float, float]:
    """Seconds per 10° turntable move through the driver: (virtual clock, real time over a pty)."""
    rig = open_rig(cfg)
    try:
        t = rig.clock.monotonic()
        for i in range(1, n + 1):
            rig.turntable.move_to(10.0 * i)
        virtual = (rig.clock.monotonic() - t) / n
    finally:
        rig.close()
    root.mkdir(parents=True, exist_ok=True)
    with SimServer(cfg) as srv:
        path = root / "served.toml"
        path.write_text(srv.rig_toml())
        rig = open_rig(load_rig(path))
        try:
            t = time.monotonic()
            for i in range(1, n + 1):
                rig.turntable.move_to(10.0 * i)
            real = (time.monotonic() - t) / n
        finally:
            rig.close()
    return virtual, real


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mode", choices=("sg", "continuous", "both"), default="sg")
    ap.add_argument("--moves", type=int, default=10)
    ap.add_argument("--azimuth-step", type=float, default=10.0)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    cfg = rig_config(a.size)
    print(describe_machine(), file=sys.stderr)
    print("| pass | virtual clock | real time over ptys | difference | frames | load avg | CPU s |")
    print("|---|---|---|---|---|---|---|")
    rows = []
    modes = ["sg", "continuous"] if a.mode == "both" else [a.mode]
    with tempfile.TemporaryDirectory(prefix="bench_rig_time_pty_") as tmp:
        if a.moves:
            v, r = moves(cfg, a.moves, Path(tmp) / "moves")
            model = move_time_s(10.0, cfg.axes["turntable"])
            rows.append({"pass": "turntable move 10°", "virtual_s": v, "real_s": r, "model_s": model,
                         "difference": r / v - 1})
            print(f"| turntable move of 10° (mean of {a.moves}; plan's model {model:.3f} s) | {v:.3f} s | "
                  f"{r:.3f} s | {r / v - 1:+.1%} | — | {os.getloadavg()[0]:.1f} | — |", flush=True)
        for mode in modes:
            sweep = Sweep(satellite="voyager", build="B3", lighting=["weak"], tilts=["E1"],
                          azimuth_step_deg=a.azimuth_step,
                          mode="stop-and-go" if mode == "sg" else "continuous")
            options = EngineOptions(save_truth=False)
            _engine, st, _wall = run_session(cfg, sweep, Path(tmp) / f"v{mode}", options=options)
            cpu = time.process_time()
            real, wall, frames = served_run(cfg, sweep, Path(tmp) / f"r{mode}", options)
            cpu = time.process_time() - cpu
            load = os.getloadavg()[0]
            label = (f"{'stop-and-go (overlapped)' if mode == 'sg' else 'continuous'}, "
                     f"{round(360 / a.azimuth_step)} azimuths")
            diff = real / st.elapsed_s - 1
            rows.append({"pass": label, "virtual_s": st.elapsed_s, "real_s": real, "wall_s": wall,
                         "difference": diff, "frames": frames, "load": load, "cpu_s": cpu})
            print(f"| {label} | {st.elapsed_s:.2f} s | {real:.2f} s | {diff:+.1%} | {frames} | {load:.1f} "
                  f"| {cpu:.1f} |", flush=True)
    if a.json:
        a.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
