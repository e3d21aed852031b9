"""Which pixels and bands of a cube can be trusted, and the cube put on a common radiometric scale.

The spectral segmenter works on spectral *shape* (unit spectra), so a global exposure or gain
factor and multiplicative shading already cancel; what exposure changes is which pixels still
carry a shape (issue 23, docs/evaluation.md "Robustness"):

- **clipped** bands: a band at the sensor's full scale records only a lower bound, and a pixel
  clipped in some bands has a flattened spectrum (over-exposure split one material into several
  "flat-topped" clusters). Without the full scale, a clipped band shows as a *plateau*: the
  fullest of the band's top bins (``PLATEAU_REL_TOL`` wide), with the bins below it that are still
  part of the spike (dark subtraction leaves each clipped value at full scale − its pixel's dark,
  a few DN apart), holding more pixels than the three times wider bin below (a natural tail
  falls towards its maximum). A processor's own mask (``saturated``,
  ``ProcessedFrame.saturated_mask``) can be given as well: (H, W), a pixel with some band clipped,
  or (bands, H, W), which bands (``processing.stability.band_saturation``). Only the per-band mask
  says where one of a band's mosaic positions clipped: the averaged value is bent low, not at the
  plateau.
- **near-black** pixels: band energy under ``snr_min`` × the noise floor. Their unit spectrum is
  mostly noise (its angular noise is about 1/SNR rad, 6° at SNR 10), and at low exposure they
  formed clusters of their own (under-exposure split a one-material build into 5–10).
  The noise floor is measured on the backdrop: per band, σ from differences of horizontal
  neighbours (both in the backdrop), σ² = mean(d²)/2 — robust to the backdrop's own level and
  not quantised to zero as a MAD of super-pixel values is.

``guided_denoise`` is the edge-preserving smoothing the segmenter applies where the SNR is low.

``normalise_cube`` divides by the white reference (per band or per pixel) and by
exposure × gain where given: the cube becomes reflectance-like, so the same object at another
exposure gives the same numbers (shape and brightness coordinate alike).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from m2s2hil.analysis.errors import AnalysisInputError

PLATEAU_REL_TOL = 0.004  # a plateau bin's width: 0.4 % of the band's maximum (≈ 4 DN on 10 bits)
PLATEAU_MIN_PIXELS = 20
PLATEAU_SEARCH = 2  # top bins (tolerance wide) that may hold the plateau: its outliers reach one above
PLATEAU_MIN_FRACTION = 0.002  # of the foreground: a natural tail puts far fewer pixels that close
MIN_UNCLIPPED = 0.05  # share of the foreground unclipped in every kept band (else bands go)
MIN_BANDS = 3


def neighbour_angle_deg(unit: np.ndarray, mask: np.ndarray) -> float:
    """Median spectral angle (degrees) between horizontal neighbours that are both in ``mask``:
    the cube's own angular noise level (material boundaries only reach the tail); NaN if none."""
    both = mask[:, 1:] & mask[:, :-1]
    if not both.any():
        return float("nan")
    cos = np.einsum("bn,bn->n", unit[:, :, 1:][:, both], unit[:, :, :-1][:, both])
    return float(np.degrees(np.median(np.arccos(np.clip(cos, -1.0, 1.0)))))


@dataclass(frozen=True)
class Reliability:
    """What ``reliability`` found; masks are (H, W) unless stated."""

    bands: np.ndarray  # int indices of the bands the features use (clipped-out bands left out)
    clipped: np.ndarray  # bool (bands, H, W): the band clipped (at its plateau, or a given per-band mask)
    plateau: np.ndarray  # bool (bands, H, W): at the plateau the cube itself shows
    saturated: np.ndarray  # a used band clipped (or the given mask)
    dark: np.ndarray  # near-black: energy (used bands) < snr_min × noise floor
    noise: np.ndarray  # (bands,) noise floor σ per band, cube units
    snr: np.ndarray  # energy / noise floor energy (used bands)

    @property
    def unreliable(self) -> np.ndarray:
        return self.saturated | self.dark

    @property
    def noise_energy(self) -> float:
        """The noise floor as band energy over the used bands: what ``snr`` divides by."""
        return noise_energy(self.noise, self.bands)

    def rejudged(self, energy: np.ndarray, gain: float, fg: np.ndarray, snr_min: float) -> Reliability:
        """Near-black judged again on a cube whose noise fell by ``gain`` (denoised: the energy is
        the filtered cube's, over the used bands); clipping is unchanged."""
        snr = energy / self.noise_energy * gain
        return replace(self, dark=(snr < snr_min) & fg, snr=snr)


def noise_energy(noise: np.ndarray, bands: np.ndarray) -> float:
    """Per-band noise σ as one band-energy figure over ``bands`` (√Σσ²)."""
    return float(np.sqrt(np.sum(noise[bands] ** 2)))


