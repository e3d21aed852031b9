"""Demosaicing quality metrics: PSNR, SSIM and SAM, per band and averaged.

Conventions (also in docs/processing.md):

- Both cubes are ``(bands, H, W)`` in the same units (DN of the sensor); a border of ``border``
  pixels is cut from every side before anything is computed (default 3·n, where the methods'
  border extrapolation stops mattering).
- PSNR_b = 10·log10(peak² / MSE_b) with ``peak`` = the sensor's full scale (1023 for 10 bits),
  not the reference's maximum; the summary PSNR is the mean of the per-band PSNRs (the MSFA
  literature's convention), not the PSNR of the pooled MSE.
- SSIM_b is Wang et al. 2004 as implemented by scikit-image with their settings: 11×11
  Gaussian window σ = 1.5, K1 = 0.01, K2 = 0.03, ``data_range = peak``; the summary is the mean over bands.
- SAM = mean over pixels of arccos(<x, x̂> / (‖x‖·‖x̂‖)) in degrees, x the reference spectrum;
  pixels where either spectrum is all zero are left out (their angle is undefined).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from skimage.metrics import structural_similarity


def _crop(cube: np.ndarray, border: int) -> np.ndarray:
    if border <= 0:
        return cube
    if 2 * border >= min(cube.shape[1:]):
        raise ValueError(f"border {border} leaves nothing of a {cube.shape[1]}×{cube.shape[2]} image")
    return cube[:, border:-border, border:-border]


def _check(est: np.ndarray, ref: np.ndarray) -> None:
    if est.shape != ref.shape or est.ndim != 3:
        raise ValueError(f"cubes differ in shape: estimate {est.shape}, reference {ref.shape}")


def psnr_per_band(est: np.ndarray, ref: np.ndarray, *, peak: float, border: int = 0) -> np.ndarray:
    _check(est, ref)
    e = _crop(est, border).astype(np.float64)
    r = _crop(ref, border).astype(np.float64)
    mse = ((e - r) ** 2).mean(axis=(1, 2))
    with np.errstate(divide="ignore"):
        return 10.0 * np.log10(peak**2 / mse)


def ssim_per_band(est: np.ndarray, ref: np.ndarray, *, peak: float, border: int = 0) -> np.ndarray:
    _check(est, ref)
    e = _crop(est, border).astype(np.float64)
    r = _crop(ref, border).astype(np.float64)
    return np.array(
        [
            structural_similarity(
                r[b], e[b], data_range=peak, gaussian_weights=True, sigma=1.5, use_sample_covariance=False
            )
            for b in range(r.shape[0])
        ]
    )


def sam_map(est: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Per-pixel spectral angle in degrees (NaN where either spectrum is all zero)."""
    _check(est, ref)
    e = est.astype(np.float64)
    r = ref.astype(np.float64)
    dot = (e * r).sum(axis=0)
    norm = np.sqrt((e * e).sum(axis=0) * (r * r).sum(axis=0))
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.where(norm > 0, dot / norm, np.nan)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def sam_deg(est: np.ndarray, ref: np.ndarray, *, border: int = 0, mask: np.ndarray | None = None) -> float:
    """Mean spectral angle (degrees) over the cropped image, optionally only where ``mask`` is True."""
    angles = _crop(sam_map(est, ref)[None], border)[0]
    if mask is not None:
        angles = angles[_crop(mask[None], border)[0]]
    return float(np.nanmean(angles)) if np.isfinite(angles).any() else float("nan")


@dataclass
class Quality:
    """Metrics of one estimate against one reference."""

    psnr_db: float
    ssim: float
    sam_deg: float
    psnr_bands: np.ndarray = field(repr=False)
    ssim_bands: np.ndarray = field(repr=False)
    rmse_dn: float = float("nan")  # sqrt of the band-averaged MSE, in DN

    @staticmethod
    def mean(items: list[Quality]) -> Quality:
        """Average over several scenes (per band and summary alike)."""
        return Quality(
            psnr_db=float(np.mean([q.psnr_db for q in items])),
            ssim=float(np.mean([q.ssim for q in items])),
            sam_deg=float(np.mean([q.sam_deg for q in items])),
            psnr_bands=np.mean([q.psnr_bands for q in items], axis=0),
            ssim_bands=np.mean([q.ssim_bands for q in items], axis=0),
            rmse_dn=float(np.sqrt(np.mean([q.rmse_dn**2 for q in items]))),
        )


def evaluate(est: np.ndarray, ref: np.ndarray, *, peak: float, border: int, ssim: bool = True) -> Quality:
    psnr_b = psnr_per_band(est, ref, peak=peak, border=border)
    ssim_b = ssim_per_band(est, ref, peak=peak, border=border) if ssim else np.full(len(psnr_b), np.nan)
    return Quality(
        psnr_db=float(np.mean(psnr_b)),
        ssim=float(np.mean(ssim_b)),
        sam_deg=sam_deg(est, ref, border=border),
        psnr_bands=psnr_b,
        ssim_bands=ssim_b,
        rmse_dn=float(np.sqrt(np.mean(peak**2 / 10.0 ** (psnr_b / 10.0)))),
    )
