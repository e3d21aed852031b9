"""Rig time of a full build (324 frames) on the virtual clock, mode by mode, against the floor.

    nice -n 10 .venv/bin/python benchmarks/bench_rig_time.py [--size 256] [--speeds 20,40,60]
                                                             [--modes sg,overlap,continuous]

Each run is a whole session built as ``capture`` builds it (``build_run``) on the built-in
simulated rig at ``--size``² (the simulated time does not depend on the sensor size; the
rendering does, so small is quick): stop-and-go as before this work (``overlap=False``),
overlapped stop-and-go (the default: the next move starts when the exposure ends), and
continuous rotation at each of ``--speeds``. Printed per run: simulated rig time, the
mode's own lower bound, the physical floor (m2s2hil.plan.floor: any mode, any order), the
ratio to the floor, frames stored. ``--json`` writes the rows.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

from bench_engine import rig_config, run_session

from m2s2hil.engine.options import EngineOptions
from m2s2hil.hostinfo import describe_machine
from m2s2hil.plan import Sweep

BUILD = dict(satellite="voyager", build="B3")


def one(cfg, sweep: Sweep, root: Path, label: str, options: EngineOptions) -> dict:
    t = time.perf_counter()
    engine, st, wall = run_session(cfg, sweep, root, options=options)
    floor = sweep.physical_floor(cfg).total_s
    done = sum(1 for e in engine.events if e.kind == "frame" and e.event_id in engine.schedule.done_ids())
    row = {"run": label, "sim_s": st.elapsed_s, "lower_bound_s": engine.report.lower_bound_s,
           "physical_floor_s": floor, "vs_floor": st.elapsed_s / floor, "frames": done,
           "state": st.state.value, "faults": len(st.faults), "wall_s": time.perf_counter() - t}
    print(f"| {label} | {row['sim_s']:.1f} s | {row['lower_bound_s'] or float('nan'):.1f} s | {floor:.1f} s | "
          f"{row['vs_floor']:.2f} | {done} | {row['state']} |", flush=True)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--speeds", default="20,40,60")
    ap.add_argument("--modes", default="sg,overlap,continuous")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    cfg = rig_config(a.size)
    modes = set(a.modes.split(","))
    print(describe_machine(), file=sys.stderr)
    print("| run | rig time (simulated) | mode's lower bound | physical floor | / floor | frames | state |")
    print("|---|---|---|---|---|---|---|")
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_rig_time_") as tmp:
        root = Path(tmp)
        if "sg" in modes:
            rows.append(one(cfg, Sweep(**BUILD), root / "sg", "stop-and-go (before: no overlap)",
                            EngineOptions(overlap=False, save_truth=False)))
        if "overlap" in modes:
            rows.append(one(cfg, Sweep(**BUILD), root / "ov", "stop-and-go, overlapped",
                            EngineOptions(save_truth=False)))
        if "continuous" in modes:
            for v in [float(x) for x in a.speeds.split(",") if x]:
                rows.append(one(cfg, Sweep(**BUILD, mode="continuous"), root / f"c{v:g}",
                                f"continuous {v:g}°/s", EngineOptions.of(speed_dps=v, save_truth=False)))
    if a.json:
        a.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
