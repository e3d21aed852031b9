"""Ground-truth cubes for judging demosaicing, built offline from data that PyPI packages ship.

- Spectra: colour-science's ColorChecker (N. Ohta, 380–780 nm; held constant beyond 780 nm, so
  the 820/877 nm bands of those scenes carry no new information) and earthlib's measured
  library (400–2450 nm; held constant below 400 nm, reaching every TOUCAN band). earthlib
  materials: one representative per class (the member closest to the class median).
- Spatial structure: scikit-image's sample pictures. Each pixel's colour is softly assigned to
  the nearest anchor colours (the ColorChecker patches' own sRGB colours, or the picture's k-means
  colour clusters for earthlib materials); its spectrum is the weighted mix of the anchors'
  spectra, scaled so its luminance follows the picture's. Texture and edges therefore come from
  a real photograph, spectra from real measurements.
- Band values: the spectrum × a 3000 K blackbody (halogen-like) integrated against Gaussian band
  responses (centre and FWHM from the camera model), scaled so the scene's maximum is 90 % of
  full scale. The cube is noise-free radiance in DN; ``mosaic_of`` samples and quantises it.
- Stress scenes for the stability study: a Siemens star of one material (any spectral angle in
  the output is a demosaicing artefact) and a two-material star (spectral edges).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING, Any

import numpy as np

from m2s2hil.processing.errors import ProcessingError
from m2s2hil.processing.mosaic import MosaicLayout, sample_cube

if TYPE_CHECKING:
    from m2s2hil.config import RigConfig

WAVELENGTHS = np.arange(340.0, 961.0, 1.0)  # nm; covers every band ± 2.5 FWHM
EARTHLIB_CLASSES = ("paint", "metal", "canopy", "soil", "tile", "bark", "glass", "asphalt")


def _analysis_extra(module: str) -> Any:
    """colour-science and earthlib come with the ``analysis`` extra, not with a capture install."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise ProcessingError(
            f"the ground-truth scenes need {module!r}, which is not installed: "
            "pip install 'm2s2hil[analysis]'"
        ) from None


@dataclass
class Scene:
    name: str
    cube: np.ndarray  # float32 (bands, H, W), noise-free radiance in DN
    description: str


def band_responses(model, wl: np.ndarray = WAVELENGTHS) -> np.ndarray:
    """(bands, λ) Gaussian spectral responses from the camera model, each summing to 1."""
    centres = np.asarray(model.bands_nm, dtype=np.float64)[:, None]
    sigma = np.asarray(model.fwhm_nm, dtype=np.float64)[:, None] / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    srf = np.exp(-0.5 * ((wl[None, :] - centres) / sigma) ** 2)
    return srf / srf.sum(axis=1, keepdims=True)


def blackbody(wl: np.ndarray = WAVELENGTHS, temperature_k: float = 3000.0) -> np.ndarray:
    colour = _analysis_extra("colour")

    shape = colour.SpectralShape(float(wl[0]), float(wl[-1]), float(wl[1] - wl[0]))
    spd = colour.sd_blackbody(temperature_k, shape).values
    return spd / spd.max()


@lru_cache(maxsize=1)
def colorchecker_spectra(
    wl_key: tuple[float, float, float] = (340.0, 960.0, 1.0),
) -> tuple[np.ndarray, list[str]]:
    """(24, λ) reflectances of the ColorChecker (N. Ohta), held constant outside 380–780 nm."""
    colour = _analysis_extra("colour")

    wl = np.arange(wl_key[0], wl_key[1] + 1e-9, wl_key[2])
    sds = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]
    names = list(sds)
    refl = np.array([np.interp(wl, sds[k].wavelengths, sds[k].values) for k in names])
    return refl, names


