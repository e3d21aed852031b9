"""Charts of the evaluation and QC reports (matplotlib, Agg).

Figures are built with ``matplotlib.figure.Figure`` and saved through the Agg canvas:
no pyplot, no global backend switch, safe in worker threads and on headless machines.
Every function writes one PNG and returns its path (or bytes for the HTML report).
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from m2s2hil.analysis.evaluation.table2 import LIGHTING_TITLES, LIGHTINGS, METRIC_TITLES, METRICS, Table2Row

RGB_COLOUR = "#d95f02"
MULTI_COLOUR = "#1b9e77"
LIGHT_COLOURS = {"directional": "#7570b3", "weak": "#66a61e", "strong": "#e6ab02"}


def _save(fig: Figure, path: str | Path) -> Path:
    FigureCanvasAgg(fig)
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(p, dpi=110, bbox_inches="tight")
    return p


def _png(fig: Figure) -> bytes:
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    return buf.getvalue()


def row_label(r: Table2Row) -> str:
    return f"{r.satellite_name} {r.build} ({r.classes}) {r.elevation}"


def table2_chart(rows: Sequence[Table2Row], path: str | Path, *, rho: float = 0.9) -> Path:
    """Macro precision, recall and Dice per row, RGB vs Multi, significance stars on the better bar
    (paired t-test at the assumed within-image correlation ``rho``, named in the title)."""
    return _save(table2_figure(rows, rho=rho), path)


def table2_figure(rows: Sequence[Table2Row], *, rho: float = 0.9) -> Figure:
    rows = [r for r in rows if r.cells]
    fig = Figure(figsize=(max(6.0, 0.9 * len(rows) + 2), 8.5))
    x = np.arange(len(rows))
    w = 0.38
    for i, metric in enumerate(METRICS):
        ax = fig.add_subplot(len(METRICS), 1, i + 1)
        rgb = [r.cells[metric].rgb if metric in r.cells else np.nan for r in rows]
        multi = [r.cells[metric].multi if metric in r.cells else np.nan for r in rows]
        ax.bar(x - w / 2, rgb, w, label="RGB", color=RGB_COLOUR)
        ax.bar(x + w / 2, multi, w, label="Multi", color=MULTI_COLOUR)
        for j, r in enumerate(rows):
            cell = r.cells.get(metric)
            if cell is not None and cell.winner:
                xx = x[j] + (w / 2 if cell.winner == "multi" else -w / 2)
                ax.text(
                    xx, max(cell.rgb, cell.multi) + 0.01, cell.stars, ha="center", va="bottom", fontsize=9
                )
        ax.set_ylim(0, 1.08)
        ax.set_ylabel(METRIC_TITLES[metric])
        ax.set_xticks(x)
        ax.set_xticklabels(
            [row_label(r) for r in rows] if i == len(METRICS) - 1 else [], rotation=30, ha="right"
        )
        ax.grid(axis="y", alpha=0.3)
        if i == 0:
            ax.legend(loc="lower right", fontsize=8)
            ax.set_title(
                f"RGB vs multispectral (* p < 0.05, ** p < 0.01, paired t-test, assumed ρ = {rho:g})"
            )
    return fig


MTC_MODE_TITLES = {
    "labels": "label mode: full label map, aligned",
    "binary": "binary mode: foreground vs background (the paper's HIL setting)",
}


def mtc_chart(rows: Sequence[Table2Row], path: str | Path, *, mode: str | None = None,
              segmenter: str | None = None) -> Path:
    """mTC per row and lighting condition on the full 0–1 axis, n (images) on every bar, the mode
    (labels or binary) and the segmenter in the title: the two modes measure different things."""
    return _save(mtc_figure(rows, mode=mode, segmenter=segmenter), path)


def mtc_figure(rows: Sequence[Table2Row], *, mode: str | None = None, segmenter: str | None = None) -> Figure:
    rows = [r for r in rows if r.mtc]
    lights = [lt for lt in LIGHTINGS if any(lt in r.mtc for r in rows)]
    fig = Figure(figsize=(max(6.0, 0.9 * len(rows) + 2), 4.4))
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(len(rows))
    w = 0.8 / max(1, len(lights))
    total = 0
    for i, lt in enumerate(lights):
        vals = [r.mtc[lt][0] if lt in r.mtc else np.nan for r in rows]
        ns = [r.mtc[lt][1] if lt in r.mtc else 0 for r in rows]
        total += sum(ns)
        xs = x + (i - (len(lights) - 1) / 2) * w
        ax.bar(xs, vals, w, label=LIGHTING_TITLES.get(lt, lt), color=LIGHT_COLOURS.get(lt))
        for xx, v, n in zip(xs, vals, ns, strict=True):
            if n and math.isfinite(v):
                ax.text(xx, min(v, 1.0) + 0.01, f"{v:.3f}\nn={n}", ha="center", va="bottom", fontsize=6)
    ax.set_ylim(0.0, 1.15)
    ax.set_yticks(np.linspace(0.0, 1.0, 6))
    ax.set_xticks(x)
    ax.set_xticklabels([row_label(r) for r in rows], rotation=30, ha="right")
    ax.set_ylabel("mTC (mean over images)")
    what = MTC_MODE_TITLES.get(mode or "", mode or "mode not given")
    who = f"{segmenter}, " if segmenter else ""
    ax.set_title(f"Prediction stability (mTC), {who}{what}; {total} images, K = 8 shifts", fontsize=9)
    ax.grid(axis="y", alpha=0.3)
    if lights:
        ax.legend(fontsize=8, loc="lower right")
    return fig


def speed_accuracy_chart(
    points: Sequence[Mapping[str, Any]], path: str | Path, *, title: str = "Speed against accuracy"
) -> Path:
    """Mean time per image (log x) against mean macro Dice, one point per segmenter.

    Bars: 95 % confidence intervals of both means (1.96 · SD / √n).
    """
    fig = Figure(figsize=(6.0, 4.2))
    ax = fig.add_subplot(1, 1, 1)
    for p in points:
        t, d = float(p["time_mean_s"]), float(p.get("dice_mean", math.nan))
        if not math.isfinite(d):
            continue
        n_t, n_d = max(1, int(p.get("images", 1))), max(1, int(p.get("scored_images", 1)))
        ci_t = 1.96 * float(p.get("time_sd_s", 0.0)) / math.sqrt(n_t)
        sd_d = float(p.get("dice_sd", math.nan))
        ci_d = 1.96 * sd_d / math.sqrt(n_d) if math.isfinite(sd_d) else 0.0
        ax.errorbar(
            [t],
            [d],
            xerr=[[min(ci_t, 0.99 * t)], [ci_t]],
            yerr=[ci_d],
            fmt="o",
            capsize=3,
            label=f"{p['segmenter']} (n={n_d})",
        )
        ax.annotate(str(p["segmenter"]), (t, d), textcoords="offset points", xytext=(6, 4), fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel("time per image (s, segmentation only)")
    ax.set_ylabel("macro Dice")
    ax.set_title(f"{title} (bars: 95 % CI of the mean)")
    ax.grid(alpha=0.3, which="both")
    if ax.lines:
        ax.legend(fontsize=7, loc="best")
    return _save(fig, path)


def stability_chart(rows: Sequence[Mapping[str, Any]], path: str | Path) -> Path:
    """The failure study: macro Dice and mTC per scenario and segmenter."""
    scenarios = list(dict.fromkeys(r["scenario"] for r in rows))
    segs = list(dict.fromkeys(r["segmenter"] for r in rows))
    fig = Figure(figsize=(max(7.0, 1.6 * len(scenarios) + 2), 6.5))
    x = np.arange(len(scenarios))
    w = 0.8 / max(1, len(segs))
    for k, (key, label) in enumerate((("dice", "macro Dice"), ("mtc", "mTC (labels, aligned)"))):
        ax = fig.add_subplot(2, 1, k + 1)
        for i, seg in enumerate(segs):
            vals = []
            for sc in scenarios:
                hit = [r.get(key) for r in rows if r["scenario"] == sc and r["segmenter"] == seg]
                v = hit[0] if hit and isinstance(hit[0], (int, float)) else np.nan
                vals.append(v)
            ax.bar(x + (i - (len(segs) - 1) / 2) * w, vals, w, label=seg)
        ax.set_ylabel(label)
        ax.set_ylim(0, 1.05)
        ax.set_xticks(x)
        ax.set_xticklabels(scenarios if k == 1 else [], rotation=20, ha="right")
        ax.grid(axis="y", alpha=0.3)
        if k == 0:
            ax.legend(fontsize=8, ncol=len(segs))
            ax.set_title("Where methods fail (simulated rig)")
    return _save(fig, path)


def qc_histogram_png(scores: Sequence[float], threshold: float) -> bytes:
    """Histogram of QC scores with the flag threshold, as PNG bytes (for the HTML report)."""
    fig = Figure(figsize=(5.5, 2.6))
    ax = fig.add_subplot(1, 1, 1)
    vals = np.array([s for s in scores if s is not None and math.isfinite(s)], dtype=float)
    if vals.size:
        ax.hist(vals, bins=np.linspace(0.0, 1.0, 41), color="#4c72b0")
    ax.axvline(threshold, color="#c44e52", linestyle="--", label=f"threshold {threshold:g}")
    ax.set_xlim(0, 1)
    ax.set_xlabel("QC stability score")
    ax.set_ylabel("frames")
    ax.yaxis.set_major_locator(MaxNLocator(integer=True))  # frames are counted, not measured
    # above the plot: flagged frames pile up at the left, good ones at the right, under either corner
    ax.legend(fontsize=8, loc="lower right", bbox_to_anchor=(1.0, 1.0), frameon=False)
    return _png(fig)


def write_evaluation_charts(
    out: str | Path,
    rows: Sequence[Table2Row],
    speed: Sequence[Mapping[str, Any]],
    *,
    has_truth: bool,
    rho: float = 0.9,
    mtc_mode: str | None = None,
    multi: str | None = None,
) -> dict[str, Path]:
    """The evaluation's charts into ``out``: table2.png, mtc.png, speed_accuracy.png."""
    out = Path(out)
    written: dict[str, Path] = {}
    if has_truth and any(r.cells for r in rows):
        written["table2.png"] = table2_chart(rows, out / "table2.png", rho=rho)
    if any(r.mtc for r in rows):
        written["mtc.png"] = mtc_chart(rows, out / "mtc.png", mode=mtc_mode, segmenter=multi)
    if has_truth and any(math.isfinite(p.get("dice_mean", math.nan)) for p in speed):
        written["speed_accuracy.png"] = speed_accuracy_chart(speed, out / "speed_accuracy.png")
    return written
