"""Robustness of the spectral segmenter over a condition matrix (issue 23 item 1).

Each cell renders the simulator's frames (``analysis.study.simframes.simulated_frames``) of
3 satellites × 3 builds at one view (E1, azimuth 30°) under one condition and segments them with
the segmenter before (``robust=False``) and after (``robust=True``, the default) the exposure /
clipping / noise handling of ``segmenters.normalise``. Per cell and segmenter: the share of
frames with K within ±1 of the visible materials, mean K − true, mean macro Dice and its
difference to the reference cell (peak 60 %, weak light, 1024² sensor: 256² cubes, the size
of the issue-15 model-selection study; at 128² cubes the 10-material builds already fail there)
of the same segmenter.

Run (minutes on 2 cores; results to docs/images/robustness.{json,png})::

    nice -n 10 .venv/bin/python benchmarks/bench_robustness.py [--size 1024] [--only peak-4%,...]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "images"

# name -> simulated_frames keywords (lighting "weak" unless given); "peak-60%" is the reference
CELLS: dict[str, dict[str, Any]] = {
    **{f"peak-{round(p * 100)}%": {"peak_fraction": p}
       for p in (0.02, 0.04, 0.05, 0.1, 0.3, 0.6, 1.0, 1.5, 2.0)},
    **{f"spot-{a}°": {"lightings": ("directional",), "spot_angle_deg": float(a)} for a in (0, 45, 80, 85)},
    "read-noise-40e": {"read_noise_e": 40.0},
    "temp-45C": {"temperature_c": 45.0},
    "sensor-512": {"size": 512},
    "fill-0.25": {"fill": 0.25},
}
REFERENCE = "peak-60%"


def run_cell(spec: dict[str, Any], size: int) -> list[dict[str, Any]]:
    from threadpoolctl import threadpool_limits

    from m2s2hil.analysis.metrics.scores import score_clusters
    from m2s2hil.analysis.segmenters.spectral import SpectralSegmenter
    from m2s2hil.analysis.study.simframes import simulated_frames, visible_materials

    kw = {"lightings": ("weak",), "size": size, **spec}
    frames = simulated_frames(builds=("B1", "B2", "B3"), elevations=("E1",), azimuths=(30.0,), **kw)
    rows = []
    with threadpool_limits(1):
        for f in frames:
            true = visible_materials(f.gt)
            for robust in (False, True):
                t0 = time.perf_counter()
                a = SpectralSegmenter(robust=robust).analyse(f.cube)
                dt = time.perf_counter() - t0
                rows.append({"frame": f.name, "build": f.build, "robust": robust, "k": a.n_materials,
                             "true": true, "dice": float(score_clusters(f.gt, a.labels)[0].macro_dice),
                             "saturated": float(f.saturated.mean()) if f.saturated is not None else 0.0,
                             "s": dt})
    return rows


def summarise(cells: dict[str, list[dict[str, Any]]]) -> list[dict[str, Any]]:
    ref = {r: float(np.mean([x["dice"] for x in cells[REFERENCE] if x["robust"] is r]))
           for r in (False, True)} if REFERENCE in cells else {False: np.nan, True: np.nan}
    out = []
    for name, rows in cells.items():
        for r in (False, True):
            sel = [x for x in rows if x["robust"] is r]
            err = np.array([x["k"] - x["true"] for x in sel])
            dice = float(np.mean([x["dice"] for x in sel]))
            out.append({"cell": name, "robust": r, "frames": len(sel),
                        "within_1": float(np.mean(np.abs(err) <= 1)),
                        "mean_error": float(err.mean()), "errors": err.tolist(), "dice": dice,
                        "dice_delta": dice - ref[r], "s_median": float(np.median([x["s"] for x in sel]))})
    return out


def markdown(summary: list[dict[str, Any]]) -> str:
    lines = ["| cell | K ±1 before | K ±1 after | mean K − true before / after | Dice before | Dice after |"
             " ΔDice vs 60 % after | K − true per frame after |", "|---|---|---|---|---|---|---|---|"]
    by = {(s["cell"], s["robust"]): s for s in summary}
    for cell in dict.fromkeys(s["cell"] for s in summary):
        b, a = by[(cell, False)], by[(cell, True)]
        lines.append(f"| {cell} | {b['within_1']:.0%} | {a['within_1']:.0%} | {b['mean_error']:+.2f} / "
                     f"{a['mean_error']:+.2f} | {b['dice']:.3f} | {a['dice']:.3f} | {a['dice_delta']:+.3f} | "
                     f"{' '.join(f'{e:+d}' for e in a['errors'])} |")
    return "\n".join(lines) + "\n"


def chart(summary: list[dict[str, Any]], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells = list(dict.fromkeys(s["cell"] for s in summary))
    by = {(s["cell"], s["robust"]): s for s in summary}
    x = np.arange(len(cells))
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(12, 7), sharex=True)
    for off, r, label, colour in ((-0.2, False, "before (robust=False)", "#bbbbbb"),
                                  (0.2, True, "after (robust=True)", "#1f77b4")):
        ax1.bar(x + off, [by[(c, r)]["within_1"] for c in cells], 0.4, label=label, color=colour)
        ax2.bar(x + off, [by[(c, r)]["dice_delta"] for c in cells], 0.4, label=label, color=colour)
    ax1.axhline(0.9, color="red", lw=1, ls="--", label="goal ≥ 90 %")
    ax1.set_ylabel("K within ±1 of visible")
    ax1.set_ylim(0, 1.05)
    ax1.legend(loc="lower right", fontsize=8)
    ax2.axhline(-0.05, color="red", lw=1, ls="--", label="goal ≥ −0.05")
    ax2.axhline(0, color="black", lw=0.5)
    ax2.set_ylabel("macro Dice − Dice at 60 % peak")
    ax2.set_xticks(x, cells, rotation=45, ha="right")
    ax2.legend(loc="lower right", fontsize=8)
    ax1.set_title(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024, help="sensor side (cube side = size / 4)")
    ap.add_argument("--only", default="", help="comma-separated cell names")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    names = [n for n in CELLS if not args.only or n in args.only.split(",")]
    raw_path = args.out / "robustness.json"
    cells: dict[str, list[dict[str, Any]]] = {}
    if raw_path.exists():  # resume: cells already measured are kept
        cells = json.loads(raw_path.read_text())["cells"]
    t0 = time.time()
    for name in names:
        if name in cells:
            continue
        spec = dict(CELLS[name])
        cells[name] = run_cell(spec, int(spec.pop("size", args.size)))
        meta = {"machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
                "python": platform.python_version(), "date": datetime.now(UTC).isoformat(timespec="minutes"),
                "size": args.size}
        args.out.mkdir(parents=True, exist_ok=True)
        raw_path.write_text(json.dumps({"meta": meta, "cells": cells}, indent=0) + "\n")
        print(f"{name}: {time.time() - t0:.0f} s", flush=True)
    ordered = {n: cells[n] for n in CELLS if n in cells}
    summary = summarise(ordered)
    print(markdown(summary))
    n_frames = len(next(iter(ordered.values()))) // 2 if ordered else 0
    chart(summary, args.out / "robustness.png",
          f"Spectral segmenter over conditions: {n_frames} frames per cell "
          f"(3 satellites × 3 builds, E1, 30°), {args.size // 4}² cubes")


if __name__ == "__main__":
    main()
