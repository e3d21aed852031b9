"""Automatic exposure: the longest exposure whose 99.9th percentile stays below 90 % of full scale.

The sensor's response is linear in exposure until it clips, so the 99.9th
percentile ``p`` of a raw frame follows ``p(t) = b + s·t`` (``b``: black level plus
nothing that scales). The search measures a frame, fits that line through the
unclipped measurements it has (the black level stands in for the second point until
there are two), jumps to the exposure the line predicts for an aim a little under
the limit, and accepts the first frame that lands in ``[accept_low, limit)`` of full
scale. A clipped frame carries no slope information, so it only shrinks the
exposure. On a linear sensor this takes two or three frames.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ExposureResult:
    exposure_s: float
    level: float  # the percentile (DN) measured at exposure_s
    frames: int  # frames taken by the search
    history: tuple[tuple[float, float], ...]  # (exposure_s, percentile DN) per frame
    converged: bool  # a frame landed in the acceptance band
    limited: str | None = None  # "max_exposure" / "min_exposure" when a limit stopped it

    def to_dict(self) -> dict:
        return {
            "exposure_s": self.exposure_s,
            "level_dn": self.level,
            "frames": self.frames,
            "history": [list(h) for h in self.history],
            "converged": self.converged,
            "limited": self.limited,
        }


def percentile_dn(data: np.ndarray, q: float, full_scale: int) -> float:
    """The ``q``-th percentile of an integer frame from its histogram (fast for 10-bit data)."""
    flat = np.asarray(data).ravel()
    if flat.dtype.kind in "ui" and full_scale <= 65535:
        hist = np.bincount(np.minimum(flat, full_scale), minlength=full_scale + 1)
        cum = np.cumsum(hist)
        rank = q / 100.0 * (cum[-1] - 1)
        return float(np.searchsorted(cum, rank + 1))
    return float(np.percentile(flat, q))


def find_exposure(
    measure: Callable[[float], np.ndarray],
    *,
    full_scale: int,
    start_s: float = 0.01,
    min_s: float = 100e-6,
    max_s: float = 5.0,
    limit: float = 0.90,
    aim: float = 0.87,
    accept_low: float = 0.83,
    percentile: float = 99.9,
    black_level: float = 0.0,
    max_frames: int = 8,
) -> ExposureResult:
    """Search the exposure with ``measure(exposure_s) -> raw frame``.

    Returns the accepted exposure, or after ``max_frames`` the longest measured
    exposure that stayed below the limit (``converged=False``).
    """
    if not 0 < accept_low < aim < limit <= 1:
        raise ValueError("need 0 < accept_low < aim < limit <= 1")
    if not 0 < min_s <= max_s:
        raise ValueError("need 0 < min_s <= max_s")
    lim, aim_dn, low = limit * full_scale, aim * full_scale, accept_low * full_scale
    clip = 0.97 * full_scale
    history: list[tuple[float, float]] = []
    linear: list[tuple[float, float]] = []  # unclipped points
    t = float(np.clip(start_s, min_s, max_s))
    for _ in range(max_frames):
        p = percentile_dn(measure(t), percentile, full_scale)
        history.append((t, p))
        if low <= p < lim:
            return ExposureResult(t, p, len(history), tuple(history), True)
        if p >= lim and t <= min_s:
            return ExposureResult(t, p, len(history), tuple(history), False, "min_exposure")
        if p < lim and t >= max_s:
            return ExposureResult(t, p, len(history), tuple(history), False, "max_exposure")
        if p >= clip:
            nxt = t / 8.0
            # An unclipped point below gives a better guess than a blind division.
            below = [pt for pt in linear if pt[0] < t]
            if below:
                nxt = max(nxt, _predict(below, black_level, aim_dn) or nxt)
                nxt = min(nxt, t * 0.95)
        else:
            linear.append((t, p))
            nxt = _predict(linear, black_level, aim_dn) or t * (2.0 if p < aim_dn else 0.5)
            nxt = float(np.clip(nxt, t / 16.0, t * 16.0))
        nxt = float(np.clip(nxt, min_s, max_s))
        if nxt == t:  # pinned at a limit that the checks above did not catch
            break
        t = nxt
    safe = [h for h in history if h[1] < lim]
    best = max(safe, key=lambda h: h[0]) if safe else min(history, key=lambda h: h[0])
    return ExposureResult(best[0], best[1], len(history), tuple(history), False)


def _predict(points: list[tuple[float, float]], black: float, aim_dn: float) -> float | None:
    """Exposure at which the line through the measurements reaches ``aim_dn``."""
    pts = sorted(points)
    if len(pts) >= 2:
        (t0, p0), (t1, p1) = _spread_pair(pts)
        slope = (p1 - p0) / (t1 - t0) if t1 != t0 else 0.0
        if slope > 0:
            offset = p1 - slope * t1
            return (aim_dn - offset) / slope
    t, p = pts[-1]
    if p - black <= 0:
        return None
    return t * (aim_dn - black) / (p - black)


def _spread_pair(pts: list[tuple[float, float]]) -> tuple[tuple[float, float], tuple[float, float]]:
    # The two unclipped points furthest apart in exposure give the best-conditioned slope.
    return pts[0], pts[-1]
