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

ROOT = Path(__file__).resolve().parents[1]
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
    ap.add_argument("--chart", nargs="+", type=Path, help="only draw the chart from these --json files")
    a = ap.parse_args()
    if a.chart:
        chart(a.chart, ROOT / "docs" / "images" / "rig_time_vs_sharpness.png")
        return
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
            speeds = [float(x) for x in a.speeds.split(",") if x]
            for v in speeds:
                rows.append(one(cfg, Sweep(**BUILD, mode="continuous"), root / f"c{v:g}",
                                f"continuous {v:g}°/s", EngineOptions.of(speed_dps=v)))
                rows[-1]["speed_dps"] = v
            if a.sharpness:
                exp = Sweep(**BUILD).exposure_for("weak")
                sh = measure_sharpness(2048, speeds, MARKS, exp)
                for r in sh["rows"]:
                    row = next(x for x in rows if x.get("speed_dps") == r["speed_dps"])
                    row["sharpness"] = {"rows": [r], "floor": sh["floor"], "floor_min": sh["floor_min"]}
                    print(f"|   sharpness at {r['speed_dps']:g}°/s (weak, {exp * 1e3:g} ms, 2048²) | mean "
                          f"{r['sharpness']:.4f}, worst {r['sharpness_min']:.4f}; still-frame floor "
                          f"{sh['floor']:.4f} |", flush=True)
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


def chart(paths: list[Path], out: Path) -> None:
    """Rig time against measured sharpness from one or more ``--json`` files (rows without a
    sharpness measurement are drawn at the still-frame noise floor when they are stop-and-go)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for p in paths for r in json.loads(p.read_text())]
    floor = next((r["sharpness"]["floor"] for r in rows if r.get("sharpness")), 1.0)
    fig, ax = plt.subplots(figsize=(7.5, 4.5), dpi=120)
    for r in rows:
        sh = r.get("sharpness")
        if sh is None and not r["run"].startswith("stop-and-go"):
            continue
        y, lo = (floor, floor) if sh is None else (sh["rows"][0]["sharpness"], sh["rows"][0]["sharpness_min"])
        colour = "tab:blue" if r["run"].startswith("stop") else (
            "tab:green" if "planned" in r["run"] else "tab:orange")
        ax.errorbar(r["sim_s"], y, yerr=[[y - lo], [0]], fmt="o", color=colour, capsize=3)
        name = r["run"].split(" at r =")[0].replace(" (before: no overlap)", ", not overlapped")
        pe = r.get("pose") or {}
        if pe.get("max_error_deg") is not None and pe["max_error_deg"] == pe["max_error_deg"]:
            name += f"\npose err ≤ {pe['max_error_deg']:.3f}°"
        dy = -22 if "not overlapped" in name else -12
        ax.annotate(name, (r["sim_s"], y), textcoords="offset points", xytext=(-60 if dy == -22 else 6, dy),
                    fontsize=7)
    fl = rows[0]["physical_floor_s"]
    ax.axvline(fl, color="grey", ls="--", lw=1)
    ax.axvline(1.15 * fl, color="grey", ls=":", lw=1)
    ax.axhline(0.99, color="red", ls=":", lw=1)
    ax.text(fl, ax.get_ylim()[0], " physical floor", fontsize=7, va="bottom", color="grey")
    ax.set_xlabel("rig time of a full build, 324 frames (s, virtual clock)")
    ax.set_ylabel("sharpness vs a still frame (mean, bar to worst)")
    ax.set_title("Rig time against sharpness (weak light, 2048²; bench_rig_time.py)", fontsize=9)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)


if __name__ == "__main__":
    main()
