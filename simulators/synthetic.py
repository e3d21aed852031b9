"""The paper's synthetic domain, rendered: one RGB image and one RGB image per band, per view.

M2S2 (section 2.3) renders its synthetic split in Blender, in RGB: the mockup's materials
carry RGB colours, and each TOUCAN band is approximated by lighting the scene with the RGB
colour of the band's centre wavelength (``wavelength_to_rgb(centre, gamma=0.80)``). This
module does the same over the simulator's scene: one rasterised and shaded view (depth,
normals, labels, the diffuse factor ``D`` and the specular factor ``S`` of
:mod:`~m2s2hil.simulators.shading`) gives every image of the view, since only the lights'
colour changes between them::

    image_c = exposure · light_c · (albedo[label, c] · D + specular[label, c] · S)

``albedo`` and ``specular`` are each material's linear-sRGB colours (the caller derives them
from the filaments' spectra, as an artist sets a Blender base colour to the filament's
look); ``light`` is white for the RGB render and the band's colour for a band render.
Images are encoded with the sRGB transfer function (Blender's "Standard" view transform),
8 bits. The mask is the view's label map, exact (no anti-aliasing).

Where this departs from a Blender (Cycles) render: no path tracing (no interreflection,
colour bleeding or soft shadows: the LED bars are shadowless directional lights plus an
ambient term, the spotlight casts hard shadow-map shadows), Lambert + Blinn-Phong instead of
the Principled BSDF (no Fresnel, no roughness-dependent lobes), no anti-aliasing or depth of
field, orthographic projection; docs/twin.md lists them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from m2s2hil.simulators.scene import Shaded


@dataclass(frozen=True)
class SyntheticView:
    """One view: the RGB render, the band renders (lit with each band's colour), the mask."""

    rgb: np.ndarray  # (H, W, 3) uint8, sRGB-encoded
    bands: tuple[np.ndarray, ...]  # n_bands × (H, W, 3) uint8
    mask: np.ndarray  # (H, W) uint8 label map (index into class_names)
    class_names: tuple[str, ...]


LUT_LEVELS = 16384  # linear steps of the encoding table: < 1 output level apart even near black


def _srgb(x: np.ndarray) -> np.ndarray:
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


_LUT = np.round(_srgb(np.linspace(0.0, 1.0, LUT_LEVELS)) * 255.0).astype(np.uint8)


def srgb_encode(linear: np.ndarray, scale: Sequence[float] | float = 1.0) -> np.ndarray:
    """Linear values × ``scale`` (per channel), clipped to 0..1, to 8-bit sRGB (IEC 61966-2-1
    transfer function), through a table of :data:`LUT_LEVELS` linear steps (the exact curve
    costs 10x more per pixel)."""
    buf = np.multiply(np.asarray(linear, dtype=np.float32), np.asarray(scale, dtype=np.float32)
                      * np.float32(LUT_LEVELS - 1))
    buf += np.float32(0.5)
    np.clip(buf, 0, LUT_LEVELS - 1, out=buf)
    return _LUT[buf.astype(np.uint16)]


def linear_image(shaded: Shaded, albedo: np.ndarray, specular: np.ndarray, light: Sequence[float],
                 exposure: float) -> np.ndarray:
    """(H, W, 3) float32 linear image of ``shaded`` lit with RGB ``light`` (module docstring)."""
    base = _white(shaded, albedo, specular, exposure)
    return base * np.asarray(light, dtype=np.float32)


def _white(shaded: Shaded, albedo: np.ndarray, specular: np.ndarray, exposure: float) -> np.ndarray:
    """The view under white light: every other light colour is a per-channel scale of it."""
    lab = shaded.label
    e = np.float32(exposure)
    alb = (np.asarray(albedo, dtype=np.float32) * e)[lab]  # (H, W, 3)
    alb *= shaded.diffuse[..., None]
    alb += (np.asarray(specular, dtype=np.float32) * e)[lab] * shaded.specular[..., None]
    return alb


def auto_exposure(shaded: Shaded, quantile: float = 0.99) -> float:
    """An exposure putting the ``quantile`` of the mockup's white-lit irradiance at 1: fixed
    once per session so every view and band shares one scale, as one Blender camera does."""
    fg = shaded.diffuse[shaded.label > 0]
    ref = float(np.quantile(fg, quantile)) if fg.size else float(shaded.diffuse.max())
    return 1.0 / max(ref, 1e-6)


def render_view(shaded: Shaded, albedo: np.ndarray, specular: np.ndarray, band_lights: np.ndarray,
                exposure: float) -> SyntheticView:
    """The RGB render and one render per row of ``band_lights`` ((n_bands, 3) RGB colours)."""
    n = len(shaded.mount.class_names)
    if np.shape(albedo) != (n, 3) or np.shape(specular) != (n, 3):
        raise ValueError(f"albedo and specular must be ({n}, 3) for {n} labels, got "
                         f"{np.shape(albedo)} and {np.shape(specular)}")
    white = _white(shaded, albedo, specular, exposure)
    rgb = srgb_encode(white)
    bands = tuple(srgb_encode(white, c) for c in band_lights)
    return SyntheticView(rgb=rgb, bands=bands, mask=np.array(shaded.label, dtype=np.uint8),
                         class_names=tuple(shaded.mount.class_names))
