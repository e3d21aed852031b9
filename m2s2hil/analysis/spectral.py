"""The default segmenter: Otsu foreground + Gaussian mixture on unit-length spectra.

Steps for a cube ``(bands, H, W)``:

1. Band energy e = ‖x‖₂ per pixel (L2 norm over bands). Foreground = pixels whose
   log(e + 10⁻³·max e) lies above its Otsu threshold (``skimage.filters.threshold_otsu``).
   Otsu runs on the log because shading is multiplicative: in the linear domain a
   satellite half in shadow forms its own histogram mode and Otsu cuts between the lit
   and the shadowed half instead of between object and background. A cube with
   constant energy has no foreground and comes back all background.
2. Each foreground spectrum is divided by its norm (unit length), so the model sees
   spectral *shape* (spectral angle), not brightness or shading.
3. ``sklearn.mixture.GaussianMixture`` with 1..``max_materials`` components (12 by
   default, above the catalog's 11 materials) is fitted on at most ``sample_size``
   foreground pixels drawn with ``np.random.default_rng(seed)``; the number with the
   lowest BIC on that sample wins. The sweep stops early once BIC has not improved for
   ``bic_patience`` consecutive counts (BIC curves are U-shaped; this saves most fits).
   Every fit uses ``random_state=seed``. A single-band cube has no spectral shape: its
   foreground is returned as one material without fitting.
4. Clean-up of the winning model (BIC over-splits non-Gaussian clusters, e.g. noise
   that grows as shading darkens, and spends components on a few outlier pixels):
   components whose unit mean spectra lie within ``merge_angle_deg`` (1°) of each other
   are merged (transitively), and merged groups holding less than
   ``min_material_fraction`` (0.2 %) of the model's weight are dropped. Each foreground
   pixel goes to the surviving group with the largest summed posterior probability.
   Groups are numbered 1..n by decreasing pixel count (ties by first component index),
   so ids are reproducible.
5. Optional (``smooth=True``): superpixels (``skimage.segmentation.slic``, SLICO, on the
   unit spectra, foreground only) and a majority vote of the cluster ids inside each.

BLAS threads: the whole analysis runs inside ``threadpoolctl.threadpool_limits(blas_threads)``
(1 by default). The GMM's linear algebra is on 10×10 matrices, where multi-threaded BLAS
is pure overhead; on a busy 2-core machine it made the BIC sweep ten times slower
(1.65 s vs 0.17 s for six fits on 20k pixels). ``None`` leaves the library default.

Known limit: unit-length spectra discard albedo, so achromatic materials that differ
only in brightness (e.g. Pro Silver vs Dark Grey, if both are spectrally flat) fall into
one cluster.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from skimage.filters import threshold_otsu
from skimage.segmentation import slic
from sklearn.exceptions import ConvergenceWarning
from sklearn.mixture import GaussianMixture
from threadpoolctl import threadpool_limits

from m2s2hil.analysis.arrays import as_cube
from m2s2hil.analysis.errors import AnalysisInputError

CovarianceType = Literal["full", "tied", "diag", "spherical"]


@dataclass(frozen=True)
class SpectralSegmentation:
    """Labels and the diagnostics of one ``SpectralSegmenter.analyse`` call."""

    labels: np.ndarray  # int32 (H, W), 0 = background
    n_materials: int
    threshold: float  # foreground threshold as band energy (NaN if energy was constant)
    bic: dict[int, float] = field(default_factory=dict)  # components -> BIC on the sample
    n_foreground: int = 0


def foreground_mask(cube: np.ndarray) -> tuple[np.ndarray, float]:
    """Otsu foreground on the log band energy of a ``(bands, H, W)`` cube.

    Returns the mask and the threshold expressed as band energy (NaN for a constant cube).
    """
    energy = np.sqrt(np.einsum("bhw,bhw->hw", cube, cube))
    top = float(energy.max())
    if top == float(energy.min()):
        return np.zeros(energy.shape, dtype=bool), float("nan")
    eps = 1e-3 * top
    log_e = np.log(energy + eps)
    t = float(threshold_otsu(log_e))
    return log_e > t, float(np.exp(t) - eps)


def majority_in_superpixels(labels: np.ndarray, superpixels: np.ndarray) -> np.ndarray:
    """Replace each label by the most frequent label of its superpixel (0 in ``superpixels`` = untouched)."""
    out = labels.copy()
    sp = superpixels.ravel()
    lab = labels.ravel()
    sel = sp > 0
    if not sel.any():
        return out
    n_lab = int(lab.max()) + 1
    counts = np.bincount(sp[sel] * n_lab + lab[sel], minlength=(int(sp.max()) + 1) * n_lab)
    winner = counts.reshape(-1, n_lab).argmax(axis=1)
    flat = out.ravel()
    flat[sel] = winner[sp[sel]]
    return flat.reshape(labels.shape)


class SpectralSegmenter:
    """Classical multispectral material segmenter (see module docstring)."""

    name = "spectral"

    def __init__(
        self,
        *,
        max_materials: int = 12,
        min_materials: int = 1,
        sample_size: int = 20_000,
        seed: int = 0,
        covariance_type: CovarianceType = "full",
        reg_covar: float = 1e-5,
        max_iter: int = 100,
        bic_patience: int = 2,
        merge_angle_deg: float = 1.0,
        min_material_fraction: float = 0.002,
        smooth: bool = False,
        n_superpixels: int = 2000,
        blas_threads: int | None = 1,
    ) -> None:
        if not 1 <= min_materials <= max_materials:
            raise AnalysisInputError(
                "max_materials",
                f"need 1 ≤ min_materials ≤ max_materials, got {min_materials}, {max_materials}",
            )
        if sample_size < 2:
            raise AnalysisInputError("sample_size", f"must be ≥ 2, got {sample_size}")
        if covariance_type not in ("full", "tied", "diag", "spherical"):
            raise AnalysisInputError("covariance_type", f"unknown covariance type {covariance_type!r}")
        if bic_patience < 1:
            raise AnalysisInputError("bic_patience", f"must be ≥ 1, got {bic_patience}")
        if merge_angle_deg < 0:
            raise AnalysisInputError("merge_angle_deg", f"must be ≥ 0, got {merge_angle_deg}")
        if not 0 <= min_material_fraction < 1:
            problem = f"must lie in [0, 1), got {min_material_fraction}"
            raise AnalysisInputError("min_material_fraction", problem)
        self.merge_angle_deg = float(merge_angle_deg)
        self.min_material_fraction = float(min_material_fraction)
        self.max_materials = int(max_materials)
        self.min_materials = int(min_materials)
        self.sample_size = int(sample_size)
        self.seed = int(seed)
        self.covariance_type: CovarianceType = covariance_type
        self.reg_covar = float(reg_covar)
        self.max_iter = int(max_iter)
        self.bic_patience = int(bic_patience)
        self.smooth = bool(smooth)
        self.n_superpixels = int(n_superpixels)
        if blas_threads is not None and blas_threads < 1:
            raise AnalysisInputError("blas_threads", f"must be ≥ 1 or None, got {blas_threads}")
        self.blas_threads = blas_threads

    def segment(self, cube: np.ndarray) -> np.ndarray:
        return self.analyse(cube).labels

    def _fit(self, sample: np.ndarray, n: int) -> GaussianMixture:
        gm = GaussianMixture(
            n_components=n,
            covariance_type=self.covariance_type,
            reg_covar=self.reg_covar,
            max_iter=self.max_iter,
            random_state=self.seed,
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)  # a non-converged fit still has a BIC
            return gm.fit(sample)

    def _groups(self, gm: GaussianMixture) -> np.ndarray:
        """0/1 matrix (components × surviving groups) after angle merging and the weight floor."""
        n = gm.n_components
        means = gm.means_ / np.maximum(np.linalg.norm(gm.means_, axis=1, keepdims=True), 1e-12)
        angle = np.degrees(np.arccos(np.clip(means @ means.T, -1.0, 1.0)))
        parent = list(range(n))

        def root(i: int) -> int:
            while parent[i] != i:
                parent[i] = parent[parent[i]]
                i = parent[i]
            return i

        for i in range(n):
            for j in range(i + 1, n):
                if angle[i, j] < self.merge_angle_deg:
                    parent[root(j)] = root(i)
        roots = sorted({root(i) for i in range(n)})
        member = np.zeros((n, len(roots)))
        for i in range(n):
            member[i, roots.index(root(i))] = 1.0
        weight = gm.weights_ @ member
        keep = weight >= self.min_material_fraction
        if not keep.any():
            keep[int(weight.argmax())] = True
        return member[:, keep]

    def analyse(self, cube: object) -> SpectralSegmentation:
        """Segment ``cube`` and return the labels with the fit's diagnostics."""
        arr = as_cube(cube)
        if self.blas_threads is None:
            return self._analyse(arr)
        with threadpool_limits(limits=self.blas_threads):
            return self._analyse(arr)

    def _analyse(self, arr: np.ndarray) -> SpectralSegmentation:
        h, w = arr.shape[1:]
        fg, threshold = foreground_mask(arr)
        labels = np.zeros((h, w), dtype=np.int32)
        n_fg = int(fg.sum())
        if n_fg == 0:
            return SpectralSegmentation(labels, 0, threshold, {}, 0)
        if arr.shape[0] == 1:  # one band has no spectral shape: the foreground is one material
            labels[fg] = 1
            return SpectralSegmentation(labels, 1, threshold, {}, n_fg)
        spectra = arr[:, fg].T  # (n_fg, bands)
        spectra = spectra / np.linalg.norm(spectra, axis=1, keepdims=True)
        rng = np.random.default_rng(self.seed)
        sample = spectra
        if n_fg > self.sample_size:
            sample = spectra[rng.choice(n_fg, self.sample_size, replace=False)]
        upper = min(self.max_materials, max(1, sample.shape[0] - 1))
        bic: dict[int, float] = {}
        best: GaussianMixture | None = None
        best_n, stale = 0, 0
        for n in range(min(self.min_materials, upper), upper + 1):
            gm = self._fit(sample, n)
            bic[n] = float(gm.bic(sample))
            if best is None or bic[n] < bic[best_n]:
                best, best_n, stale = gm, n, 0
            else:
                stale += 1
                if stale >= self.bic_patience:
                    break
        assert best is not None
        groups = self._groups(best)
        resp = best.predict_proba(spectra) @ groups  # (n_fg, n_groups) summed posteriors
        comp = resp.argmax(axis=1)
        n_groups = groups.shape[1]
        sizes = np.bincount(comp, minlength=n_groups)
        order = np.argsort(-sizes, kind="stable")
        rank = np.empty(n_groups, dtype=np.int32)
        rank[order] = np.arange(1, n_groups + 1, dtype=np.int32)
        labels[fg] = rank[comp]
        if self.smooth:
            unit = np.zeros_like(arr)
            unit[:, fg] = spectra.T
            sp = slic(unit, n_segments=self.n_superpixels, slic_zero=True, mask=fg, channel_axis=0,
                      start_label=1)
            labels = majority_in_superpixels(labels, sp).astype(np.int32)
        n_used = int(np.count_nonzero(np.bincount(labels.ravel())[1:]))
        return SpectralSegmentation(labels, n_used, threshold, bic, n_fg)
