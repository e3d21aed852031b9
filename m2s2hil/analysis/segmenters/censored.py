"""Clipped pixels as censored data: which a fitted material explains, and how the rest are grouped.

A band at its clipping plateau records only a lower bound: the pixel's value there is *at least*
the plateau. The robust segmenter keeps such pixels out of its fit and labels them afterwards by
their unclipped bands (``spectral.relabel_saturated``). That fails when whole materials are
clipped: at 50 ms under strong light every pixel of Voyager B2's bright materials is clipped in
bands 1–7 (docs/evaluation.md, "Where methods fail"), the fit sees only the dim material and the
rim blends, and every clipped pixel went to that one material (K = 1, Dice 0.34).

Here a saturated pixel x (clipped bands C, observed bands O) is *explained* by a material of mean
spectrum m when both hold:

- on O the shapes agree: the angle between x_O and m_O is at most ``tau_deg``;
- on C the material reaches the clip: with the scale s = x_O·m_O / m_O·m_O that fits O, every
  clipped band's prediction s·m_b is at least (1 − ``shortfall``) × the band's lower bound: its
  plateau, or, where the processor's per-band mask says a band clipped below it (one of its mosaic
  positions clipped, the cell's mean bent low), the recorded value itself. A material whose shape
  would put a clipped band below its bound cannot have produced the pixel (this is the censored
  likelihood's hinge: a lower bound the prediction does not reach).

The unexplained pixels are grouped by a mixture of their own, on their spectra as recorded (a
clipped value is the same lower bound for every bright pixel of a material, so a material's
pixels with one clip pattern sit together). A material clipped in a different number of bands at
different brightness forms one group per pattern; groups whose means agree on the bands both
observe are the same material and merge (``merge_censored``).
"""

from __future__ import annotations

import numpy as np

MIN_OBSERVED_SHARE = 0.3  # a group's band counts as observed where this share of its pixels is unclipped
MIN_COMMON_BANDS = 3


def plateau_levels(cube: np.ndarray, clipped: np.ndarray) -> np.ndarray:
    """(bands,) the lowest value on each band's clipping plateau (inf where the band never clips)."""
    levels = np.full(cube.shape[0], np.inf)
    for b in range(cube.shape[0]):
        if clipped[b].any():
            levels[b] = float(cube[b][clipped[b]].min())
    return levels


def lower_bounds(x: np.ndarray, observed: np.ndarray, levels: np.ndarray, plateau: np.ndarray | None = None
                 ) -> np.ndarray:
    """(m, bands): each clipped band's lower bound, the band's plateau level where the pixel is on
    the plateau (``plateau`` (m, bands); None: every clipped band is), else its recorded value; inf
    where observed (no bound to reach)."""
    on = ~observed if plateau is None else plateau & ~observed
    bounds = np.where(on, levels[None, :], x)
    return np.where(observed, np.inf, bounds)


def explained(x: np.ndarray, observed: np.ndarray, means: np.ndarray, bounds: np.ndarray, *,
              tau_deg: float, shortfall: float = 0.15) -> np.ndarray:
    """(m,) bool: some row of ``means`` (n, bands) explains each pixel of ``x`` (m, bands) whose
    unclipped bands are ``observed`` (m, bands), its clipped ones bounded below by ``bounds``
    (``lower_bounds``) — see the module docstring."""
    xo = x * observed
    num = xo @ means.T  # (m, n)
    mo2 = observed.astype(np.float64) @ (means**2).T
    cos = num / np.maximum(np.sqrt((xo**2).sum(axis=1, keepdims=True) * mo2), 1e-12)
    shape_ok = cos >= np.cos(np.radians(tau_deg))
    scale = num / np.maximum(mo2, 1e-12)
    reach = np.ones_like(scale)
    for b in range(x.shape[1]):
        c = ~observed[:, b] & np.isfinite(bounds[:, b]) & (bounds[:, b] > 0)
        if c.any():
            reach[c] = np.minimum(reach[c], scale[c] * means[None, :, b] / bounds[c, b][:, None])
    return (shape_ok & (reach >= 1.0 - shortfall)).any(axis=1)


def observed_means(x: np.ndarray, observed: np.ndarray, comp: np.ndarray, n_groups: int) -> np.ndarray:
    """(n_groups, bands): each group's mean of each band over its pixels unclipped there; NaN where
    fewer than ``MIN_OBSERVED_SHARE`` of them are (the band is censored for that group)."""
    out = np.full((n_groups, x.shape[1]), np.nan)
    for g in range(n_groups):
        sel = comp == g
        if not sel.any():
            continue
        ok = observed[sel]
        mean = (x[sel] * ok).sum(axis=0) / np.maximum(ok.sum(axis=0), 1)
        out[g] = np.where(ok.mean(axis=0) >= MIN_OBSERVED_SHARE, mean, np.nan)
    return out


def merge_censored(x: np.ndarray, observed: np.ndarray, comp: np.ndarray, n_groups: int, angle_deg: float
                   ) -> np.ndarray:
    """``comp`` (one group index per pixel of ``x``) with groups merged (transitively) whose
    ``observed_means`` lie within ``angle_deg`` on the ≥ ``MIN_COMMON_BANDS`` bands both observe;
    indices renumbered 0..k−1 in order of their lowest original index."""
    means = observed_means(x, observed, comp, n_groups)
    parent = list(range(n_groups))

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    cos_min = np.cos(np.radians(angle_deg))
    for i in range(n_groups):
        for j in range(i + 1, n_groups):
            both = np.isfinite(means[i]) & np.isfinite(means[j])
            if int(both.sum()) < MIN_COMMON_BANDS:
                continue
            a, b = means[i][both], means[j][both]
            if a @ b >= cos_min * np.linalg.norm(a) * np.linalg.norm(b):
                parent[root(j)] = root(i)
    roots = sorted({root(i) for i in range(n_groups)})
    lut = np.array([roots.index(root(i)) for i in range(n_groups)], dtype=np.int64)
    return lut[comp]