@lru_cache(maxsize=1)
def earthlib_spectra(classes: tuple[str, ...] = EARTHLIB_CLASSES) -> tuple[np.ndarray, list[str]]:
    """(K, λ) one measured reflectance per earthlib class, resampled to ``WAVELENGTHS``."""
    earthlib = _analysis_extra("earthlib")

    lib = earthlib.full_library
    wl_lib = np.asarray(lib.sensor.band_centers, dtype=np.float64) * 1000.0  # µm → nm
    data = np.asarray(lib.data, dtype=np.float64)
    level3 = lib.metadata["LEVEL_3"].to_numpy()
    keep = wl_lib <= WAVELENGTHS[-1] + 20
    out, names = [], []
    for cls in classes:
        rows = data[level3 == cls][:, keep]
        if len(rows) == 0:
            raise ValueError(f"earthlib has no class {cls!r}")
        med = np.median(rows, axis=0)
        best = rows[np.argmin(np.abs(rows - med).sum(axis=1))]
        out.append(np.clip(np.interp(WAVELENGTHS, wl_lib[keep], best), 0.0, None))
        names.append(cls)
    return np.array(out), names


def spectra_srgb(refl: np.ndarray, wl: np.ndarray = WAVELENGTHS) -> np.ndarray:
    """(K, 3) linear sRGB of reflectances under D65 (the ColorChecker patches' own colours)."""
    colour = _analysis_extra("colour")

    rgb = []
    for r in refl:
        sd = colour.SpectralDistribution(dict(zip(wl, r, strict=True)))
        sd = sd.copy().trim(colour.SpectralShape(380, 780, 1))
        xyz = colour.sd_to_XYZ(sd, illuminant=colour.SDS_ILLUMINANTS["D65"]) / 100.0
        rgb.append(colour.XYZ_to_sRGB(xyz, apply_cctf_encoding=False))
    return np.clip(np.array(rgb), 1e-4, None)


def picture(name: str) -> np.ndarray:
    """A scikit-image sample picture as linear RGB floats in [0, 1]."""
    import skimage.data

    img = getattr(skimage.data, name)()
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    srgb = img[..., :3].astype(np.float64) / 255.0
    return np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)  # sRGB decoding


_LUMA = np.array([0.2126, 0.7152, 0.0722])


def spectral_scene(
    rgb: np.ndarray, band_values: np.ndarray, anchor_rgb: np.ndarray, *, sigma: float = 0.04, top: int = 3
) -> np.ndarray:
    """(bands, H, W) cube: each pixel mixes the anchors nearest in chromaticity, shaded by its luminance.

    ``band_values`` is (K, bands): the band signals of the K anchor spectra; ``anchor_rgb`` (K, 3).
    """
    eps = 1e-6
    chroma = rgb / (rgb.sum(axis=2, keepdims=True) + eps)
    a_chroma = anchor_rgb / anchor_rgb.sum(axis=1, keepdims=True)
    d2 = ((chroma[:, :, None, :2] - a_chroma[None, None, :, :2]) ** 2).sum(axis=3)  # (H, W, K)
    order = np.argsort(d2, axis=2)
    cut = np.take_along_axis(d2, order[:, :, top - 1 : top], axis=2)
    wts = np.exp(-0.5 * d2 / sigma**2) * (d2 <= cut)
    wts /= wts.sum(axis=2, keepdims=True) + 1e-300
    wts = np.where(np.isfinite(wts), wts, 0.0)
    lum = rgb @ _LUMA
    a_lum = anchor_rgb @ _LUMA
    shade = lum / (wts @ a_lum + eps)
    cube = (wts @ band_values) * shade[:, :, None]  # (H, W, bands)
    return np.ascontiguousarray(cube.transpose(2, 0, 1))


def _to_dn(cube: np.ndarray, full_scale: int, level: float = 0.9) -> np.ndarray:
    return (cube * (level * full_scale / cube.max())).astype(np.float32)


def _crop(img: np.ndarray, n: int, size: int | None) -> np.ndarray:
    h, w = img.shape[:2]
    if size is not None:
        h, w = min(h, size), min(w, size)
    h, w = h - h % n, w - w % n
    return img[:h, :w]


