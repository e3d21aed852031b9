"""Model selection of the spectral segmenter: how many materials each candidate finds, how well
it segments, and what it costs (results: docs/evaluation.md, "How many materials").

    .venv/bin/python benchmarks/bench_segmenters.py frames   # simulate the frames (cached as .npz)
    .venv/bin/python benchmarks/bench_segmenters.py run      # evaluate every candidate, write table + chart
    # the real resolution (512² cubes), one azimuth, old and new default only:
    .venv/bin/python benchmarks/bench_segmenters.py frames --size 2048 --azimuths 30
    .venv/bin/python benchmarks/bench_segmenters.py run --size 2048 --out bench-out/segmenters-2048 \
        --only "BIC, all pixels (old default)" --only "+ brightness feature, merge 1.5° (new default)"

Frames: ``analysis.study.simframes.simulated_frames`` (the simulator's frame source with its ground
truth) for every satellite × build × lighting × tilt of the catalog (3 × 3 × 3 × 3 = 81 scenes) at
two turntable angles (30°, 200°): 162 frames, on a ``--size``² sensor (default 1024: 256²
super-pixel cubes), cached as .npz under ``--cache``/<size>. K is compared with
``simframes.visible_materials`` (materials with ≥ 0.5 % of the object and ≥ 20 pixels).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

DEFAULT_CACHE = Path("bench-out/segmenter-frames")  # one folder per sensor size below it
# the spectral segmenter's defaults before issue 15; every issue-15 candidate is built without the
# reliability masks issue 23 made the default (robust=False), so the rows measure what they name
OLD_DEFAULT: dict[str, Any] = {"fit_pixels": "all", "foreground": "otsu", "brightness_weight": 0.0,
                               "merge_angle_deg": 1.0, "robust": False}
ISSUE_15: dict[str, Any] = {"robust": False}  # issue 15's default


def cache_frames(folder: Path, size: int, azimuths: tuple[float, ...] = (30.0, 200.0)) -> int:
    """Render the frames missing from ``folder`` (one .npz each); returns how many were rendered."""
    from m2s2hil.analysis.study.simframes import simulated_frames, visible_materials

    folder.mkdir(parents=True, exist_ok=True)
    have = [p.stem for p in folder.glob("*.npz")]
    n = 0
    for f in simulated_frames(size=size, azimuths=azimuths, skip=have):
        np.savez_compressed(folder / f"{f.name}.npz", cube=f.cube, gt=f.gt.astype(np.uint8),
                            materials=np.array(f.materials), exposure_s=f.exposure_s)
        print(f"{f.name}: {f.exposure_s * 1e3:.2f} ms, visible {visible_materials(f.gt)}", flush=True)
        n += 1
    return n


def load_frames(folder: Path) -> list[dict[str, Any]]:
    frames = []
    for p in sorted(folder.glob("*.npz")):
        with np.load(p) as z:
            sat, build, light, elev, az = p.stem.split("_")
            frames.append({"name": p.stem, "satellite": sat, "build": build, "lighting": light,
                           "elevation": elev, "azimuth": float(az), "cube": z["cube"],
                           "gt": z["gt"].astype(np.int64), "materials": [str(m) for m in z["materials"]]})
    return frames


# ------------------------------------------------------------------------------ candidates
def candidates() -> dict[str, Callable[[dict[str, Any]], Any]]:
    """name -> f(frame) returning a label map. All share the Otsu foreground and unit spectra
    unless named otherwise; ``catalog K`` is told the build's material count (not a selector)."""
    from m2s2hil.analysis.segmenters.spectral import SpectralSegmenter

    def spectral(**kw: Any) -> Callable[[dict[str, Any]], Any]:
        seg = SpectralSegmenter(**kw)
        return lambda f: seg.segment(f["cube"])

    def catalog_k(f: dict[str, Any]) -> Any:
        satellite, build = f["satellite"], f["build"]
        return SpectralSegmenter.for_build(satellite, build, robust=False).segment(f["cube"])

    old = OLD_DEFAULT
    homog = {**old, "fit_pixels": "homogeneous", "noise_scaled": False}
    return {
        "BIC, all pixels (old default)": spectral(**old),
        "ICL, all pixels": spectral(**old, criterion="icl"),
        "Bayesian GMM (Dirichlet 1e-3), all pixels": spectral(**old, criterion="bayes"),
        "BIC + merge by valley test": merge_by_valley_test,
        "BIC, log-chromaticity": spectral(**{**old, "features": "log-chromaticity"}),
        "BIC + SLIC majority vote": spectral(**old, smooth=True),
        "BIC, homogeneous pixels (3°)": spectral(**homog),
        "+ noise-scaled homogeneity": spectral(**{**homog, "noise_scaled": True}),
        "+ backdrop foreground": spectral(**{**homog, "noise_scaled": True, "foreground": "backdrop"}),
        "+ brightness feature, merge 1.5° (new default)": spectral(**ISSUE_15),
        "new default with ICL": spectral(**ISSUE_15, criterion="icl"),
        "new default with Bayesian GMM": spectral(**ISSUE_15, criterion="bayes"),
        "catalog K (told the build; not a selector)": catalog_k,
        # issue 23: reliability masks, guided-filter denoising, interior test, censored fit
        "today's default (issue 23)": spectral(),
    }


