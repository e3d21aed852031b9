"""Small synthetic multispectral scenes with known ground truth (tests, benchmarks, QC demos).

A scene is a dark background with an elliptical "satellite" split into angular
sectors, one material per sector. Each material has its own reflectance spectrum;
a smooth shading field (0.55–1.0, the same for all bands) and Gaussian noise are
applied, so a correct segmenter must rely on spectral *shape*, not brightness.
"""

from __future__ import annotations

import numpy as np

from m2s2hil.analysis.errors import AnalysisInputError


def material_spectra(n_materials: int, n_bands: int = 10, seed: int = 0) -> np.ndarray:
    """``(n_materials, n_bands)`` smooth, clearly distinct spectra in [0.15, 0.95].

    Material m peaks at band ``(m + 0.5)·n_bands/n_materials`` (a Gaussian bump over a flat base).
    """
    rng = np.random.default_rng(seed)
    x = np.arange(n_bands)
    centres = (np.arange(n_materials) + 0.5) * n_bands / n_materials
    width = max(n_bands / n_materials, 1.5)
    bumps = np.exp(-0.5 * ((x[None, :] - centres[:, None]) / width) ** 2)
    base = rng.uniform(0.15, 0.25, size=(n_materials, 1))
    return base + (0.95 - base) * bumps


def synthetic_scene(
    shape: tuple[int, int] = (64, 64),
    n_materials: int = 3,
    n_bands: int = 10,
    *,
    spectra: np.ndarray | None = None,
    noise: float = 0.01,
    background_level: float = 0.02,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(cube float32 (bands, H, W), gt int32 (H, W))``; gt 0 = background, 1..n = materials."""
    h, w = shape
    if h < 8 or w < 8:
        raise AnalysisInputError("shape", f"scene must be at least 8×8, got {shape}")
    spec = material_spectra(n_materials, n_bands, seed) if spectra is None else np.asarray(spectra, float)
    if spec.shape != (n_materials, n_bands):
        raise AnalysisInputError("spectra", f"expected shape {(n_materials, n_bands)}, got {spec.shape}")
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    cy, cx = (h - 1) / 2, (w - 1) / 2
    inside = ((yy - cy) / (0.4 * h)) ** 2 + ((xx - cx) / (0.42 * w)) ** 2 <= 1.0
    angle = (np.arctan2(yy - cy, xx - cx) + np.pi) / (2 * np.pi)  # 0..1
    sector = np.minimum((angle * n_materials).astype(np.int32), n_materials - 1)
    gt = np.where(inside, sector + 1, 0).astype(np.int32)
    shading = 0.55 + 0.45 * (0.5 + 0.5 * np.cos(2 * np.pi * (xx / w * 0.7 + yy / h * 0.4)))
    cube = np.full((n_bands, h, w), background_level, dtype=np.float64)
    for m in range(n_materials):
        sel = gt == m + 1
        cube[:, sel] = spec[m][:, None] * shading[sel][None, :]
    cube += rng.normal(0.0, noise, size=cube.shape)
    return np.clip(cube, 0.0, None).astype(np.float32), gt


def exposed_scene(
    peak_fraction: float,
    shape: tuple[int, int] = (64, 64),
    n_materials: int = 3,
    *,
    full_scale: float = 1000.0,
    e_per_dn: float = 13.2,
    read_noise_e: float = 13.0,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """``synthetic_scene`` as a sensor records it at an exposure: the brightest material band
    peaks at ``peak_fraction`` of ``full_scale`` DN, shot and read noise (electrons, as
    ``simulators.sensor``), values clipped to [0, full_scale] — over 1 the bright bands clip,
    at a few percent the dark pixels drown in read noise. Same scene for every exposure."""
    if not peak_fraction > 0:
        raise AnalysisInputError("peak_fraction", f"must be > 0, got {peak_fraction}")
    clean, gt = synthetic_scene(shape, n_materials, noise=0.0, background_level=0.0, seed=seed)
    signal_dn = clean.astype(np.float64) * (peak_fraction * full_scale / float(clean.max()))
    rng = np.random.default_rng(seed + 1)
    electrons = signal_dn * e_per_dn
    noisy = electrons + rng.standard_normal(clean.shape) * np.sqrt(electrons + read_noise_e**2)
    return np.clip(noisy / e_per_dn, 0.0, full_scale).astype(np.float32), gt
