"""Exposure brackets end to end: captured by the engine on the simulated rig, scored by ``evaluate``.

Per satellite × build (9 sessions): weak diffuse and the spotlight at tilt E1, azimuth 0–350° every
``--step``, each spotlight pose again at ``--factor`` × its exposure (``Sweep.bracket``), the plan's
fixed exposures (weak 8 ms, directional 3 ms), the real engine and store (``simulate_session``).
Then ``evaluate_jobs`` with one mixture per sweep (``spectral-sweep`` and its RGB counterpart),
twice: each spotlight pose merged with its bracket (``EvalOptions.bracket``, the default) and its
own frame alone (``--no-bracket``). The weak-light images are the same in both runs and are each
pose's reference.

Per run and segmenter: K within ±1 of the visible materials (``simframes.visible_materials`` of the
truth on the cube's grid), macro Dice, and ΔDice against weak light paired by pose, with a 95 % t
interval; per build, the frames within ±1. ``--pose`` also scores ``spectral-pose`` (each spotlit
pose labelled with the materials of its weak-light frame, ``segmenters.pose``). Results go to
``docs/images/bracket_capture_spot<angle>[_pose].json``.

    nice -n 10 .venv/bin/python benchmarks/bench_bracket_capture.py [--size 1024] [--step 10]
        [--spot 45] [--factor 16] [--pose] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import statistics
import tempfile
import time
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from m2s2hil.analysis.evaluation.evaluate import evaluate_jobs
from m2s2hil.analysis.evaluation.jobs import FrameJob, collect_jobs
from m2s2hil.analysis.evaluation.loading import load_truth
from m2s2hil.analysis.evaluation.options import EvalOptions
from m2s2hil.analysis.study.simframes import visible_materials
from m2s2hil.analysis.study.stability import simulate_session
from m2s2hil.store.layout import JOURNAL

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "images"
SATELLITES = ("voyager", "iss", "hubble")
BUILDS = ("B1", "B2", "B3")
SEGMENTERS = ("spectral-sweep", "rgb-sweep")


def capture(root: Path, *, size: int, step: float, spot: float, factor: float, seed: int) -> float:
    t0 = time.perf_counter()
    for sat in SATELLITES:
        for build in BUILDS:
            simulate_session(
                root,
                satellite=sat,
                build=build,
                lighting=("weak", "directional"),
                tilts=("E1",),
                azimuth_step_deg=step,
                size=size,
                seed=seed,
                qc=None,
                session_id=f"{sat}-{build}",
                bracket={"directional": [factor]},
                spot_angle_deg=spot,
            )
    return time.perf_counter() - t0


def true_counts(jobs: Sequence[FrameJob], shapes: dict[str, list[int]]) -> dict[str, int]:
    out = {}
    for job in jobs:
        gt = load_truth(job, tuple(shapes[job.image_id][1:]))
        out[job.image_id] = visible_materials(gt) if gt is not None else -1
    return out


def pose(rec: dict[str, Any]) -> tuple[str, str, float]:
    return rec["satellite"], rec["build"], round(float(rec["azimuth_deg"]), 3)


def summarise(records: list[dict[str, Any]], truth: dict[str, int],
              names: Sequence[str] = SEGMENTERS) -> dict[str, Any]:
    out: dict[str, Any] = {}
    weak = {pose(r): r for r in records if r["lighting"] == "weak" and not r["error"]}
    for name in names:
        rows = {}
        for light in ("weak", "directional"):
            recs = [
                r
                for r in records
                if r["lighting"] == light and not r["error"] and "dice" in r["results"].get(name, {})
            ]
            within = [abs(r["results"][name]["n_segments"] - truth[r["image_id"]]) <= 1 for r in recs]
            dice = np.array([r["results"][name]["dice"] for r in recs])
            paired = np.array(
                [
                    r["results"][name]["dice"] - weak[pose(r)]["results"][name]["dice"]
                    for r in recs
                    if pose(r) in weak and "dice" in weak[pose(r)]["results"][name]
                ]
            )
            half = (
                float(stats.t.ppf(0.975, paired.size - 1) * paired.std(ddof=1) / np.sqrt(paired.size))
                if paired.size > 1
                else float("nan")
            )
            builds = {}
            for sat in SATELLITES:
                for build in BUILDS:
                    mine = [r for r in recs if (r["satellite"], r["build"]) == (sat, build)]
                    err = [r["results"][name]["n_segments"] - truth[r["image_id"]] for r in mine]
                    builds[f"{sat}_{build}"] = {
                        "within": int(sum(abs(e) <= 1 for e in err)),
                        "frames": len(mine),
                        "mean_error": float(np.mean(err)) if err else float("nan"),
                    }
            rows[light] = {
                "frames": len(recs),
                "k_within": float(np.mean(within)) if within else float("nan"),
                "dice": float(dice.mean()) if dice.size else float("nan"),
                "delta_dice": float(paired.mean()) if paired.size else float("nan"),
                "delta_half": half,
                "clipped_fraction": float(np.mean([r.get("clipped_fraction") or 0.0 for r in recs])),
                "bracket_frames": sorted({int(r.get("bracket_frames", 1)) for r in recs}),
                "builds": builds,
            }
        out[name] = rows
    return out


def markdown(runs: dict[str, dict[str, Any]], names: Sequence[str] = SEGMENTERS) -> str:
    lines = [
        "| segmenter | spotlight pose | K ±1 | Dice | ΔDice vs weak (paired) | 95 % interval |",
        "|---|---|---|---|---|---|",
    ]
    for name in names:
        ref = runs["bracket"][name]["weak"]
        lines.append(
            f"| {name} | weak light (reference) | {ref['k_within']:.1%} | {ref['dice']:.3f} | 0 | – |"
        )
        for run, label in (("own", "its own frame"), ("bracket", "merged with its bracket")):
            d = runs[run][name]["directional"]
            lines.append(
                f"| {name} | {label} | {d['k_within']:.1%} | {d['dice']:.3f} | {d['delta_dice']:+.3f} | "
                f"{d['delta_dice'] - d['delta_half']:+.3f} to {d['delta_dice'] + d['delta_half']:+.3f} |"
            )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024, help="sensor side (cube side = size / 4)")
    ap.add_argument("--step", type=float, default=10.0, help="azimuth step, degrees")
    ap.add_argument("--spot", type=float, default=45.0, help="spotlight incidence (the built-in rig's: 45°)")
    ap.add_argument("--factor", type=float, default=16.0, help="the bracket's exposure multiple")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--keep", type=Path, help="capture into (or reuse) this data root instead of a temporary one"
    )
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--name", default=None, help="output stem (default bracket_capture_spot<angle>[_pose])")
    ap.add_argument("--pose", action="store_true", help="also score spectral-pose")
    args = ap.parse_args()
    names = (*SEGMENTERS, "spectral-pose") if args.pose else SEGMENTERS
    root = args.keep or Path(tempfile.mkdtemp(prefix="bracket-capture-"))
    started = datetime.now(UTC)
    capture_s = 0.0
    if not any(root.glob(f"*/{JOURNAL}")):
        capture_s = capture(
            root, size=args.size, step=args.step, spot=args.spot, factor=args.factor, seed=args.seed
        )
        print(f"captured 9 sessions in {capture_s:.0f} s", flush=True)
    jobs, _ = collect_jobs(root)
    runs: dict[str, dict[str, Any]] = {}
    wall: dict[str, float] = {}
    truth: dict[str, int] | None = None
    for run, merge in (("bracket", True), ("own", False)):
        t0 = time.perf_counter()
        result = evaluate_jobs(
            jobs,
            EvalOptions(multi="spectral-sweep", mtc_for="none", bracket=merge, extra=tuple(names[2:])),
            workers=0,
        )
        wall[run] = time.perf_counter() - t0
        if truth is None:
            truth = true_counts(
                jobs, {r["image_id"]: r["cube_shape"] for r in result.records if not r["error"]}
            )
        runs[run] = summarise(result.records, truth, names)
        print(f"{run}: evaluated {len(jobs)} images in {wall[run]:.0f} s", flush=True)
    table = markdown(runs, names)
    print(table)
    args.out.mkdir(parents=True, exist_ok=True)
    stem = args.name or f"bracket_capture_spot{args.spot:g}" + ("_pose" if args.pose else "")
    (args.out / f"{stem}.json").write_text(
        json.dumps(
            {
                "started": started.isoformat(timespec="seconds"),
                "machine": platform.processor() or platform.machine(),
                "python": platform.python_version(),
                "size": args.size,
                "step": args.step,
                "spot_angle_deg": args.spot,
                "factor": args.factor,
                "seed": args.seed,
                "images": len(jobs),
                "capture_s": capture_s,
                "evaluate_s": wall,
                "median_evaluate_s": statistics.median(wall.values()),
                "runs": runs,
                "table": table,
            },
            indent=1,
        )
        + "\n"
    )
    if args.keep is None:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