def normalise_cube(
    cube: np.ndarray, *, white: np.ndarray | None = None, exposure_s: float | None = None, gain: float = 1.0
) -> np.ndarray:
    """``cube / (white · exposure_s · gain)``: ``white`` per band ``(bands,)`` or per pixel
    ``(bands, H, W)`` (the calibration's white reference), non-positive entries refused."""
    out = np.asarray(cube, dtype=np.float64)
    if white is not None:
        w = np.asarray(white, dtype=np.float64)
        if w.ndim == 1:
            w = w[:, None, None]
        if w.shape[0] != out.shape[0] or w.ndim != 3:
            raise AnalysisInputError("white", f"shape {np.shape(white)} does not fit a cube of {out.shape}")
        if not np.all(np.isfinite(w)) or np.any(w <= 0):
            raise AnalysisInputError("white", "the white reference must be finite and > 0 in every band")
        out = out / w
    if exposure_s is not None:
        if not exposure_s > 0 or not gain > 0:
            raise AnalysisInputError("exposure_s", f"exposure and gain must be > 0, got {exposure_s}, {gain}")
        out = out / (exposure_s * gain)
    return out


def clipped_bands(cube: np.ndarray, fg: np.ndarray) -> np.ndarray:
    """(bands, H, W) bool: per band, the pixels on a clipping plateau (see module docstring);
    a band without a plateau has none.

    The plateau is found at the most populated bin of the band's top ``PLATEAU_SEARCH`` bins, not
    at the band's maximum: dark subtraction leaves every clipped pixel at full scale minus its own
    dark value, so the plateau is a few DN wide, and a few pixels with a low dark value sit above
    it. Anchored at the maximum, a tolerance of a few DN missed a fifth of it (Hubble B1 at
    200 % peak: 2 500 of 13 000 clipped values of a band, and whole bands whose maximum was 5 DN
    above the plateau's centre).
    """
    out = np.zeros(cube.shape, dtype=bool)
    n_fg = int(fg.sum())
    need = max(PLATEAU_MIN_PIXELS, int(PLATEAU_MIN_FRACTION * n_fg))
    for b in range(cube.shape[0]):
        band = cube[b]
        top = float(band.max())
        if top <= 0:
            continue
        # the width of a bin: the relative tolerance, but at least one quantisation step
        # (at low exposure a natural tail of integer-like values has many pixels *at* its maximum)
        levels = np.unique(band[band >= 0.9 * top])
        step = float(np.min(np.diff(levels))) if levels.size > 1 else 0.0
        delta = max(PLATEAU_REL_TOL * top, step)
        n_bins = PLATEAU_SEARCH + 4  # the search window and a shoulder below it
        edges = top - delta * np.arange(n_bins, -1, -1)
        counts, _ = np.histogram(band[band >= edges[0]], bins=edges)
        mode = n_bins - 1 - int(np.argmax(counts[::-1][:PLATEAU_SEARCH]))  # the top-most fullest bin
        # the plateau reaches down while a bin holds a tenth of the fullest and twice the one below
        lo = mode
        while lo >= 2 and counts[lo - 1] > max(2 * counts[lo - 2], 0.1 * counts[mode]):
            lo -= 1
        near = band >= edges[lo]
        n_near = int(near.sum())
        shoulder = int(np.count_nonzero((band >= edges[lo] - 3 * delta) & ~near))  # three bins below
        # a spike: the fullest bin holds more than the three times wider bin below the plateau (a
        # natural tail, falling or flat, does not)
        if n_near >= need and int(counts[mode]) > shoulder:
            out[b] = near
    return out


def backdrop_noise(cube: np.ndarray, fg: np.ndarray) -> np.ndarray:
    """(bands,) noise σ per band from horizontal neighbour differences inside the backdrop."""
    both = ~fg[:, 1:] & ~fg[:, :-1]
    if int(both.sum()) < 10:  # no backdrop to measure on: the object's own fine differences
        both = np.ones_like(both)
    d = (cube[:, :, 1:] - cube[:, :, :-1])[:, both]
    sigma = np.sqrt(np.mean(d.astype(np.float64) ** 2, axis=1) / 2.0)
    tiny = 1e-9 * max(float(np.abs(cube).max()), 1e-12)
    return np.maximum(sigma, tiny)


