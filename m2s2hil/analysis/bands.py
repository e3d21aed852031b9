"""PCA band selection (paper 2.4.1: "PCA to pick the three bands with the largest loadings
on the leading components", which gave bands 5, 9, 10).

Procedure:

1. Pool pixels (rows) × bands (columns) from one or more cubes, optionally only the
   pixels of a mask per cube (e.g. the foreground), and draw at most ``max_pixels`` of
   them uniformly without replacement (``np.random.default_rng(seed)``).
2. ``standardize=True`` (default) z-scores each band first (``StandardScaler``), i.e.
   PCA of the correlation matrix: the bands differ in sensitivity and illumination, and
   unstandardised PCA would mostly rank bands by their brightness. ``False`` runs PCA on
   the centred covariance.
3. ``sklearn.decomposition.PCA`` with ``n_components`` (default ``k``) components.
   The loadings are ``components_`` (unit eigenvectors; scaling a component by
   √eigenvalue would not change which band is largest within it).
4. Rule: for component i = 1..k, pick the band with the largest |loading| on
   component i among the bands not picked yet. Bands are reported in pick order.

Band numbers are 0-based indices in the API (``bands``) and 1-based in reports
(``bands_1based``, ``loadings_table``), as in the paper.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from sklearn.decomposition import PCA
from sklearn.preprocessing import StandardScaler

from m2s2hil.analysis.arrays import as_cube
from m2s2hil.analysis.errors import AnalysisInputError

# The bands of the paper's binary mTC (HIL setting), 1-based as the paper numbers them.
PAPER_BANDS: tuple[int, ...] = (5, 9, 10)


@dataclass(frozen=True)
class BandSelection:
    """Selected bands (0-based, pick order), the loadings and the variance explained."""

    bands: tuple[int, ...]
    loadings: np.ndarray  # (n_components, n_bands)
    explained_variance_ratio: np.ndarray
    standardize: bool
    n_pixels: int

    @property
    def bands_1based(self) -> tuple[int, ...]:
        return tuple(b + 1 for b in self.bands)

    def loadings_table(self, bands_nm: Sequence[float] | None = None) -> str:
        """Markdown table: one row per band (1-based, with wavelength if given), one column per PC.

        The picked band of each component is starred.
        """
        n_comp, n_bands = self.loadings.shape
        head = ["band"] + (["nm"] if bands_nm is not None else [])
        head += [f"PC{i + 1} ({self.explained_variance_ratio[i]:.1%})" for i in range(n_comp)]
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        picked = {b: i for i, b in enumerate(self.bands)}
        for b in range(n_bands):
            cells = [str(b + 1)] + ([f"{bands_nm[b]:g}"] if bands_nm is not None else [])
            for i in range(n_comp):
                star = "*" if picked.get(b) == i else ""
                cells.append(f"{self.loadings[i, b]:+.3f}{star}")
            lines.append("| " + " | ".join(cells) + " |")
        return "\n".join(lines)


def _pixels(cubes: Sequence[object], masks: Sequence[object] | None) -> np.ndarray:
    if masks is not None and len(masks) != len(cubes):
        raise AnalysisInputError("masks", f"{len(masks)} masks for {len(cubes)} cubes")
    rows = []
    n_bands = None
    for i, c in enumerate(cubes):
        cube = as_cube(c, f"cubes[{i}]")
        if n_bands is None:
            n_bands = cube.shape[0]
        elif cube.shape[0] != n_bands:
            raise AnalysisInputError(f"cubes[{i}]", f"has {cube.shape[0]} bands, cubes[0] has {n_bands}")
        flat = cube.reshape(cube.shape[0], -1)
        if masks is not None:
            m = np.asarray(masks[i], dtype=bool)
            if m.shape != cube.shape[1:]:
                problem = f"shape {m.shape} differs from the cube's {cube.shape[1:]}"
                raise AnalysisInputError(f"masks[{i}]", problem)
            flat = flat[:, m.ravel()]
        rows.append(flat.T)
    return np.concatenate(rows, axis=0)


def select_bands_pca(
    cubes: object | Sequence[object],
    k: int = 3,
    *,
    n_components: int | None = None,
    standardize: bool = True,
    masks: Sequence[object] | None = None,
    max_pixels: int = 200_000,
    seed: int = 0,
) -> BandSelection:
    """Pick ``k`` bands by PCA loadings over one cube ``(bands, H, W)`` or a sequence of cubes."""
    arr = cubes if not isinstance(cubes, np.ndarray) else [cubes]
    seq = list(arr)  # type: ignore[call-overload]
    if not seq:
        raise AnalysisInputError("cubes", "need at least one cube")
    x = _pixels(seq, masks).astype(np.float64)
    n_bands = x.shape[1]
    n_comp = k if n_components is None else int(n_components)
    if not 1 <= k <= n_bands:
        raise AnalysisInputError("k", f"must lie in 1..{n_bands} (the number of bands), got {k}")
    if not k <= n_comp <= n_bands:
        raise AnalysisInputError("n_components", f"must lie in {k}..{n_bands}, got {n_comp}")
    if x.shape[0] <= n_comp:
        raise AnalysisInputError("cubes", f"only {x.shape[0]} pixels for {n_comp} components")
    if x.shape[0] > max_pixels:
        pick = np.random.default_rng(seed).choice(x.shape[0], size=max_pixels, replace=False)
        x = x[pick]
    if standardize:
        x = StandardScaler().fit_transform(x)
    pca = PCA(n_components=n_comp, svd_solver="full").fit(x)
    loadings = pca.components_
    chosen: list[int] = []
    for i in range(k):
        order = np.argsort(-np.abs(loadings[i]), kind="stable")
        chosen.append(int(next(b for b in order if b not in chosen)))
    return BandSelection(tuple(chosen), loadings, pca.explained_variance_ratio_, standardize, int(x.shape[0]))
