"""Calibration results as pictures (matplotlib, Agg): a master dark's level map and hot pixels, the
white reference's uniformity per band, the mosaic phase check's cost of every origin shift.

Each function returns PNG bytes and a one-line text alternative with the figures that matter.

- **Dark level map**: the master dark averaged over each mosaic cell (the fixed-pattern offset
  the dark subtraction removes). **Hot pixels**: dark pixels above the median by more than
  ``HOT_SIGMA`` robust standard deviations (1.4826 × the median absolute deviation) and at least
  ``HOT_MIN_DN``; EMVA 1288 (release 4.0, §8) likewise finds defect pixels as outliers of the dark
  image's distribution rather than by a fixed level.
- **White uniformity**: each band of the dark-subtracted white panel (super-pixel grid) divided by
  its brightest 1/8 × 1/8 block, on one colour scale; the title gives the dimmest block's ratio,
  the figure ``check_white`` (m2s2hil/rig/calibrate.py) holds against its 50 % limit.
- **Phase cost map**: ``cost[sy][sx]``, the relative disagreement of the layout's duplicated band
  positions when the layout is shifted by (sy, sx) (m2s2hil/processing/stability.py); the
  nominal origin is (0, 0) and should be the minimum.
"""

from __future__ import annotations

import io
from collections.abc import Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

HOT_SIGMA = 6.0
HOT_MIN_DN = 4.0
MIN_UNIFORMITY = 0.5  # as m2s2hil.rig.calibrate.MIN_UNIFORMITY (not imported: analysis sits below rig)


def _png(fig: Figure) -> bytes:
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=fig.dpi)
    return buf.getvalue()


def hot_pixels(dark: np.ndarray) -> tuple[np.ndarray, float]:
    """(mask of hot pixels, the threshold in DN) of a master dark."""
    d = np.asarray(dark, np.float64)
    med = float(np.median(d))
    sigma = 1.4826 * float(np.median(np.abs(d - med)))
    thr = med + max(HOT_SIGMA * sigma, HOT_MIN_DN)
    return d > thr, thr


def dark_maps_png(dark: np.ndarray, period: int, *, title: str) -> tuple[bytes, str]:
    """The dark's level map (per mosaic cell) and its hot pixels, side by side."""
    d = np.asarray(dark, np.float64)
    h, w = d.shape
    cells = d[: h // period * period, : w // period * period].reshape(h // period, period, w // period,
                                                                     period).mean(axis=(1, 3))
    hot, thr = hot_pixels(d)
    ys, xs = np.nonzero(hot)
    # fixed margins, not matplotlib's constrained layout: it costs more than the drawing here
    fig = Figure(figsize=(9.6, 4.4), dpi=100)
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.12, top=0.86, wspace=0.32)
    a1, a2 = fig.subplots(1, 2)
    lo, hi = np.percentile(cells, [0.5, 99.5])
    im = a1.imshow(cells, cmap="magma", vmin=lo, vmax=max(hi, lo + 1e-6), extent=(0, w, h, 0))
    fig.colorbar(im, ax=a1, label="mean dark level per cell (DN)", shrink=0.85)
    a1.set_title(f"dark level · median {np.median(d):.1f} DN", fontsize=10)
    a2.imshow(np.zeros_like(cells), cmap="gray", vmin=0, vmax=1, extent=(0, w, h, 0))
    a2.scatter(xs, ys, s=10 if len(xs) < 2000 else 2, c="#ff4d4f", marker="s", linewidths=0)
    a2.set_xlim(0, w)
    a2.set_ylim(h, 0)
    a2.set_title(f"hot pixels (> {thr:.1f} DN): {len(xs)} ({100 * len(xs) / d.size:.3f} %)", fontsize=10)
    for a in (a1, a2):
        a.set_xlabel("x (pixels)")
        a.set_ylabel("y (pixels)")
    fig.suptitle(title, fontsize=11)
    alt = (f"{title}: dark level median {np.median(d):.1f} DN (cells {lo:.1f}–{hi:.1f} DN); "
           f"{len(xs)} hot pixels above {thr:.1f} DN")
    return _png(fig), alt