def reliability(
    cube: np.ndarray, fg: np.ndarray, *, snr_min: float = 10.0, saturated: np.ndarray | None = None
) -> Reliability:
    """Clipped bands, saturated and near-black pixels of ``cube`` (bands, H, W) with foreground ``fg``;
    ``saturated``: the processor's clipping mask, (H, W) or per band (bands, H, W)."""
    n_bands = cube.shape[0]
    given, per_band = _given_mask(saturated, n_bands, fg.shape)
    clipped = clipped_bands(cube, fg)
    n_fg = max(int(fg.sum()), 1)
    frac = clipped[:, fg].sum(axis=1) / n_fg
    keep = np.ones(n_bands, dtype=bool)
    # every band stays (a clipped value is masked per pixel, in the fit and in relabel_saturated)
    # while ≥ MIN_UNCLIPPED of the foreground is unclipped in all of them; else the most clipped
    # bands go, one at a time (dropping every band clipped on > 30 % lost materials at 150 % peak)
    for b in np.argsort(-frac, kind="stable"):
        if frac[b] == 0 or int(keep.sum()) <= min(MIN_BANDS, n_bands):
            break
        if 1.0 - clipped[keep][:, fg].any(axis=0).mean() >= MIN_UNCLIPPED:
            break
        keep[b] = False
    bands = np.flatnonzero(keep)
    plateau = clipped
    if per_band is not None:  # which bands clipped: the plateau's and the bent ones alike
        clipped = clipped | per_band
    sat = clipped[bands].any(axis=0)
    if given is not None and per_band is None:
        # a processor's mask flags any clipped band; those left out of the features do not count
        sat = sat | (given & ~clipped[~keep].any(axis=0)) if (~keep).any() else sat | given
    noise = backdrop_noise(cube, fg)
    energy = np.sqrt(np.einsum("bhw,bhw->hw", cube[bands], cube[bands]))
    snr = energy / noise_energy(noise, bands)
    return Reliability(bands, clipped, plateau, sat & fg, (snr < snr_min) & fg, noise, snr)


def _given_mask(saturated: np.ndarray | None, n_bands: int, shape: tuple[int, ...]
                ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(pixel mask, per-band mask or None) of a given clipping mask, its shape checked."""
    if saturated is None:
        return None, None
    given = np.asarray(saturated, dtype=bool)
    if given.shape == tuple(shape):
        return given, None
    if given.shape == (n_bands, *shape):
        return np.asarray(given.any(axis=0)), given
    raise AnalysisInputError("saturated", f"mask shape {given.shape}, expected {tuple(shape)} or "
                             f"{(n_bands, *shape)}")


def pool_size(noise_deg: float, target_deg: float) -> int:
    """Pixels to average so that an angular noise of ``noise_deg`` per pixel falls to ``target_deg``:
    the mean of n independent spectra has 1/√n of the noise, so n = ⌈(noise / target)²⌉ (1 = none)."""
    if not np.isfinite(noise_deg) or noise_deg <= target_deg:
        return 1
    return int(np.ceil((noise_deg / target_deg) ** 2))


def superpixel_means(cube: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """(n_segments + 1, bands) mean spectrum of each segment id of ``segments`` (row 0: id 0)."""
    ids = segments.ravel()
    n = int(ids.max()) + 1
    count = np.maximum(np.bincount(ids, minlength=n), 1).astype(np.float64)
    flat = cube.reshape(cube.shape[0], -1)
    return np.stack([np.bincount(ids, weights=flat[b], minlength=n) for b in range(cube.shape[0])], axis=1) \
        / count[:, None]


def guided_denoise(cube: np.ndarray, fg: np.ndarray, per: int, *, edge_sigmas: float = 3.0
                   ) -> tuple[np.ndarray, int]:
    """Edge-preserving smoothing of the foreground (``cv2.ximgproc.guidedFilter``) averaging about
    ``per`` pixels where the spectrum is flat; returns the cube and the filter radius.

    Guide: the foreground's first three principal components of the unit spectra, each scaled by
    its own noise σ (neighbour differences), so ``eps`` = ``edge_sigmas``² is in units of the noise:
    a window whose guide varies by less than that is averaged (noise), one that varies more (a
    material edge) follows the guide and is kept. The radius gives a (2r + 1)² box of ≥ ``per``.
    """
    import cv2

    radius = max(1, int(np.ceil((np.sqrt(per) - 1) / 2)))
    unit = cube / np.maximum(np.linalg.norm(cube, axis=0, keepdims=True), 1e-12)
    x = unit[:, fg].T
    mean = x.mean(axis=0)
    _, _, vt = np.linalg.svd(x - mean, full_matrices=False)
    comps = np.einsum("kb,bhw->khw", vt[:3], unit - mean[:, None, None])
    both = fg[:, 1:] & fg[:, :-1]
    d = (comps[:, :, 1:] - comps[:, :, :-1])[:, both]
    sigma = np.sqrt(np.maximum(np.mean(d**2, axis=1) / 2.0, 1e-12))
    guide = np.ascontiguousarray(np.moveaxis(comps / sigma[:, None, None], 0, -1), dtype=np.float32)
    guide[~fg] = 0.0
    out = np.asarray(cube, dtype=np.float64).copy()
    # normalised filtering: the backdrop does not bleed into the rim (weights = foreground)
    m = fg.astype(np.float32)
    gf = cv2.ximgproc.createGuidedFilter(guide, radius, float(edge_sigmas) ** 2)
    norm = gf.filter(m)
    for b in range(cube.shape[0]):
        band = (cube[b] * fg).astype(np.float32)
        out[b][fg] = (gf.filter(band) / np.maximum(norm, 1e-6))[fg]
    return out, radius
