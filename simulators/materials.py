"""Spectral reflectance of the PLA filaments, evaluated in the camera's bands.

Each filament is a smooth spectrum built from a few logistic steps and Gaussian peaks
plus PLA's near-infrared plateau (parameters in ``data/materials.toml``, which also
explains the model). A band's reflectance is the spectrum averaged under a Gaussian
of the band's centre and FWHM, so a wide band (431 nm, 65 nm FWHM) sees a smoother
version of the curve than a narrow one.

Metallic ("PLA Pro") filaments get a strong Blinn-Phong specular lobe tinted by their
diffuse colour; plain PLA a faint white gloss.
"""

from __future__ import annotations

import tomllib
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cache
from importlib import resources

import numpy as np

# Spectral grid for band integration: wide enough for ±3σ of every TOUCAN band.
GRID_NM = np.arange(300.0, 1100.0, 1.0)
FWHM_TO_SIGMA = 1.0 / (2.0 * np.sqrt(2.0 * np.log(2.0)))

MATERIAL_KEYS = (
    "pro_silver", "dark_grey", "pro_metallic_blue", "pro_gold", "cold_white",
    "pro_metallic_magenta", "red", "azure_blue", "olive_brown", "lime_green", "wood",
)


class UnknownMaterialError(KeyError):
    """A material key with no reflectance model."""

    def __str__(self) -> str:
        return str(self.args[0])


@dataclass(frozen=True)
class SpectralMaterial:
    key: str
    base: float
    metallic: bool = False
    steps: tuple[tuple[float, float, float], ...] = ()
    peaks: tuple[tuple[float, float, float], ...] = ()
    nir: float | None = None
    nir_edge: float = 740.0
    nir_width: float = 18.0
    specular: float = 0.04
    shininess: float = 25.0
    tint: float = 0.0
    extra: dict = field(default_factory=dict, compare=False, repr=False)

    def spectrum(self, nm: np.ndarray) -> np.ndarray:
        """Reflectance (0..1) at wavelengths ``nm``."""
        nm = np.asarray(nm, dtype=np.float64)
        r = np.full(nm.shape, self.base)
        for c, w, h in self.steps:
            r += h / (1.0 + np.exp(-(nm - c) / w))
        for c, w, h in self.peaks:
            r += h * np.exp(-0.5 * ((nm - c) / w) ** 2)
        if self.nir is not None:
            s = 1.0 / (1.0 + np.exp(-(nm - self.nir_edge) / self.nir_width))
            r = r + (self.nir - r) * s
        return np.clip(r, 0.0, 1.0)


def band_weights(bands_nm: Sequence[float], fwhm_nm: Sequence[float]) -> np.ndarray:
    """Normalised Gaussian band responses on ``GRID_NM``: shape (n_bands, len(GRID_NM))."""
    c = np.asarray(bands_nm, dtype=np.float64)[:, None]
    s = np.asarray(fwhm_nm, dtype=np.float64)[:, None] * FWHM_TO_SIGMA
    w = np.exp(-0.5 * ((GRID_NM[None, :] - c) / s) ** 2)
    return w / w.sum(axis=1, keepdims=True)


def band_average(spectrum: np.ndarray, bands_nm: Sequence[float], fwhm_nm: Sequence[float]) -> np.ndarray:
    """A spectrum sampled on ``GRID_NM`` averaged under each band's Gaussian response."""
    return band_weights(bands_nm, fwhm_nm) @ np.asarray(spectrum, dtype=np.float64)


@cache
def load_materials() -> dict[str, SpectralMaterial]:
    """The reflectance table (eleven filaments plus the ``background`` backdrop)."""
    text = resources.files("m2s2hil.simulators").joinpath("data/materials.toml").read_text()
    raw = tomllib.loads(text)
    out: dict[str, SpectralMaterial] = {}
    for key, v in raw.items():
        v = dict(v)
        out[key] = SpectralMaterial(
            key=key,
            base=float(v.pop("base")),
            metallic=bool(v.pop("metallic", False)),
            steps=tuple(tuple(map(float, s)) for s in v.pop("steps", ())),
            peaks=tuple(tuple(map(float, p)) for p in v.pop("peaks", ())),
            nir=v.pop("nir", None),
            nir_edge=float(v.pop("nir_edge", 740.0)),
            nir_width=float(v.pop("nir_width", 18.0)),
            specular=float(v.pop("specular", 0.04)),
            shininess=float(v.pop("shininess", 25.0)),
            tint=float(v.pop("tint", 0.0)),
            extra=v,
        )
    missing = set(MATERIAL_KEYS) - set(out)
    if missing:
        raise UnknownMaterialError(f"materials.toml lacks {sorted(missing)}")
    return out


def material(key: str) -> SpectralMaterial:
    table = load_materials()
    try:
        return table[key]
    except KeyError:
        known = ", ".join(k for k in table if k != "background")
        raise UnknownMaterialError(f"no reflectance model for material {key!r}; known: {known}") from None


def reflectance(key: str, bands_nm: Sequence[float], fwhm_nm: Sequence[float]) -> np.ndarray:
    """Diffuse reflectance of ``key`` in each band (float64, shape (n_bands,))."""
    return band_average(material(key).spectrum(GRID_NM), bands_nm, fwhm_nm)


def specular_colour(key: str, bands_nm: Sequence[float], fwhm_nm: Sequence[float]) -> np.ndarray:
    """Peak specular reflectance per band: white gloss mixed with the diffuse colour by ``tint``."""
    m = material(key)
    rho = reflectance(key, bands_nm, fwhm_nm)
    colour = rho / max(float(rho.max()), 1e-6)
    return m.specular * ((1.0 - m.tint) + m.tint * colour)


@dataclass(frozen=True)
class MaterialTable:
    """Per-label arrays for a class list ``["background", *materials]``."""

    names: tuple[str, ...]
    rho: np.ndarray  # (n_labels, n_bands) float32 diffuse reflectance
    spec: np.ndarray  # (n_labels, n_bands) float32 specular colour
    shininess: np.ndarray  # (n_labels,) float32


def material_table(
    materials: Sequence[str], bands_nm: Sequence[float], fwhm_nm: Sequence[float]
) -> MaterialTable:
    names = ("background", *materials)
    rho = np.stack([reflectance(k, bands_nm, fwhm_nm) for k in names]).astype(np.float32)
    spec = np.stack([specular_colour(k, bands_nm, fwhm_nm) for k in names]).astype(np.float32)
    shin = np.array([material(k).shininess for k in names], dtype=np.float32)
    return MaterialTable(names=names, rho=rho, spec=spec, shininess=shin)