def merge_by_valley_test(f: dict[str, Any], ratio: float = 0.5) -> np.ndarray:
    """BIC mixture (all pixels), then merge components pairwise while the pooled pixels of the pair,
    projected on their Fisher direction, show no valley: the density between the two modes stays
    above ``ratio`` × the smaller mode (a unimodal pair is one material drawn out by shading)."""
    from scipy import ndimage

    from m2s2hil.analysis.segmenters.spectral import SpectralSegmenter, features_of

    labels = SpectralSegmenter(**OLD_DEFAULT).segment(f["cube"])
    unit = features_of(f["cube"])  # unit-length spectra
    ids = [int(i) for i in np.unique(labels) if i > 0]
    px = {i: unit[:, labels == i].T for i in ids}

    def valley(a: np.ndarray, b: np.ndarray) -> float:
        cov = np.cov(np.vstack([a - a.mean(0), b - b.mean(0)]).T) + 1e-9 * np.eye(a.shape[1])
        w = np.linalg.solve(cov, b.mean(0) - a.mean(0))
        pa, pb = a @ w, b @ w
        both = np.concatenate([pa, pb])
        edges = np.linspace(*np.percentile(both, [0.5, 99.5]), 41)
        hist = ndimage.uniform_filter1d(np.histogram(both, edges)[0].astype(float), 3)
        i1, i2 = sorted(int(np.clip(np.searchsorted(edges, np.median(p)) - 1, 0, 39)) for p in (pa, pb))
        if i2 - i1 < 2:
            return 1.0
        peaks = min(hist[max(0, i1 - 2) : i1 + 3].max(), hist[max(0, i2 - 2) : i2 + 3].max())
        return float(hist[i1 : i2 + 1].min() / max(peaks, 1e-9))

    while len(px) > 1:
        keys = sorted(px)
        pairs = [(valley(px[a], px[b]) if min(len(px[a]), len(px[b])) >= 12 else 1.0, a, b)
                 for n, a in enumerate(keys) for b in keys[n + 1 :]]
        r, a, b = max(pairs)
        if r < ratio:
            break
        px[a] = np.vstack([px[a], px.pop(b)])
        labels[labels == b] = a
    return labels