def colorchecker_scene(model, picture_name: str, *, size: int | None = None) -> Scene:
    refl, _ = colorchecker_spectra()
    light = blackbody()
    bands = (refl * light) @ band_responses(model).T  # (24, bands)
    rgb = _crop(picture(picture_name), len(model.layout), size)
    cube = spectral_scene(rgb, bands, spectra_srgb(refl))
    return Scene(
        f"colorchecker/{picture_name}",
        _to_dn(cube, model.full_scale),
        f"ColorChecker spectra (colour-science) on skimage '{picture_name}' {rgb.shape[1]}×{rgb.shape[0]}",
    )


def earthlib_scene(model, picture_name: str, *, size: int | None = None, seed: int = 0) -> Scene:
    from sklearn.cluster import KMeans

    refl, names = earthlib_spectra()
    light = blackbody()
    bands = (refl * light) @ band_responses(model).T  # (K, bands)
    rgb = _crop(picture(picture_name), len(model.layout), size)
    flat = rgb.reshape(-1, 3)
    sample = flat[np.random.default_rng(seed).choice(len(flat), size=min(len(flat), 20000), replace=False)]
    km = KMeans(n_clusters=len(names), n_init=4, random_state=seed).fit(sample)
    anchors = np.clip(km.cluster_centers_, 1e-4, None)
    cube = spectral_scene(rgb, bands, anchors)
    return Scene(
        f"earthlib/{picture_name}",
        _to_dn(cube, model.full_scale),
        f"earthlib spectra ({', '.join(names)}) on skimage '{picture_name}' {rgb.shape[1]}×{rgb.shape[0]}",
    )


def simulator_scene(
    model,
    satellite: str = "voyager",
    build: str = "B3",
    *,
    azimuth_deg: float = 30.0,
    tilt_deg: float = 0.0,
    size: int = 512,
    seed: int = 1,
    rig: RigConfig | None = None,
) -> Scene:
    """The simulated TOUCAN's noise-free radiance (``SimFrameSource.truth().radiance()``) of a mockup
    under every lamp of ``rig`` (default: the built-in rig), rescaled to 90 % of full scale at its
    maximum (as a shorter exposure would)."""
    from m2s2hil.config import default_rig
    from m2s2hil.sim_config import build_frame_source, build_world
    from m2s2hil.simulators.clock import VirtualClock

    rig = rig or default_rig()
    cam = model.model_copy(update={"width": size, "height": size})
    clock = VirtualClock()
    world = build_world(rig, clock)
    world.mount(satellite, build)
    world.attach_axis("turntable", lambda: azimuth_deg)
    world.attach_axis("tilt", lambda: tilt_deg)
    for lamp in rig.lamps.values():
        world.set_lamp(lamp.channel, True)
    clock.advance(max((lamp.warmup_s for lamp in rig.lamps.values()), default=0.0) + 1.0)  # past warm-up
    src = build_frame_source(rig, world, seed=seed, model=cam)
    src.capture(0.01, 1.0)
    cube = np.array(src.truth().radiance(), dtype=np.float32)
    return Scene(
        f"simulator/{satellite}-{build}",
        _to_dn(cube, model.full_scale),
        f"simulated TOUCAN, {satellite} {build} at azimuth {azimuth_deg:g}°, tilt {tilt_deg:g}°, {size}²",
    )


def reference_scenes(model, *, size: int | None = None, simulator: bool = True) -> list[Scene]:
    """The accuracy set: two ColorChecker, two earthlib and (when it runs) two simulator scenes."""
    scenes = [
        colorchecker_scene(model, "astronaut", size=size),
        colorchecker_scene(model, "coffee", size=size),
        earthlib_scene(model, "rocket", size=size),
        earthlib_scene(model, "chelsea", size=size),
    ]
    if simulator:
        side = min(512, size or 512)
        scenes.append(simulator_scene(model, "voyager", "B3", azimuth_deg=30.0, size=side))
        scenes.append(simulator_scene(model, "hubble", "B1", azimuth_deg=120.0, tilt_deg=-10.0, size=side))
    return scenes


