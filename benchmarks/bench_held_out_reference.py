"""Is the spotlight's Dice loss in the pixels? Held-out supervised references on the robustness cells.

Per cell (``bench_robustness.CELLS``, rendered view by view as ``bench_robustness_wide.run_view``
renders them: the same frames, seed 0, E1) and per satellite × build, the azimuths 0–330° every
``--step``. Each view is labelled by classifiers trained on the build's other views of the same
cell (``metrics.bounds.held_out_dice``), and scored like the segmenter (macro Dice, oracle
matching); ``qda-in`` is ``pixel_bounds``' QDA fitted on the view itself. ``--refs`` names them as
``model:features`` (``qda``/``boosting`` × ``segmenter``/``pixel``/``context``).

Each reference's ΔDice against its own 60 % cell, paired by pose with a 95 % t interval, is drawn
beside the segmenter's (``spectral-sweep`` with per-band masks, frame for frame from the whole-sweep
run ``--segmenter-json``, the same poses), with the goal's −0.05 line:
``docs/images/held_out_reference.{json,png}``.

    nice -n 10 .venv/bin/python benchmarks/bench_held_out_reference.py [--step 30]
        [--cells peak-60%,spot-0°,...] [--refs boosting:context,qda:segmenter,...]
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
from bench_robustness import REFERENCE, render_views  # type: ignore[import-not-found]
from scipy import stats

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "images"
GOAL = -0.05
DEFAULT_CELLS = ("peak-60%", "spot-0°", "spot-45°", "spot-80°", "spot-0°-x16", "spot-45°-x16", "spot-80°-x16")
DEFAULT_REFS = ("qda:segmenter", "boosting:segmenter", "boosting:pixel", "boosting:context")
LABELS = {
    "segmenter": "the segmenter (unsupervised)",
    "qda-in": "Gaussian a material, fitted on the frame",
    "qda:segmenter": "Gaussian a material, held out",
    "boosting:segmenter": "trees, held out",
    "boosting:pixel": "trees + every band's log, held out",
    "boosting:context": "trees + logs + neighbours, held out",
}


def run_cell(cell: str, refs: list[str], azimuths: list[float], size: int, seed: int) -> list[dict[str, Any]]:
    from threadpoolctl import threadpool_limits

    from m2s2hil.analysis.metrics.bounds import held_out_dice, pixel_bounds

    rows: list[dict[str, Any]] = []
    with threadpool_limits(1):
        for build, frames in render_views(cell, azimuths, size, seed).items():
            views = [(f.azimuth_deg, f.cube, f.gt) for f in frames]
            cubes, gts = [v[1] for v in views], [v[2] for v in views]
            scores = {"qda-in": [pixel_bounds(c, g).qda for c, g in zip(cubes, gts, strict=True)]}
            for ref in refs:
                model, features = ref.split(":")
                t0 = time.process_time()
                scores[ref] = held_out_dice(cubes, gts, model=model, features=features, seed=seed)  # type: ignore[arg-type]
                scores[f"{ref}:s"] = [(time.process_time() - t0) / len(views)] * len(views)
            for i, (az, _, gt) in enumerate(views):
                rows.append(
                    {
                        "cell": cell,
                        "pose": f"{build}_{az:g}",
                        "build": build,
                        "azimuth": az,
                        "materials": int(np.unique(gt[gt > 0]).size),
                        **{k: v[i] for k, v in scores.items()},
                    }
                )
            print(
                f"  {cell} {build}: " + ", ".join(f"{r} {np.mean(scores[r]):.3f}" for r in ["qda-in", *refs]),
                flush=True,
            )
    return rows


def paired(rows: list[dict[str, Any]], ref: dict[str, float], key: str) -> dict[str, float]:
    d = np.array([r[key] - ref[r["pose"]] for r in rows if r["pose"] in ref and key in r])
    if d.size < 2:
        return {
            "delta": float(d.mean()) if d.size else float("nan"),
            "low": float("nan"),
            "high": float("nan"),
        }
    half = float(stats.t.ppf(0.975, d.size - 1) * d.std(ddof=1) / np.sqrt(d.size))
    return {"delta": float(d.mean()), "low": float(d.mean()) - half, "high": float(d.mean()) + half}


def summarise(rows: list[dict[str, Any]], keys: list[str]) -> list[dict[str, Any]]:
    cells = list(dict.fromkeys(r["cell"] for r in rows))
    base = {k: {r["pose"]: r[k] for r in rows if r["cell"] == REFERENCE and k in r} for k in keys}
    out = []
    for cell in cells:
        mine = [r for r in rows if r["cell"] == cell]
        out.append(
            {
                "cell": cell,
                "frames": len(mine),
                **{
                    k: {"dice": float(np.mean([r[k] for r in mine if k in r])), **paired(mine, base[k], k)}
                    for k in keys
                    if any(k in r for r in mine)
                },
            }
        )
    return out


def join_segmenter(rows: list[dict[str, Any]], path: Path, size: int, seed: int) -> None:
    """Each row's Dice of the segmenter from a ``bench_robustness_wide`` JSON (same cell and pose),
    when that run rendered the same frames (sensor size and seed)."""
    if not path.is_file():
        return
    data = json.loads(path.read_text())
    if (data["meta"].get("size"), data["meta"].get("seed")) != (size, seed):
        print(f"{path.name}: another size or seed; the segmenter is left out", flush=True)
        return
    for r in rows:
        hit = next((f for f in data["cells"].get(r["cell"], []) if f["pose"] == r["pose"]), None)
        if hit is not None:
            r["segmenter"] = float(hit["dice"])


def markdown(summary: list[dict[str, Any]], keys: list[str]) -> str:
    lines = ["| cell | " + " | ".join(keys) + " |", "|---" * (len(keys) + 1) + "|"]
    for s in summary:
        cells = []
        for k in keys:
            v = s.get(k)
            if v is None:
                cells.append("–")
            elif s["cell"] == REFERENCE:
                cells.append(f"{v['dice']:.3f} (reference)")
            else:
                cells.append(f"{v['delta']:+.3f} [{v['low']:+.3f}, {v['high']:+.3f}]")
        lines.append(f"| {s['cell']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def chart(summary: list[dict[str, Any]], keys: list[str], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [s for s in summary if s["cell"] != REFERENCE]
    fig, ax = plt.subplots(figsize=(10, 5.6))
    width = 0.8 / len(keys)
    colours = plt.get_cmap("tab10")
    for j, k in enumerate(keys):
        x = np.arange(len(shown)) + (j - (len(keys) - 1) / 2) * width
        d = np.array([s[k]["delta"] if k in s else np.nan for s in shown])
        lo = np.array([s[k]["low"] if k in s else np.nan for s in shown])
        hi = np.array([s[k]["high"] if k in s else np.nan for s in shown])
        ax.bar(
            x,
            d,
            width,
            label=LABELS.get(k, k),
            color="#444444" if k == "segmenter" else colours(j),
            yerr=np.vstack([d - lo, hi - d]),
            capsize=2,
            error_kw={"ecolor": "#333333", "lw": 0.8},
        )
    ax.axhline(GOAL, color="#c0392b", ls="--", lw=1, label="goal: ΔDice ≥ −0.05")
    ax.axhline(0, color="black", lw=0.6)
    ax.set_xticks(range(len(shown)), [s["cell"] for s in shown], fontsize=9)
    ax.set_ylabel("ΔDice vs its own 60 % peak cell\n(paired by pose, 95 % t interval)", fontsize=9)
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8, ncol=3, loc="upper center", bbox_to_anchor=(0.5, -0.1))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def title(views: int, seed: int) -> str:
    return (
        f"Told the materials by the build's other views ({views} views a build, seed {seed}), "
        "against the segmenter"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=lambda v: v.split(","), default=list(DEFAULT_CELLS))
    ap.add_argument("--refs", type=lambda v: v.split(","), default=list(DEFAULT_REFS))
    ap.add_argument(
        "--step", type=float, default=30.0, help="azimuth step, degrees (views per build: 360 / step)"
    )
    ap.add_argument("--size", type=int, default=1024, help="sensor side (cube side = size / 4)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--segmenter-json", type=Path, default=OUT / "robustness_wide_sweep_bracket.json")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--name", default="held_out_reference")
    ap.add_argument("--replot", action="store_true", help="draw the chart again from the run's JSON")
    args = ap.parse_args()
    if args.replot:
        data = json.loads((args.out / f"{args.name}.json").read_text())
        keys = ["segmenter", "qda-in", *data["meta"]["refs"]]
        chart(
            data["summary"],
            keys,
            args.out / f"{args.name}.png",
            title(len(data["meta"]["azimuths"]), args.seed),
        )
        return
    if REFERENCE not in args.cells:
        args.cells.insert(0, REFERENCE)
    azimuths = [float(a) for a in np.arange(0.0, 360.0, args.step)]
    started, t0 = datetime.now(UTC), time.time()
    rows: list[dict[str, Any]] = []
    keys = ["segmenter", "qda-in", *args.refs]
    for cell in args.cells:
        rows += run_cell(cell, args.refs, azimuths, args.size, args.seed)
        join_segmenter(rows, args.segmenter_json, args.size, args.seed)
        summary = summarise(rows, keys)
        meta = {
            "started": started.isoformat(timespec="seconds"),
            "wall_s": time.time() - t0,
            "machine": platform.processor() or platform.machine(),
            "python": platform.python_version(),
            "azimuths": azimuths,
            "size": args.size,
            "seed": args.seed,
            "refs": args.refs,
            "segmenter_json": str(args.segmenter_json.relative_to(ROOT))
            if args.segmenter_json.is_relative_to(ROOT)
            else str(args.segmenter_json),
        }
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / f"{args.name}.json").write_text(
            json.dumps({"meta": meta, "summary": summary, "rows": rows}, indent=0) + "\n"
        )
    table = markdown(summary, keys)
    print(table)
    chart(summary, keys, args.out / f"{args.name}.png", title(len(azimuths), args.seed))


if __name__ == "__main__":
    main()