def evaluate_candidates(frames: list[dict[str, Any]], names: list[str] | None = None) -> list[dict[str, Any]]:
    """Per candidate: K error against the visible materials, macro Dice, seconds per image."""
    from threadpoolctl import threadpool_limits

    from m2s2hil.analysis.metrics.scores import score_clusters
    from m2s2hil.analysis.study.simframes import visible_materials

    rows = []
    for name, fn in candidates().items():
        if names and name not in names:
            continue
        errs, dice, secs = [], [], []
        with threadpool_limits(1):
            for f in frames:
                t0 = time.perf_counter()
                labels = fn(f)
                secs.append(time.perf_counter() - t0)
                k = int(np.count_nonzero(np.bincount(np.asarray(labels).ravel())[1:]))
                errs.append(k - visible_materials(f["gt"]))
                dice.append(score_clusters(f["gt"], labels)[0].macro_dice)
        e = np.array(errs)
        row = {"candidate": name, "images": len(frames), "within_1": float(np.mean(np.abs(e) <= 1)),
               "exact": float(np.mean(e == 0)), "median_error": float(np.median(e)),
               "mean_error": float(e.mean()), "dice": float(np.mean(dice)),
               "dice_sd": float(np.std(dice, ddof=1)), "s_per_image": statistics.median(secs),
               "by_build": {b: float(np.mean([x for x, f in zip(errs, frames, strict=True)
                                              if f["build"] == b])) for b in ("B1", "B2", "B3")}}
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def markdown(rows: list[dict[str, Any]]) -> str:
    lines = ["| candidate | K within ±1 | K exact | median K − true | mean K − true (B1 / B2 / B3) | "
             "macro Dice | s/image (median) |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        b = r["by_build"]
        lines.append(f"| {r['candidate']} | {r['within_1']:.0%} | {r['exact']:.0%} | "
                     f"{r['median_error']:+g} | {r['mean_error']:+.2f} "
                     f"({b['B1']:+.1f} / {b['B2']:+.1f} / {b['B3']:+.1f}) | "
                     f"{r['dice']:.3f} | {r['s_per_image']:.2f} |")
    return "\n".join(lines)


def chart(rows: list[dict[str, Any]], path: Path, title: str) -> None:
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    colours = colormaps["tab20"]
    fig = Figure(figsize=(11.0, 4.6))
    for k, (key, label) in enumerate((("exact", "K exact (share of images)"),
                                      ("within_1", "K within ±1 (share of images)"), ("dice", "macro Dice"))):
        ax = fig.add_subplot(1, 3, k + 1)
        for i, r in enumerate(rows):
            ax.scatter(r["s_per_image"], r[key], s=36, marker="os^Dv<>ph*X"[i % 11], color=colours(i % 20),
                       label=r["candidate"] if k == 0 else None)
        ax.set_xscale("log")
        ax.set_xlabel("s per image (median, 1 thread)")
        ax.set_ylabel(label)
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3, which="both")
        if key != "dice":
            ax.axhline(0.9 if key == "within_1" else 0.6, color="grey", linestyle="--", linewidth=0.8)
    fig.legend(loc="lower center", ncol=3, fontsize=7, frameon=False)
    fig.suptitle(title, fontsize=9)
    fig.subplots_adjust(bottom=0.32, wspace=0.35)
    FigureCanvasAgg(fig)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("what", choices=("frames", "run", "chart"))
    ap.add_argument("--cache", type=Path, default=DEFAULT_CACHE)
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--only", action="append", help="candidate name (repeatable)")
    ap.add_argument("--azimuths", type=float, nargs="+", default=[30.0, 200.0],
                    help="turntable angles rendered by `frames` (default 30 200)")
    ap.add_argument("--out", type=Path, default=Path("bench-out/segmenters"))
    ap.add_argument("--title", help="chart title for `chart`")
    args = ap.parse_args()
    cache = args.cache / str(args.size)
    if args.what == "frames":
        t0 = time.perf_counter()
        n = cache_frames(cache, args.size, tuple(args.azimuths))
        print(f"{n} frames rendered in {time.perf_counter() - t0:.0f} s")
        return
    from m2s2hil.hostinfo import describe_machine

    if args.what == "chart":  # redraw from a previous run's segmenters.json
        rows = json.loads((args.out / "segmenters.json").read_text())
        chart(rows, args.out / "segmenters.png", args.title or "Model selection")
        return
    frames = load_frames(cache)
    if not frames:
        raise SystemExit(f"no frames in {cache}: run `frames --size {args.size}` first")
    rows = evaluate_candidates(frames, args.only)
    args.out.mkdir(parents=True, exist_ok=True)
    side = frames[0]["cube"].shape[1]
    title = (f"Model selection on {len(frames)} simulated frames (3 satellites × 3 builds × 3 lightings × "
             f"3 tilts × {max(1, len(frames) // 81)} azimuth(s), {side}² cubes); dashed: targets")
    (args.out / "segmenters.json").write_text(json.dumps(rows, indent=2) + "\n")
    (args.out / "segmenters.md").write_text(f"{describe_machine()}\n\n{markdown(rows)}\n")
    chart(rows, args.out / "segmenters.png", title)
    print(markdown(rows))


if __name__ == "__main__":
    main()
