"""The default segmenter: foreground + Gaussian mixture on shading-invariant spectra, fitted on the
interior of material regions.

Steps for a cube ``(bands, H, W)`` (defaults since issue 15; docs/evaluation.md, "How many
materials", has the comparison that chose them):

1. Band energy e = ‖x‖₂ per pixel. Foreground on log(e + 10⁻³·max e) (the log because shading is
   multiplicative: in the linear domain a half in shadow forms its own histogram mode).
   ``foreground="backdrop"`` (default): above the lower of the Otsu threshold and the backdrop's
   median + 6 robust SDs (``foreground_mask``) — with a bright object Otsu's cut can fall above a
   dark material and hand it to the background. ``"otsu"``: Otsu alone (the old rule).
   ``"noise"``: the same bound on the energy instead of its log (a dark backdrop is noise, whose
   log spreads widely): it finds faces in the spotlight's shadow (Dice +0.02 at 80°) but took in
   dim rim pixels at 5 % peak (−0.02), so it is not the default. A cube
   with constant energy has no foreground and comes back all background.
   Robust only (``dim_radius`` r, 2; sixth pass of issue 23; ``segmenters.foreground``): regions
   whose pixels are each within the backdrop's noise but whose (2r + 1)² window means (the
   foreground left out) stand above the backdrop's join the foreground, after an opening that
   drops rims of blends (Hubble B2's dark part at 5 % peak: 11 % → 77 % of it found).
1b. Reliability (``robust=True``, default since issue 23; ``segmenters.normalise``): every band
   stays in the features while ≥ 5 % of the foreground is unclipped in all of them (else the most
   clipped go, one at a time; dropping every band clipped on > 30 % lost six of Voyager B3's
   eight materials at 150 % peak); pixels clipped in a used band (a plateau at the band's
   maximum, or the processor's ``saturated`` mask given to
   ``analyse``) and near-black pixels (energy < ``snr_min`` (10) × the backdrop's noise floor) are
   *unreliable*: out of the fit and of model selection, then labelled — near-black pixels by the
   mixture's posterior like any other, saturated ones by the nearest material mean in spectral
   angle over the bands that did not clip (too few: the nearest reliable pixel's material);
   ``SpectralSegmentation.unreliable`` says which. Near-black is judged again on the denoised cube
   (step 1c; ``dark_after_denoise``): the SNR × the measured fall of the angular noise.
   Saturated pixels that no fitted material
   explains as censored data (shape on the bands that held, clip reached on those that did not;
   ``segmenters.censored``) and that have an interior of ≥ ``censored_min_share`` (5 %) of the
   foreground get a mixture of their own, within what a given count leaves (``censored=True``,
   default since the fifth pass of issue 23: a material clipped on every pixel otherwise joined
   the dim one, K = 1 at 50 ms in strong light); ``SpectralSegmentation.censored`` says which.
   The homogeneity angle of step 3 becomes at least 1.5 × the cube's median neighbour angle, so a
   dim cube keeps fit pixels (with a fixed 3° none passed at 4 % peak and the fit fell back to
   every pixel, which over-splits). ``white`` (per band) divides the cube by the white reference
   first. ``robust=False``: the issue-15 segmenter, unchanged.
1c. Denoising (robust only): where the median neighbour angle exceeds ``pool_target_deg`` (2°, about
   its value at the 60 %-peak reference, so the reference is untouched) the cube should average
   n = ⌈(angle / 2°)²⌉ pixels (the mean of n spectra has 1/√n of the noise). ``denoise="guided"``
   (default since the third pass of issue 23): an edge-preserving guided filter
   (``normalise.guided_denoise``: ``cv2.ximgproc``, a (2r + 1)² ≥ n window, guided by the unit
   spectra's first three principal components in units of their own noise, eps = 3², so a window
   whose spectra differ by more than the noise — a material edge — keeps them); then the
   per-pixel steps 3–5 on the filtered cube, the fit taking every ``fit_stride``-th (2) pixel in
   each direction, since filtered neighbours are correlated (0: one per window, which under-split:
   5 % peak 67 %, against 89 % with 2). ``denoise="slic"`` (the second pass): SLICO superpixels of
   n pixels, one fit sample per superpixel; superpixels mostly on the rim or clipped, still
   near-black, or spread inside more than ``SPREAD_FACTOR`` × the median (two materials) are out
   of the fit; fewer than 50 usable superpixels: no pooling. It over-split at 10 % peak, where
   n = 2 superpixels make a poor pool, and cost 1–3 s per 256² cube there.
2. Features: each spectrum divided by its norm (unit length: spectral angle, shape not
   brightness) or ``features="log-chromaticity"``; plus, with ``brightness_weight`` w > 0
   (default 0.1), w·log e as one more coordinate — an albedo cue: achromatic materials (silver,
   dark grey, white) have nearly the same spectral shape and differ mostly in brightness, while
   shading on a face changes log e far less than the albedo ratio between them.
3. Fit pixels (``fit_pixels="homogeneous"``): foreground pixels inside the eroded foreground whose
   four neighbours lie within ``homogeneity_deg`` (3°) of them; with ``noise_scaled`` the angle
   grows as √(median e / e) for pixels darker than the median (shot noise), so a dark material
   still has fit pixels. Rim pixels (object + backdrop) and material boundaries (two spectra; the
   super-pixel grid also samples the bands at slightly different places) stay out of the fit:
   fitted on every pixel (``"all"``, the old default), BIC spent components on those blends.
3b. Blends inside the object (``edge_step`` s > 0, robust only; ninth pass of issue 23; off by
   default, 0.2 in ``spectral-sweep``): pixels darker than a 4-neighbour by more than a factor
   e^s on the cube as captured (``darker_than_a_neighbour``) leave the fit too. A one-pixel gap
   between two of ISS's solar-panel cells shows the backdrop; the super-pixels beside it sample
   each band at another place of the 4 × 4 mosaic, so their spectra are garbled (a band at 0 %
   of the energy, the next at 45 %), and BIC fitted them as materials of their own (ISS B1, one
   material, split in three along the gaps). The guided filter, which follows spectral shape,
   does not smooth them away. ``blend_filter_step`` (off; 0.5 in ``spectral-sweep``): blends
   darker by e^step are also kept out of the guided filter's averages, with ``blend_filter_angle``
   a > 0 (degrees; 0 here, 12 in ``spectral-sweep``) only those more than a from the brighter
   neighbour's shape (``darker_than_a_neighbour``). Under the spotlight at 80° a face turning from the
   light is that much darker on 9–15 % of the foreground with the same shape; left out of the
   filter by brightness alone, those pixels stayed noisy and split Voyager B1 (one material) in
   two. The limit is fixed, not a multiple of the cube's noise angle: at 5 % peak, where the
   noise angle is largest, 3 × it let most blends back into the filter.
4. Count: ``sklearn.mixture.GaussianMixture`` with 1..``max_materials`` (12) components on at most
   ``sample_size`` fit pixels (``np.random.default_rng(seed)``); the lowest ``criterion`` wins:
   ``"bic"`` (default) or ``"icl"`` (BIC + twice the classification entropy). The sweep stops
   once it has not improved for ``bic_patience`` counts. ``"bayes"``: one
   ``BayesianGaussianMixture`` with a sparse Dirichlet weight prior (``weight_prior``), surplus
   components end with ~0 weight. ``n_materials`` fixes the count (``for_build``: from the
   catalog, named ``spectral-catalog-k``). A single-band cube: the foreground is one material.
   A fit whose component collapses (sklearn's "ill-defined empirical covariance") is refitted
   with 10×, 100×, 1000× ``reg_covar``; a count that still fails ends the sweep, and if the
   fewest components fail, ``AnalysisInputError("reg_covar", …)`` says what to change. Robust:
   a larger count within ``tie_break`` (1.0) component penalties of the best is a near tie, won
   by the largest whose label map has more materials and stays as coherent (``segmenters.ties``).
5. Clean-up: components whose unit mean spectra (brightness coordinate left out) lie within
   ``merge_angle_deg`` (1.5°) merge. Robust (``merge_linkage="average"``, sixth pass of issue 23):
   by average linkage, two groups joining while the mean angle between their components is under
   it; single linkage (``"single"``, the issue-15 rule and ``robust=False``'s) joined chains of
   components along a material's shading, and so materials 2° apart. Or, with ``merge_noise``
   k > 0 (robust only, single linkage; off by default: at the reference it merged real
   materials), within k × the angle two samples of one spectrum differ by at the components'
   brightness; groups under ``min_material_fraction``
   (0.2 %) of the weight are dropped; every foreground pixel goes to the group with the largest
   summed posterior. Robust only (since the fourth pass of issue 23): a group whose pixels keep
   fewer than ``min_core_fraction`` (0.06 %, ≈ 10 pixels of a 256² cube's object) of the
   foreground after a one-pixel erosion has no interior — blends along the rim, a material
   boundary or clipped pixels, one or two pixels wide — and is dropped, its pixels going to their
   next group (a real part that small is dropped too). Groups are numbered 1..n by decreasing
   pixel count (ties by first component index), so ids are reproducible.
6. Optional (``smooth=True``): superpixels (``skimage.segmentation.slic``, SLICO, on the
   features, foreground only) and a majority vote of the cluster ids inside each.

BLAS threads: the whole analysis runs inside ``threadpoolctl.threadpool_limits(blas_threads)``
(1 by default). The GMM's linear algebra is on 10×10 matrices, where multi-threaded BLAS
is pure overhead; on a busy 2-core machine it made the BIC sweep ten times slower
(1.65 s vs 0.17 s for six fits on 20k pixels). ``None`` leaves the library default.

Known limits (robustness: docs/evaluation.md, "Robustness to exposure, clipping and light"):
below ~10 % peak the 8–10-material builds still lose their smallest parts (denoising, dim
regions and the near-black test on the denoised cube recover most: K ±1 on 78 % of the whole
sweep's frames at 5 %, 93 % at 60 %; docs/evaluation.md, "The goal on the whole sweep"), above
~150 % clipping still splits some (at 200 % the censored fit takes a glossy material's highlights
for materials of their own), and under the spotlight faces in shadow are found only in part
(dim regions) and labelled from little signal (there even a classifier told the truth,
``metrics.bounds``, loses 0.06–0.11 Dice per pixel);
the brightness coordinate separates dark grey from silver, but silver and cold white (close in
both shape and brightness) can still merge; materials that cover only a few pixels have no
homogeneous interior and are found only if their spectra stand out. The defaults were chosen on
the simulator's frames (docs/evaluation.md), not on real captures.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal, TypeAlias, TypeVar

import numpy as np
from scipy import ndimage
from scipy.special import xlogy
from skimage.segmentation import slic
from threadpoolctl import threadpool_limits

from m2s2hil.analysis.arrays import as_cube
from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.segmenters.censored import explained, lower_bounds, merge_censored, plateau_levels
from m2s2hil.analysis.segmenters.foreground import ForegroundRule, dim_regions, foreground_mask
from m2s2hil.analysis.segmenters.normalise import (
    Reliability,
    guided_denoise,
    neighbour_angle_deg,
    normalise_cube,
    pool_size,
    reliability,
    superpixel_means,
)
from m2s2hil.analysis.segmenters.ties import COHERENCE_TOL, coherence, component_penalty, near_ties
from m2s2hil.catalog import load_catalog

if TYPE_CHECKING:  # scikit-learn loads with the first fit (2 s of CPU a process that never fits)
    from sklearn.mixture import BayesianGaussianMixture, GaussianMixture

CovarianceType = Literal["full", "tied", "diag", "spherical"]
Criterion = Literal["bic", "icl", "bayes"]
FitPixels = Literal["homogeneous", "all"]
Features = Literal["unit", "log-chromaticity"]
Denoise = Literal["guided", "slic"]
MergeLinkage = Literal["single", "average"]
M = TypeVar("M", "GaussianMixture", "BayesianGaussianMixture")
Mixture: TypeAlias = "GaussianMixture | BayesianGaussianMixture"


@dataclass(frozen=True)
class SpectralSegmentation:
    """Labels and the diagnostics of one ``SpectralSegmenter.analyse`` call."""

    labels: np.ndarray  # int32 (H, W), 0 = background
    n_materials: int
    threshold: float  # foreground threshold as band energy (NaN if energy was constant)
    bic: dict[int, float] = field(default_factory=dict)  # components -> BIC on the sample
    n_foreground: int = 0
    unreliable: np.ndarray | None = None  # bool (H, W): saturated or near-black, kept out of the fit
    bands: tuple[int, ...] = ()  # bands the features used (clipped bands left out); () = all
    fit: np.ndarray | None = None  # bool (H, W): the pixels the mixture was fitted on
    pooled: int = 1  # pixels the cube was averaged over before the fit (filter or superpixel; 1 = none)
    censored: np.ndarray | None = None  # bool (H, W): saturated pixels no material explained, fitted apart
    shared: bool = False  # labelled with a mixture given to ``analyse`` (a sweep's), not its own


@dataclass(frozen=True)
class _Prepared:
    """One cube made ready for the mixture (``SpectralSegmenter._prepare``)."""

    arr: np.ndarray  # the cube the features come from (white-normalised, used bands, denoised)
    fg: np.ndarray
    threshold: float
    rel: Reliability | None
    unit: np.ndarray
    feats: np.ndarray
    spectra: np.ndarray  # (n_fg, features): every foreground pixel's features
    fit: np.ndarray  # bool (H, W): the fit pixels
    sample: np.ndarray  # (n, features): the rows the mixture is fitted on
    per: int
    noise_deg: float
    raw_noise_deg: float
    averaged: int
    n_fg: int


MIN_FIT_PIXELS = 50
# Homogeneity angle ≥ this × the median neighbour angle: at 60 % peak that median is ≈ 1–2° and the
# fixed 3° rules; at 4 % peak it is ≈ 6° and a fixed 3° left no pixel (then the fit fell back to all).
NOISE_ANGLE_FACTOR = 1.5
SPREAD_FACTOR = 1.5
CENSORED_NOISE_FACTOR = 3.0  # a saturated pixel's allowed angle to its material, in noise angles


def features_of(cube: np.ndarray, features: Features = "unit") -> np.ndarray:
    """Per-pixel shading-invariant features ``(bands, H, W)``: unit-length spectra (spectral angle),
    or log-chromaticity log(x_b) − mean_b log(x_b) (a multiplicative shading factor cancels in both)."""
    if features == "log-chromaticity":
        top = float(cube.max()) if cube.size else 0.0
        logs = np.log(np.maximum(cube, 1e-3 * top if top > 0 else 1e-12))
        return (logs - logs.mean(axis=0, keepdims=True)).astype(np.float64)
    norm = np.linalg.norm(cube, axis=0, keepdims=True)
    return cube / np.maximum(norm, 1e-12)


def homogeneous_pixels(
    features: np.ndarray, fg: np.ndarray, max_angle_deg: float, scale: np.ndarray | None = None
) -> np.ndarray:
    """Foreground pixels away from the object's rim whose four neighbours all lie within
    ``max_angle_deg`` of them (angle between feature vectors): the interior of material regions.

    A spatial prior for the fit: pixels at the rim mix object and backdrop, pixels at a material
    boundary mix two spectra (and the super-pixel grid samples the bands at slightly different
    places), and the mixture would spend components on those blends. ``scale`` (per pixel, ≥ 1)
    widens the angle where the noise is larger.
    """
    inner = ndimage.binary_erosion(fg, iterations=1)
    unit = features / np.maximum(np.linalg.norm(features, axis=0, keepdims=True), 1e-12)
    cos_min = np.ones(fg.shape)
    for axis in (1, 2):
        for step in (1, -1):
            cos_min = np.minimum(cos_min, np.einsum("bhw,bhw->hw", unit, np.roll(unit, step, axis=axis)))
    if scale is None:
        return inner & (cos_min > np.cos(np.radians(max_angle_deg)))
    limit = np.radians(np.minimum(max_angle_deg * scale, 89.0))
    return inner & (np.arccos(np.clip(cos_min, -1.0, 1.0)) < limit)


def darker_than_a_neighbour(energy: np.ndarray, step: float, unit: np.ndarray | None = None,
                            min_angle_deg: float = 0.0) -> np.ndarray:
    """(H, W) bool: pixels whose energy is below a 4-neighbour's by more than a factor e^step; with
    ``unit`` (the unit spectra) and ``min_angle_deg`` > 0, only where the pixel's shape is also more
    than that angle from the brighter neighbour's.

    The dark side of a brightness edge is where a super-pixel cell holds part object, part
    something darker (a one-pixel gap between ISS's solar-panel cells, showing the backdrop): its
    bands are sampled at different places of the 4 × 4 mosaic cell, so each sees another share of
    the two and the spectrum's shape is garbled (a band 0 % and another 45 % of the energy at
    60 % peak). Such cells are blends, as the object's rim is; the rim is left out of the fit by
    eroding the foreground, and these by this test. Only the darker side: the brightest pixels of
    a part two or three pixels wide (Voyager's booms) are darker than none of their neighbours.
    The angle tells such a blend from shading (a surface turning from the light changes
    brightness, not shape)."""
    log_e = np.log(np.maximum(energy, 1e-12 * max(float(energy.max()), 1e-12)))
    shapes = unit if min_angle_deg > 0 else None
    cos_max = np.cos(np.radians(min_angle_deg))
    found = np.zeros(energy.shape, dtype=bool)
    whole, head, tail = slice(None), slice(1, None), slice(None, -1)
    for here, there in (((head, whole), (tail, whole)), ((tail, whole), (head, whole)),
                        ((whole, head), (whole, tail)), ((whole, tail), (whole, head))):
        step_down = log_e[there] - log_e[here] > step
        if shapes is not None:
            step_down &= np.einsum("bhw,bhw->hw", shapes[(whole, *here)], shapes[(whole, *there)]) < cos_max
        found[here] |= step_down
    return found


def relabel_saturated(labels: np.ndarray, cube: np.ndarray, clipped: np.ndarray, saturated: np.ndarray
                      ) -> np.ndarray:
    """Saturated foreground pixels get the material whose mean spectrum (over the reliable pixels)
    is nearest in spectral angle on the pixel's *unclipped* bands (a clipped value is only a lower
    bound); with fewer than two unclipped bands, the label of the nearest reliable pixel."""
    out = labels.copy()
    n = int(labels.max())
    good = (labels > 0) & ~saturated
    if n == 0 or not good.any():
        return out
    means = np.stack([cube[:, (labels == k) & good].mean(axis=1) if ((labels == k) & good).any()
                      else np.zeros(cube.shape[0]) for k in range(1, n + 1)])  # (n, bands)
    sel = saturated & (labels > 0)
    x = cube[:, sel].T  # (m, bands)
    ok = ~clipped[:, sel].T  # (m, bands) bands that held
    num = (x * ok) @ means.T
    den = np.sqrt(((x * ok) ** 2).sum(axis=1, keepdims=True) * (ok @ (means**2).T))
    best = (num / np.maximum(den, 1e-12)).argmax(axis=1) + 1
    few = ok.sum(axis=1) < 2
    if few.any():  # too little shape left: the nearest reliable pixel's material
        _, (iy, ix) = ndimage.distance_transform_edt(~good, return_indices=True)
        ys, xs = np.nonzero(sel)
        best[few] = labels[iy[ys[few], xs[few]], ix[ys[few], xs[few]]]
    out[sel] = best
    return out


def cored_groups(comp: np.ndarray, fg: np.ndarray, n_groups: int, min_core: float) -> np.ndarray:
    """(n_groups,) bool: the groups whose pixels (``comp``, one per foreground pixel) keep at least
    ``min_core`` pixels after a one-pixel erosion, i.e. have an interior. A cluster of blends —
    rim pixels, a material boundary, partly clipped cells next to clipped ones — is one or two
    pixels wide and has none. At least the group with the largest interior is kept."""
    cores = np.zeros(n_groups)
    plane = np.full(fg.shape, -1, dtype=np.int64)
    plane[fg] = comp
    for g in range(n_groups):
        cores[g] = int(ndimage.binary_erosion(plane == g).sum())
    keep = cores >= min_core
    if not keep.any():
        keep[int(cores.argmax())] = True
    return keep


def single_linkage_groups(angle: np.ndarray, limit: np.ndarray) -> np.ndarray:
    """(n,) group of each component: components closer than ``limit`` (per pair) join, transitively."""
    from scipy.sparse.csgraph import connected_components

    close = angle < limit
    _, group = connected_components(close, directed=False)
    return _first_seen(group)


def average_linkage_groups(angle: np.ndarray, limit_deg: float) -> np.ndarray:
    """(n,) group of each component: average linkage (UPGMA) on the angles, cut below ``limit_deg``.

    Two groups join only while the *mean* angle between their components is under the limit.
    With single linkage a chain of components a fraction of a degree apart joined materials 2°
    apart: under the spotlight the shading of Hubble's body and its dark part (2.2° apart) was
    fitted as nine components 0.1–0.7° apart, and they chained into one group (Dice 0.76; with
    average linkage 0.96)."""
    from scipy.cluster.hierarchy import fcluster, linkage
    from scipy.spatial.distance import squareform

    dist = angle.copy()
    np.fill_diagonal(dist, 0.0)
    tree = linkage(squareform(dist, checks=False), method="average")
    # strictly below the limit, as single linkage's test (fcluster joins at ≤ t)
    group = fcluster(tree, t=np.nextafter(limit_deg, 0.0), criterion="distance") - 1
    return _first_seen(np.asarray(group))


def _first_seen(group: np.ndarray) -> np.ndarray:
    """Group ids renumbered 0.. in order of their first component (reproducible column order)."""
    _, first, inverse = np.unique(group, return_index=True, return_inverse=True)
    order = np.argsort(np.argsort(first))
    return order[inverse]


REG_COVAR_RETRIES = 3  # each ×10: sklearn's own advice for a collapsed component


def _fitted(make: Callable[[float], M], sample: np.ndarray, reg_covar: float, what: str) -> M:
    """``make(reg_covar).fit(sample)``; a component collapsed onto too few distinct samples (a
    ``diag`` fit of a one-material build at 60 % peak did) is refitted with 10×, 100×, 1000× the
    regularisation before the fit is refused with a typed error that says what to change."""
    from sklearn.exceptions import ConvergenceWarning

    reg = reg_covar
    for _ in range(REG_COVAR_RETRIES + 1):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ConvergenceWarning)  # a non-converged fit still has a BIC
                return make(reg).fit(sample)
        except ValueError as exc:
            if "ill-defined empirical covariance" not in str(exc):
                raise
            reg *= 10.0
    problem = (f"the mixture of {what} could not be fitted: a component collapsed even with reg_covar "
               f"{reg / 10:g}; raise reg_covar, lower max_materials or use covariance_type='full'")
    raise AnalysisInputError("reg_covar", problem)


def ranked(labels: np.ndarray) -> np.ndarray:
    """``labels`` renumbered 1..n by decreasing pixel count (ties by the old id); 0 stays 0."""
    counts = np.bincount(labels.ravel())
    ids = np.flatnonzero(counts[1:]) + 1
    order = ids[np.argsort(-counts[ids], kind="stable")]
    lut = np.zeros(counts.size, dtype=np.int32)
    lut[order] = np.arange(1, order.size + 1, dtype=np.int32)
    return lut[labels]


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
        merge_angle_deg: float = 1.5,
        min_material_fraction: float = 0.002,
        smooth: bool = False,
        n_superpixels: int = 2000,
        blas_threads: int | None = 1,
        fit_pixels: FitPixels = "homogeneous",
        homogeneity_deg: float = 3.0,
        noise_scaled: bool = True,
        brightness_weight: float = 0.1,
        foreground: ForegroundRule = "backdrop",
        criterion: Criterion = "bic",
        features: Features = "unit",
        weight_prior: float = 1e-3,
        n_materials: int | None = None,
        robust: bool = True,
        snr_min: float = 10.0,
        white: object | None = None,
        pool_target_deg: float = 2.0,
        merge_noise: float = 0.0,
        denoise: Denoise = "guided",
        fit_stride: int = 2,
        min_core_fraction: float = 6e-4,
        censored: bool = True,
        censored_min_share: float = 0.05,
        dark_after_denoise: bool = True,
        dim_radius: int = 2,
        merge_linkage: MergeLinkage | None = None,
        tie_break: float | None = None,
        edge_step: float = 0.0,
        blend_filter_step: float = 0.0,
        blend_filter_angle: float = 0.0,
    ) -> None:
        for key, step in (("edge_step", edge_step), ("blend_filter_step", blend_filter_step),
                          ("blend_filter_angle", blend_filter_angle)):
            if not (isinstance(step, int | float) and step >= 0 and np.isfinite(step)):
                raise AnalysisInputError(key, f"must be a finite number ≥ 0 (0 = off), got {step!r}")
        self.edge_step = float(edge_step)
        self.blend_filter_step = float(blend_filter_step)
        self.blend_filter_angle = float(blend_filter_angle)
        if tie_break is not None and not tie_break >= 0:
            problem = f"must be ≥ 0 (0 = the sweep decides) or None, got {tie_break}"
            raise AnalysisInputError("tie_break", problem)
        self.tie_break = None if tie_break is None else float(tie_break)
        if merge_linkage not in (None, "single", "average"):
            problem = f"expected 'single' or 'average', got {merge_linkage!r}"
            raise AnalysisInputError("merge_linkage", problem)
        self.merge_linkage: MergeLinkage | None = merge_linkage
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
        if fit_pixels not in ("homogeneous", "all"):
            raise AnalysisInputError("fit_pixels", f"expected 'homogeneous' or 'all', got {fit_pixels!r}")
        if not 0 < homogeneity_deg < 90:
            raise AnalysisInputError("homogeneity_deg", f"must lie in (0, 90), got {homogeneity_deg}")
        if criterion not in ("bic", "icl", "bayes"):
            raise AnalysisInputError("criterion", f"expected 'bic', 'icl' or 'bayes', got {criterion!r}")
        if features not in ("unit", "log-chromaticity"):
            raise AnalysisInputError("features", f"expected 'unit' or 'log-chromaticity', got {features!r}")
        if not weight_prior > 0:
            raise AnalysisInputError("weight_prior", f"must be > 0, got {weight_prior}")
        if n_materials is not None and not 1 <= n_materials <= max_materials:
            problem = f"must lie in 1..max_materials ({max_materials}) or be None, got {n_materials}"
            raise AnalysisInputError("n_materials", problem)
        if brightness_weight < 0:
            raise AnalysisInputError("brightness_weight", f"must be ≥ 0, got {brightness_weight}")
        if foreground not in ("noise", "backdrop", "otsu"):
            problem = f"expected 'noise', 'backdrop' or 'otsu', got {foreground!r}"
            raise AnalysisInputError("foreground", problem)
        if not snr_min >= 0:
            raise AnalysisInputError("snr_min", f"must be ≥ 0, got {snr_min}")
        if not pool_target_deg >= 0:
            problem = f"must be ≥ 0 (0 = no pooling), got {pool_target_deg}"
            raise AnalysisInputError("pool_target_deg", problem)
        if not merge_noise >= 0:
            problem = f"must be ≥ 0 (0 = the fixed merge angle), got {merge_noise}"
            raise AnalysisInputError("merge_noise", problem)
        if denoise not in ("guided", "slic"):
            raise AnalysisInputError("denoise", f"expected 'guided' or 'slic', got {denoise!r}")
        self.denoise: Denoise = denoise
        if fit_stride < 0:
            raise AnalysisInputError("fit_stride", f"must be ≥ 0 (0 = the filter window), got {fit_stride}")
        self.fit_stride = int(fit_stride)
        if not 0 <= min_core_fraction < 1:
            problem = f"must lie in [0, 1) (0 = no interior test), got {min_core_fraction}"
            raise AnalysisInputError("min_core_fraction", problem)
        self.min_core_fraction = float(min_core_fraction)
        if not 0 <= censored_min_share < 1:
            raise AnalysisInputError("censored_min_share", f"must lie in [0, 1), got {censored_min_share}")
        self.censored = bool(censored)
        self.dark_after_denoise = bool(dark_after_denoise)
        if dim_radius < 0:
            raise AnalysisInputError("dim_radius", f"must be ≥ 0 (0 = no dim regions), got {dim_radius}")
        self.dim_radius = int(dim_radius)
        self.censored_min_share = float(censored_min_share)
        self.pool_target_deg = float(pool_target_deg)
        self.merge_noise = float(merge_noise)
        self.robust = bool(robust)
        self.snr_min = float(snr_min)
        self.white = None if white is None else np.asarray(white, dtype=np.float64)
        self.noise_scaled = bool(noise_scaled)
        self.brightness_weight = float(brightness_weight)
        self.foreground: ForegroundRule = foreground
        self.fit_pixels: FitPixels = fit_pixels
        self.homogeneity_deg = float(homogeneity_deg)
        self.criterion: Criterion = criterion
        self.features: Features = features
        self.weight_prior = float(weight_prior)
        self.n_materials = n_materials

    @classmethod
    def for_build(cls, satellite: str, build: str, **options: object) -> SpectralSegmenter:
        """The catalog mode: told how many materials the build has (``catalog.toml``), so nothing is
        selected. Named ``spectral-catalog-k``; it knows what an image of an unknown object would not,
        and is never what ``spectral`` does."""
        k = len(load_catalog().build(satellite, build).materials)
        upper = max(k, int(options.pop("max_materials", 12)))  # type: ignore[call-overload]
        seg = cls(n_materials=k, max_materials=upper, **options)  # type: ignore[arg-type]
        seg.name = "spectral-catalog-k"
        return seg

    def segment(self, cube: np.ndarray, *, saturated: np.ndarray | None = None) -> np.ndarray:
        return self.analyse(cube, saturated=saturated).labels

    def _fit(self, sample: np.ndarray, n: int) -> GaussianMixture:
        from sklearn.mixture import GaussianMixture

        return _fitted(lambda reg: GaussianMixture(
            n_components=n,
            covariance_type=self.covariance_type,
            reg_covar=reg,
            max_iter=self.max_iter,
            random_state=self.seed,
        ), sample, self.reg_covar, f"{n} components")

    def _fit_bayes(self, sample: np.ndarray, upper: int) -> BayesianGaussianMixture:
        """Variational mixture with a sparse Dirichlet weight prior: surplus components get ~0 weight."""
        from sklearn.mixture import BayesianGaussianMixture

        return _fitted(lambda reg: BayesianGaussianMixture(
            n_components=upper,
            covariance_type=self.covariance_type,
            weight_concentration_prior_type="dirichlet_distribution",
            weight_concentration_prior=self.weight_prior,
            reg_covar=reg,
            max_iter=max(self.max_iter, 200),
            random_state=self.seed,
        ), sample, self.reg_covar, f"{upper} components (variational)")

    def _score(self, gm: GaussianMixture, sample: np.ndarray) -> float:
        """BIC, or ICL = BIC + 2·(classification entropy), which also penalises overlapping components."""
        value = float(gm.bic(sample))
        if self.criterion == "icl":
            z = gm.predict_proba(sample).astype(np.float64)
            value -= 2.0 * float(np.sum(xlogy(z, z)))
        return value

    def _select(self, sample: np.ndarray, *, given: bool = True, most: int | None = None,
                fits: dict[int, GaussianMixture | BayesianGaussianMixture] | None = None,
                ) -> tuple[GaussianMixture | BayesianGaussianMixture, dict[int, float]]:
        """The mixture for ``sample``: the given count (``n_materials``, unless ``given`` is false),
        the variational fit, or the lowest ``criterion`` over 1..``max_materials`` components (or
        ``most``, if fewer; stopping after ``bic_patience`` counts without improvement); returns it
        with the criterion per count tried (and each count's mixture in ``fits``, when given)."""
        upper = min(self.max_materials, max(1, sample.shape[0] - 1), most or self.max_materials)
        bic: dict[int, float] = {}
        best: GaussianMixture | BayesianGaussianMixture | None = None
        if given and self.n_materials is not None:  # the count is given (e.g. the catalog's): no selection
            best = self._fit(sample, min(self.n_materials, upper))
        elif self.criterion == "bayes":
            best = self._fit_bayes(sample, upper)
        else:
            best_n, stale = 0, 0
            for n in range(min(self.min_materials, upper), upper + 1):
                try:
                    gm = self._fit(sample, n)
                except AnalysisInputError:
                    if best is None:  # not even the fewest components fit: say so
                        raise
                    break  # more components than the sample can hold apart: the count so far stands
                bic[n] = self._score(gm, sample)
                if fits is not None:
                    fits[n] = gm
                if best is None or bic[n] < bic[best_n]:
                    best, best_n, stale = gm, n, 0
                else:
                    stale += 1
                    if stale >= self.bic_patience:
                        break
        assert best is not None
        return best, bic

    def _linkage(self) -> MergeLinkage:
        """``merge_linkage``, or by default average linkage when robust (single: the issue-15 rule)."""
        if self.merge_linkage is not None:
            return self.merge_linkage
        return "average" if self.robust else "single"

    def _groups(self, gm: GaussianMixture | BayesianGaussianMixture, n_spectral: int,
                limit: np.ndarray | None = None) -> np.ndarray:
        """0/1 matrix (components × surviving groups) after angle merging and the weight floor;
        ``limit`` (components × components, degrees): the noise-aware merge angle (single
        linkage), else the fixed one with ``merge_linkage``."""
        n = gm.n_components
        spec = gm.means_[:, :n_spectral]  # angle between the spectral parts (not brightness)
        means = spec / np.maximum(np.linalg.norm(spec, axis=1, keepdims=True), 1e-12)
        angle = np.degrees(np.arccos(np.clip(means @ means.T, -1.0, 1.0)))
        if limit is None and self._linkage() == "average" and n > 1:
            group = average_linkage_groups(angle, self.merge_angle_deg)
        else:
            fixed = np.full((n, n), self.merge_angle_deg)
            group = single_linkage_groups(angle, fixed if limit is None else limit)
        member = np.zeros((n, int(group.max()) + 1))
        member[np.arange(n), group] = 1.0
        weight = gm.weights_ @ member
        keep = weight >= self.min_material_fraction
        if not keep.any():
            keep[int(weight.argmax())] = True
        return member[:, keep]

    def _pool(self, arr: np.ndarray, unit: np.ndarray, fg: np.ndarray, rel: Reliability, per: int
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Superpixels of about ``per`` pixels (SLICO on the unit spectra, foreground only: edges
        between materials bound them where they stand above the noise) and each pixel's spectrum
        replaced by its superpixel's mean; the fit's samples are one row per superpixel, so the
        samples BIC counts are independent (pooled pixels are not). Superpixels that are mostly
        rim or saturated, or whose mean is still near-black, are left out of the fit."""
        shown = np.zeros_like(unit)
        shown[:, fg] = unit[:, fg]
        n_fg = int(fg.sum())
        sp = slic(shown, n_segments=max(1, n_fg // per), slic_zero=True, mask=fg, channel_axis=0,
                  start_label=1, enforce_connectivity=True)
        means = superpixel_means(arr, sp)  # (n_sp + 1, bands)
        out = arr.copy()
        out[:, fg] = means[sp[fg]].T
        unit_p, energy_p, feats = self._features(out)
        ids = sp.ravel()
        n = int(sp.max()) + 1
        size = np.bincount(ids, minlength=n)
        clean = ndimage.binary_erosion(fg) & ~rel.saturated
        clean_n = np.bincount(ids, weights=clean.ravel().astype(np.float64), minlength=n)
        clean_share = clean_n / np.maximum(size, 1)
        noise_e = rel.noise_energy
        snr = np.linalg.norm(means, axis=1) * np.sqrt(np.maximum(size, 1)) / noise_e
        # spread inside a superpixel (RMS angle of its pixels to its mean): one that straddles two
        # materials spreads more than the noise; like the homogeneity test, it stays out of the fit
        cos = np.einsum("bn,bn->n", unit[:, fg], unit_p[:, fg])
        ang2 = np.zeros(n)
        np.add.at(ang2, sp[fg], np.arccos(np.clip(cos, -1.0, 1.0)) ** 2)
        spread = np.sqrt(ang2 / np.maximum(size, 1))
        good = (size > 0) & (clean_share >= 0.5) & (snr >= self.snr_min)
        if good.sum() > 1:
            good &= spread <= SPREAD_FACTOR * float(np.median(spread[good]))
        good[0] = False
        fit = fg & good[sp]
        first = np.zeros(n, dtype=np.int64)  # one pixel of each superpixel carries its features
        first[ids[::-1]] = np.arange(ids.size)[::-1]
        rows = feats.reshape(feats.shape[0], -1)[:, first[good]].T
        return out, unit_p, energy_p, feats, fit, rows

    def _assign(self, gm: GaussianMixture | BayesianGaussianMixture, sample: np.ndarray,
                spectra: np.ndarray, fg: np.ndarray, rel: Reliability | None, noise_deg: float,
                n_spectral: int) -> np.ndarray:
        """Each foreground pixel's group (0-based) under ``gm``: components merged into groups,
        the group of the largest summed posterior, groups without an interior dropped."""
        limit = None
        if rel is not None and self.merge_noise > 0 and np.isfinite(noise_deg):
            limit = self._merge_limit(gm, sample, noise_deg, n_spectral)
        groups = self._groups(gm, n_spectral, limit)
        resp = gm.predict_proba(spectra) @ groups  # (n_fg, n_groups) summed posteriors
        comp = resp.argmax(axis=1)
        if rel is not None and self.min_core_fraction > 0:  # a material has an interior
            keep = cored_groups(comp, fg, resp.shape[1], self.min_core_fraction * int(fg.sum()))
            if not keep.all():
                comp = resp[:, keep].argmax(axis=1)
        return comp

    def _tie_break(self) -> float:
        """``tie_break``, or by default one component's penalty when robust (0: the sweep decides)."""
        if self.tie_break is not None:
            return self.tie_break
        return 1.0 if self.robust else 0.0

    def _merge_limit(self, gm: GaussianMixture | BayesianGaussianMixture, sample: np.ndarray,
                     noise_deg: float, n_spectral: int) -> np.ndarray:
        """Merge angle per pair of components: ``merge_noise`` × the angle two samples of the same
        spectrum differ by at the components' brightness, √(θᵢ² + θⱼ²), with θ = the measured noise
        angle of one sample (``noise_deg``, at the median brightness) × √(median e / e) — shot noise
        (a dimmer material's shape is noisier); never below ``merge_angle_deg``."""
        n = gm.n_components
        e = np.linalg.norm(sample[:, :n_spectral], axis=1)  # unit spectra: 1; brightness from the log
        if self.brightness_weight > 0:
            e = np.exp(sample[:, -1] / self.brightness_weight)
        comp = gm.predict(sample)
        med = float(np.median(e))
        ek = np.array([float(np.median(e[comp == k])) if np.any(comp == k) else med for k in range(n)])
        theta = noise_deg * np.sqrt(np.clip(med / np.maximum(ek, 1e-12), 0.25, 16.0))
        pair = self.merge_noise * np.sqrt(theta[:, None] ** 2 + theta[None, :] ** 2)
        return np.maximum(pair, self.merge_angle_deg)

    def _censored(self, arr: np.ndarray, feats: np.ndarray, labels: np.ndarray, fg: np.ndarray,
                  rel: Reliability, noise_deg: float) -> tuple[np.ndarray, np.ndarray | None]:
        """Saturated pixels that no fitted material explains as censored data (``segmenters.censored``)
        get a mixture of their own, when they have an interior of at least ``censored_min_share`` of
        the foreground (``feats``: ``arr``'s clustering features, already computed); returns the
        labels (renumbered by size) and those pixels, or the labels unchanged and None."""
        clipped = rel.clipped[rel.bands]
        # only pixels with a band known to be clipped (at its plateau, or in a per-band mask) are
        # censored data; a pixel only a per-pixel mask flags has no band whose lower bound to test,
        # and its bent shape is no material's (tenth and eleventh passes)
        sat = rel.saturated & fg & clipped.any(axis=0)
        good = fg & ~rel.unreliable
        n = int(labels.max())
        # a count given for the build bounds the whole map: the censored fit gets what is left
        room = None if self.n_materials is None else self.n_materials - n
        if n == 0 or not good.any() or (room is not None and room < 1):
            return labels, None
        means = np.stack([arr[:, (labels == k) & good].mean(axis=1) if np.any((labels == k) & good)
                          else np.zeros(arr.shape[0]) for k in range(1, n + 1)])
        # a saturated pixel may lie as far from its material as noise puts two pixels of one
        tau = self.homogeneity_deg
        if np.isfinite(noise_deg):
            tau = min(max(tau, CENSORED_NOISE_FACTOR * noise_deg), 45.0)
        x, observed = arr[:, sat].T, ~clipped[:, sat].T
        on = rel.plateau[rel.bands]
        bounds = lower_bounds(x, observed, plateau_levels(arr, on), on[:, sat].T)
        un = np.zeros_like(fg)
        un[sat] = ~explained(x, observed, means, bounds, tau_deg=tau)
        core = un & ndimage.binary_erosion(un)
        if int(core.sum()) < max(MIN_FIT_PIXELS, self.censored_min_share * int(fg.sum())):
            return labels, None
        sample = feats[:, core].T
        if sample.shape[0] > self.sample_size:
            rng = np.random.default_rng(self.seed)
            sample = sample[rng.choice(sample.shape[0], self.sample_size, replace=False)]
        gm, _ = self._select(sample, given=False, most=room)  # their own count, within the room
        groups = self._groups(gm, arr.shape[0])
        resp = gm.predict_proba(feats[:, un].T) @ groups
        comp = resp.argmax(axis=1)
        if self.min_core_fraction > 0:
            keep = cored_groups(comp, un, resp.shape[1], self.min_core_fraction * int(fg.sum()))
            resp = resp[:, keep]
            comp = resp.argmax(axis=1)
        comp = merge_censored(arr[:, un].T, ~clipped[:, un].T, comp, resp.shape[1], tau)
        out = labels.copy()
        out[un] = n + 1 + comp
        return ranked(out), un

    def _features(self, arr: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit spectra, energy and the clustering features: the spectra plus, when weighted, log
        energy (the albedo cue: achromatic materials differ mostly in brightness)."""
        unit = features_of(arr, self.features)
        energy = np.linalg.norm(arr, axis=0)
        if self.brightness_weight <= 0:
            return unit, energy, unit
        log_e = np.log(np.maximum(energy, 1e-12))[np.newaxis]
        return unit, energy, np.concatenate([unit, self.brightness_weight * log_e])

    def analyse(self, cube: object, *, saturated: np.ndarray | None = None,
                mixture: Mixture | None = None) -> SpectralSegmentation:
        """Segment ``cube`` and return the labels with the fit's diagnostics; ``saturated``: the
        processor's clipping mask (H, W), used with the segmenter's own plateau test. ``mixture``: a
        mixture fitted elsewhere (``segmenters.sweep``: on a whole sweep's fit pixels) labels the
        cube instead of one selected on its own pixels, when its features have this cube's width
        (the same bands used); otherwise the cube's own is selected (``shared`` says which)."""
        arr = as_cube(cube)
        with self._threads():
            prep = self._prepare(arr, saturated)
            if isinstance(prep, SpectralSegmentation):
                return prep
            return self._label(prep, mixture)

    def fit_sample(self, cube: object, *, saturated: np.ndarray | None = None, clean_only: bool = False
                   ) -> np.ndarray | None:
        """The rows ``(n, features)`` the mixture would be fitted on for ``cube`` (its fit pixels'
        features, at most ``sample_size``); None for a cube without foreground or with one band.
        With ``clean_only`` a cube with fewer than ``MIN_FIT_PIXELS`` clean fit pixels (homogeneous,
        neither saturated nor near-black) gives those, not its reliable pixels or its whole
        foreground as ``analyse`` falls back to: in an over-exposed frame those are mostly the
        mosaic's blends beside clipped cells, shapes of no material (a sweep has other frames)."""
        arr = as_cube(cube)
        with self._threads():
            prep = self._prepare(arr, saturated, clean_only=clean_only)
        return None if isinstance(prep, SpectralSegmentation) else prep.sample

    def select(self, sample: np.ndarray) -> tuple[Mixture, dict[int, float]]:
        """The mixture for fit rows ``sample`` (as ``analyse`` selects it: the given count, the
        variational fit or the lowest criterion) and the criterion per count tried."""
        rows = np.asarray(sample, dtype=np.float64)
        if rows.ndim != 2 or rows.shape[0] < 2 or not np.all(np.isfinite(rows)):
            raise AnalysisInputError("sample", f"need finite rows (n ≥ 2, features), got shape {rows.shape}")
        with self._threads():
            return self._select(rows)

    def _threads(self) -> AbstractContextManager[object]:
        return nullcontext() if self.blas_threads is None else threadpool_limits(limits=self.blas_threads)

    def _prepare(self, arr: np.ndarray, saturated: np.ndarray | None = None, *, clean_only: bool = False
                 ) -> _Prepared | SpectralSegmentation:
        """Everything before the mixture: foreground, reliability, denoising, features and the fit
        sample; a cube with nothing to fit comes back finished (a ``SpectralSegmentation``).
        ``clean_only``: the fit pixels are the clean ones however few (see ``fit_sample``)."""
        h, w = arr.shape[1:]
        if self.white is not None:
            arr = normalise_cube(arr, white=self.white)
        fg, threshold = foreground_mask(arr, self.foreground)
        if self.robust and self.dim_radius > 0:  # regions too dim per pixel, found on window means
            fg = fg | dim_regions(arr, fg, radius=self.dim_radius)
        labels = np.zeros((h, w), dtype=np.int32)
        n_fg = int(fg.sum())
        if n_fg == 0:
            return SpectralSegmentation(labels, 0, threshold, {}, 0)
        if arr.shape[0] == 1:  # one band has no spectral shape: the foreground is one material
            labels[fg] = 1
            return SpectralSegmentation(labels, 1, threshold, {}, n_fg)
        rel: Reliability | None = None
        if self.robust:  # clipped bands out of the features, unreliable pixels out of the fit
            rel = reliability(arr, fg, snr_min=self.snr_min, saturated=saturated)
            arr = arr[rel.bands]
        unit, energy, feats = self._features(arr)
        pooled: np.ndarray | None = None  # the fit's samples when the cube is pooled into superpixels
        per, noise_deg = 1, float("nan")
        raw_noise_deg = noise_deg
        if rel is not None:
            noise_deg = neighbour_angle_deg(unit, ndimage.binary_erosion(fg) & ~rel.unreliable)
            raw_noise_deg = noise_deg  # saturated pixels are never filtered: their noise stays this
            if self.pool_target_deg > 0:
                per = pool_size(noise_deg, self.pool_target_deg)
        stride, averaged = 1, 1
        edges = None  # blends inside the object, judged on the cube as captured (the guided filter,
        if rel is not None and self.edge_step > 0:  # guided by spectral shape, smooths them away)
            edges = darker_than_a_neighbour(energy, self.edge_step)
        if per > 1 and rel is not None and self.denoise == "guided":
            averaged = per
            averaged_over = fg & ~rel.saturated
            if self.blend_filter_step > 0:  # strong blends are not averaged in, as clipped pixels are not
                averaged_over &= ~darker_than_a_neighbour(energy, self.blend_filter_step, unit,
                                                          self.blend_filter_angle)
            arr, radius = guided_denoise(arr, averaged_over, per)
            unit, energy, feats = self._features(arr)
            noise_deg = neighbour_angle_deg(unit, ndimage.binary_erosion(fg) & ~rel.unreliable)
            if self.dark_after_denoise and np.isfinite(noise_deg) and noise_deg > 0:
                # near-black is judged on the cube the fit sees: averaging n pixels divides the noise
                # by √n, measured here as the fall of the angular noise (a dark material at 5 % peak
                # was near-black per pixel, out of the fit, and joined its neighbour)
                rel = rel.rejudged(energy, max(raw_noise_deg / noise_deg, 1.0), fg, self.snr_min)
            # filtered neighbours are correlated: fit on a coarser grid (0: one sample per window)
            stride = self.fit_stride or 2 * radius + 1
        elif per > 1 and rel is not None:
            pooled_cube = self._pool(arr, unit, fg, rel, per)
            if pooled_cube[-1].shape[0] >= MIN_FIT_PIXELS:  # else too few superpixels: per pixel
                arr, unit, energy, feats, fit, pooled = pooled_cube
                averaged = per
        spectra = feats[:, fg].T  # (n_fg, features)
        if pooled is not None:  # the fit pixels were chosen per superpixel
            pass
        elif self.fit_pixels == "all":
            fit = fg
        else:
            scale = None
            if self.noise_scaled:  # angular noise grows as 1/√signal (shot noise): dark pixels get more room
                ref = float(np.median(energy[fg]))
                scale = np.sqrt(np.maximum(ref / np.maximum(energy, 1e-12), 1.0))
            angle = self.homogeneity_deg
            if rel is not None and np.isfinite(noise_deg):  # the angle follows the cube's noise
                angle = min(max(angle, NOISE_ANGLE_FACTOR * noise_deg), 45.0)
            fit = homogeneous_pixels(unit, fg, angle, scale)
            # the mosaic garbles a cell that is part object, part gap: a blend, out of the fit
            if edges is not None and int((fit & ~edges).sum()) >= MIN_FIT_PIXELS:
                fit = fit & ~edges
        if rel is not None and pooled is None:
            fit = fit & ~rel.unreliable
            if int(fit.sum()) < MIN_FIT_PIXELS and not clean_only:
                fit = fg & ~rel.unreliable
        if pooled is None and int(fit.sum()) < MIN_FIT_PIXELS and not clean_only:  # too few: use them all
            fit = fg
        if stride > 1:  # keep the fit pixels of a coarse grid (denoised pixels are not independent)
            grid = np.zeros_like(fit)
            grid[::stride, ::stride] = True
            if int((fit & grid).sum()) >= MIN_FIT_PIXELS:
                fit = fit & grid
        pool = feats[:, fit].T if pooled is None else pooled
        rng = np.random.default_rng(self.seed)
        sample = pool
        if pool.shape[0] > self.sample_size:
            sample = pool[rng.choice(pool.shape[0], self.sample_size, replace=False)]
        return _Prepared(arr, fg, threshold, rel, unit, feats, spectra, fit, sample, per, noise_deg,
                         raw_noise_deg, averaged, n_fg)

    def _label(self, prep: _Prepared, mixture: Mixture | None = None) -> SpectralSegmentation:
        """Labels from the mixture: ``mixture`` when given and of the sample's width, else selected
        on the cube's own sample; then merging, near ties, saturated pixels and smoothing."""
        arr, fg, rel, unit, feats, spectra = prep.arr, prep.fg, prep.rel, prep.unit, prep.feats, prep.spectra
        sample, per, noise_deg, raw_noise_deg = prep.sample, prep.per, prep.noise_deg, prep.raw_noise_deg
        labels = np.zeros(fg.shape, dtype=np.int32)
        fits: dict[int, Mixture] = {}
        bic: dict[int, float] = {}
        shared = mixture is not None and int(mixture.means_.shape[1]) == sample.shape[1]
        if mixture is not None and shared:
            best = mixture
        else:
            best, bic = self._select(sample, fits=fits)
        noise_fit = noise_deg / np.sqrt(2.0 * per)
        comp = self._assign(best, sample, spectra, fg, rel, noise_fit, unit.shape[0])
        ties: list[int] = []
        if self._tie_break() > 0 and fits:
            margin = self._tie_break() * component_penalty(sample.shape[1], self.covariance_type,
                                                           sample.shape[0])
            ties = near_ties(bic, best.n_components, margin)
        if ties:  # near-tied larger counts: the map decides
            shown = np.zeros(fg.shape, dtype=np.int32)
            shown[fg] = comp + 1
            floor, used = coherence(shown) - COHERENCE_TOL, len(np.unique(comp))
            for n in ties:
                other = self._assign(fits[n], sample, spectra, fg, rel, noise_fit, unit.shape[0])
                shown[fg] = other + 1
                found = len(np.unique(other))
                if found > used and coherence(shown) >= floor:
                    comp, used = other, found
        labels[fg] = comp + 1
        labels = ranked(labels)  # ids by decreasing size, ties by component order: reproducible
        censored: np.ndarray | None = None
        if rel is not None and self.censored and rel.saturated.any():
            labels, censored = self._censored(arr, feats, labels, fg, rel, raw_noise_deg)
        if rel is not None and rel.saturated.any():
            rest = rel.saturated if censored is None else rel.saturated & ~censored
            labels = relabel_saturated(labels, arr, rel.clipped[rel.bands], rest)
        if self.smooth:
            shown = np.zeros_like(unit)
            shown[:, fg] = unit[:, fg]
            sp = slic(shown, n_segments=self.n_superpixels, slic_zero=True, mask=fg, channel_axis=0,
                      start_label=1)
            labels = majority_in_superpixels(labels, sp).astype(np.int32)
        n_used = int(np.count_nonzero(np.bincount(labels.ravel())[1:]))
        if rel is None:
            return SpectralSegmentation(labels, n_used, prep.threshold, bic, prep.n_fg, shared=shared)
        return SpectralSegmentation(labels, n_used, prep.threshold, bic, prep.n_fg, rel.unreliable,
                                    tuple(int(b) for b in rel.bands), prep.fit, prep.averaged, censored,
                                    shared)