def band_uniformity(cube: np.ndarray) -> list[float]:
    """Per band, the dimmest 1/8 × 1/8 block mean over the brightest (``check_white``'s figure)."""
    nb, h, w = cube.shape
    bh, bw = max(1, h // 8), max(1, w // 8)
    blocks = cube[:, : bh * 8, : bw * 8].reshape(nb, 8, bh, 8, bw).mean(axis=(2, 4))
    hi = blocks.max(axis=(1, 2))
    return [float(b.min() / m) if m > 0 else 0.0 for b, m in zip(blocks, hi, strict=True)]


def white_uniformity_png(cube: np.ndarray, bands_nm: Sequence[float], *, title: str) -> tuple[bytes, str]:
    """Each band of the white reference relative to its brightest block, on one colour scale."""
    nb, h, w = cube.shape
    uni = band_uniformity(cube)
    cols = 5
    rows = -(-nb // cols)
    fig = Figure(figsize=(10.5, 2.3 * rows + 0.6), dpi=100)
    fig.subplots_adjust(left=0.01, right=0.88, bottom=0.02, top=0.86, wspace=0.06, hspace=0.22)
    axes = np.atleast_1d(fig.subplots(rows, cols)).ravel()
    bh, bw = max(1, h // 8), max(1, w // 8)
    im = None
    for b, ax in enumerate(axes):
        ax.set_xticks([])
        ax.set_yticks([])
        if b >= nb:
            ax.set_visible(False)
            continue
        blocks = cube[b, : bh * 8, : bw * 8].reshape(8, bh, 8, bw).mean(axis=(1, 3))
        top = float(blocks.max()) or 1.0
        im = ax.imshow(cube[b] / top, cmap="viridis", vmin=MIN_UNIFORMITY, vmax=1.05)
        bad = uni[b] < MIN_UNIFORMITY
        ax.set_title(f"{bands_nm[b]:g} nm · {100 * uni[b]:.0f} %", fontsize=9,
                     color="#b52b27" if bad else "black")
    if im is not None:
        fig.colorbar(im, cax=fig.add_axes((0.9, 0.08, 0.015, 0.74)), label="relative to the brightest block")
    fig.suptitle(f"{title} · dimmest block / brightest per band (limit {100 * MIN_UNIFORMITY:.0f} %)",
                 fontsize=10)
    worst = int(np.argmin(uni))
    alt = (f"{title}: uniformity per band from {100 * min(uni):.0f} % ({bands_nm[worst]:g} nm) to "
           f"{100 * max(uni):.0f} %")
    return _png(fig), alt


def phase_cost_png(cost: Sequence[Sequence[float]], offset: Sequence[int], *,
                   conclusive: bool) -> tuple[bytes, str]:
    """The cost of every origin shift as a heat map, values printed, the origin and best marked."""
    c = 100 * np.asarray(cost, np.float64)
    n = c.shape[0]
    fig = Figure(figsize=(4.6, 4.2), dpi=100)
    fig.subplots_adjust(left=0.14, right=0.97, bottom=0.12, top=0.92)
    ax = fig.subplots()
    im = ax.imshow(c, cmap="viridis_r", vmin=0)
    fig.colorbar(im, ax=ax, label="duplicates' disagreement (%)", shrink=0.85)
    best = np.unravel_index(int(np.argmin(c)), c.shape)
    for sy in range(n):
        for sx in range(n):
            ax.text(sx, sy, f"{c[sy, sx]:.1f}", ha="center", va="center", fontsize=8,
                    color="white" if c[sy, sx] > 0.5 * c.max() else "black")
    ax.add_patch(_square(0, 0, "#ffffff", "-"))
    ax.add_patch(_square(int(best[1]), int(best[0]), "#ff4d4f", "--"))
    ax.set_xticks(range(n))
    ax.set_yticks(range(n))
    ax.set_xlabel("layout shift x (pixels)")
    ax.set_ylabel("layout shift y (pixels)")
    verdict = ("matches the layout" if conclusive and tuple(offset) == (0, 0) else
               f"offset ({offset[0]}, {offset[1]})" if conclusive else "inconclusive (scene too uniform)")
    ax.set_title(f"mosaic phase: {verdict}", fontsize=10)
    alt = (f"mosaic phase cost map, {n}×{n} shifts: cost at origin {c[0, 0]:.2f} %, best {c[best]:.2f} % "
           f"at shift ({best[0]}, {best[1]}); {verdict}")
    return _png(fig), alt


def _square(x: int, y: int, colour: str, style: str):
    from matplotlib.patches import Rectangle

    return Rectangle((x - 0.5, y - 0.5), 1, 1, fill=False, edgecolor=colour, linewidth=2.2, linestyle=style)
