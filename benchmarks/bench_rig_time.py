"""Rig time of a full build (324 frames) on the virtual clock, mode by mode, against the floor.

    nice -n 10 .venv/bin/python benchmarks/bench_rig_time.py [--size 256] [--speeds 20,40,60]
                                                             [--modes sg,overlap,continuous]

Each run is a whole session built as ``capture`` builds it (``build_run``) on the built-in
simulated rig at ``--size``² (the simulated time does not depend on the sensor size; the
rendering does, so small is quick): stop-and-go as before this work (``overlap=False``),
overlapped stop-and-go (the default: the next move starts when the exposure ends), and
continuous rotation at each of ``--speeds`` (the planned exposures), and continuous passes
planned for a sharpness target (m2s2hil.plan.continuous: exposure, gain and ω chosen together
for each ``--blur`` bound at the mockup's rim, SNR ≥ 20 at a quarter of the brightest signal).
Printed per run: simulated rig time, the
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

from bench_engine import measure_sharpness, mockup_radius_px, rig_config, run_session

from m2s2hil.engine.options import EngineOptions
from m2s2hil.hostinfo import describe_machine
from m2s2hil.plan import Sweep
from m2s2hil.plan.continuous import SharpnessTarget, plan_continuous
from m2s2hil.store.session import SessionStore

BUILD = dict(satellite="voyager", build="B3")
MARKS = [15.0, 75.0, 135.0, 195.0, 255.0, 315.0]


def one(cfg, sweep: Sweep, root: Path, label: str, options: EngineOptions) -> dict:
    t = time.perf_counter()
    engine, st, _wall = run_session(cfg, sweep, root, options=options)
    floor = sweep.physical_floor(cfg).total_s
    pose = None
    if options.save_truth:  # pose error: the recorded (interpolated) pose against the simulator's
        store = SessionStore.open_path(engine.store.path)
        err = [abs(f.meta["truth"]["azimuth_deg"] - f.meta["pose"]["turntable_deg"]) for f in store.frames()
               if f.meta.get("truth") and f.meta.get("pose", {}).get("turntable_deg") is not None]
        unc = [f.meta.get("continuous", {}).get("pose_uncertainty_deg") or 0.0 for f in store.frames()]
        store.close()
        pose = {"max_error_deg": max(err, default=float("nan")), "max_uncertainty_deg": max(unc, default=0.0)}
    done = sum(1 for e in engine.events if e.kind == "frame" and e.event_id in engine.schedule.done_ids())
    row = {"run": label, "sim_s": st.elapsed_s, "lower_bound_s": engine.report.lower_bound_s,
           "physical_floor_s": floor, "vs_floor": st.elapsed_s / floor, "frames": done,
           "state": st.state.value, "faults": len(st.faults), "wall_s": time.perf_counter() - t,
           "pose": pose}
    lower = row["lower_bound_s"] or float("nan")
    perr = "—" if pose is None else f"{pose['max_error_deg']:.4f}° (±{pose['max_uncertainty_deg']:.4f}°)"
    print(f"| {label} | {row['sim_s']:.1f} s | {lower:.1f} s | {floor:.1f} s | "
          f"{row['vs_floor']:.2f} | {done} | {row['state']} | {perr} |", flush=True)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--speeds", default="20,40,60")
    ap.add_argument("--modes", default="sg,overlap,continuous,planned")
    ap.add_argument("--blur", default="1.0", help="blur bounds (px at the rim, 2048² sensor) of 'planned'")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--sharpness", action="store_true", help="measure the planned passes' sharpness at 2048²")
    a = ap.parse_args()
    cfg = rig_config(a.size)
    modes = set(a.modes.split(","))
    print(describe_machine(), file=sys.stderr)
    print("| run | rig time (simulated) | mode's lower bound | physical floor | / floor | frames | state "
          "| worst pose error (recorded uncertainty) |")
    print("|---|---|---|---|---|---|---|---|")
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
        if "planned" in modes:
            radius = mockup_radius_px(256) * 2048 / 256  # the rim in full-resolution pixels
            for b in [float(x) for x in a.blur.split(",") if x]:
                plan = plan_continuous(Sweep(**BUILD), cfg, SharpnessTarget(max_blur_px=b, radius_px=radius))
                label = (f"continuous planned: blur ≤ {b:g} px at r = {radius:.0f} px, gain {plan.gain:g}, "
                         + ", ".join(f"{c} {p.exposure_s * 1e3:.2f} ms {p.omega_dps:.0f}°/s SNR {p.snr:.0f}"
                                     for c, p in plan.conditions.items()))
                rows.append(one(cfg, plan.sweep, root / f"p{b:g}", label,
                                EngineOptions.of(max_blur_px=b, radius_px=radius)))
                rows[-1]["plan"] = plan.model_dump(exclude={"sweep", "estimate"})
                if a.sharpness:
                    # Blur alone: moving frames against still ones at the same exposure and gain.
                    w = plan.conditions["weak"]
                    sh = measure_sharpness(2048, [w.omega_dps], MARKS, w.exposure_s, gain=plan.gain)
                    rows[-1]["sharpness"] = sh
                    r = sh["rows"][0]
                    print(f"|   sharpness (weak, 2048², {len(MARKS)} azimuths) | mean {r['sharpness']:.4f}, "
                          f"worst {r['sharpness_min']:.4f}; still-frame noise floor {sh['floor']:.4f} |",
                          flush=True)
    if a.json:
        a.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