# --- stress scenes ----------------------------------------------------------------------------


def _material_bands(model, index: int = 0) -> np.ndarray:
    refl, _ = earthlib_spectra()
    return (refl[index] * blackbody()) @ band_responses(model).T


def siemens_star(model, size: int = 256, spokes: int = 48, *, two_materials: bool = False) -> Scene:
    """A star whose spokes get arbitrarily thin towards the centre: aliasing for every method."""
    yy, xx = np.mgrid[0:size, 0:size] - (size - 1) / 2.0
    theta = np.arctan2(yy, xx)
    pattern = 0.5 + 0.5 * np.cos(spokes * theta)  # smooth spokes, no step to alias from the pattern itself
    a = _material_bands(model, 0)
    if two_materials:
        b = _material_bands(model, 2)  # paint vs vegetation: very different spectra
        cube = a[:, None, None] * pattern + b[:, None, None] * (1.0 - pattern) * (a.sum() / b.sum())
        label = "two-material"
    else:
        cube = a[:, None, None] * (0.15 + 0.85 * pattern)
        label = "one-material"
    return Scene(
        f"star/{label}", _to_dn(cube, model.full_scale), f"{label} Siemens star, {spokes} spokes, {size}²"
    )


def mosaic_of(
    scene_cube: np.ndarray,
    layout: MosaicLayout,
    full_scale: int,
    *,
    offset: tuple[int, int] = (0, 0),
    gain_dn_per_e: float | None = None,
    read_noise_dn: float = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """Sample a radiance cube through the MSFA, optionally with shot + read noise, then quantise (uint16)."""
    m: np.ndarray = sample_cube(scene_cube, layout, offset=offset, dtype=None).astype(np.float64)
    rng = np.random.default_rng(seed)
    if gain_dn_per_e:
        m = rng.poisson(np.clip(m, 0, None) / gain_dn_per_e) * gain_dn_per_e
    if read_noise_dn:
        m = m + rng.normal(0.0, read_noise_dn, m.shape)
    return np.clip(np.rint(m), 0, full_scale).astype(np.uint16)


def synthetic_scene(model, size: int = 128, *, seed: int = 0, level: float = 0.9) -> Scene:
    """A scene without external data (tests, quick benchmarks): smooth shading, random discs and a
    fine texture, each region with its own random spectrum (band levels) and a sensor-like tilt of
    band levels so the bands differ on average, as in a raw frame."""
    rng = np.random.default_rng(seed)
    nb = model.n_bands
    n = len(model.layout)
    size -= size % n
    yy, xx = np.mgrid[0:size, 0:size] / size
    base = rng.uniform(0.3, 1.0, nb)
    cube = base[:, None, None] * (0.6 + 0.4 * np.sin(2.5 * xx + 1.3 * yy))[None]
    for _ in range(6):
        cy, cx, r = rng.uniform(0.15, 0.85), rng.uniform(0.15, 0.85), rng.uniform(0.06, 0.2)
        disc = (yy - cy) ** 2 + (xx - cx) ** 2 < r * r
        cube[:, disc] = rng.uniform(0.1, 1.0, nb)[:, None] * (0.8 + 0.2 * xx[disc])[None]
    cube *= 1.0 + 0.05 * np.sin(40.0 * xx)[None] * np.cos(33.0 * yy)[None]  # texture at ~1/8 cycles/px
    cube *= np.linspace(0.35, 1.0, nb)[:, None, None]  # bands differ in level like a raw frame
    return Scene(
        f"synthetic/{seed}", _to_dn(cube, model.full_scale, level), f"synthetic {size}², seed {seed}"
    )
