"""The RGB baseline: what an RGB camera would see of the scene, and the paper's wavelength→RGB map.

**Camera rendering** (``camera_rgb``, the default of the ``rgb`` and ``sam-rgb`` segmenters):
the image a colour camera behind an IR-cut filter would record, as a Luther-condition camera
(its channels are linear combinations of the CIE 1931 colour-matching functions) reporting
linear sRGB:

1. the scene spectrum is rebuilt from the band values by linear interpolation between the
   band centres (each band a hat function peaking at its centre; constant below the first and
   above the last centre);
2. an IR-cut filter passes λ ≤ ``ir_cut_nm`` (700 nm by default, a typical hot-mirror edge)
   and nothing above;
3. X, Y, Z = ∫ spectrum · x̄, ȳ, z̄ dλ over 380–780 nm with the CIE 1931 2° observer
   (``cie1931``: the CIE table every 5 nm, linearly interpolated to 1 nm);
4. linear sRGB = M · XYZ (IEC 61966-2-1), each channel scaled so an equal-energy spectrum
   gives R = G = B = its value (keeps the cube's intensity scale), negative values (colours
   outside the sRGB gamut) clipped to 0 as a camera's output is.

So the result is one fixed ``(bands, 3)`` weight matrix (``camera_weights``); with the TOUCAN
bands and the 700 nm cut, bands at or above 775 nm get weight 0 (they used to supply 22.7 % of
the red channel) and 719 nm only its share below 700 nm. Band values are taken as the radiance
in the band: the TOUCAN's own per-band quantum efficiency and the lamp spectrum are not divided
out (a white-referenced cube has them removed already). This is an assumption of this project,
not the paper's method: the paper's RGB images are Blender renders.

**Bruton rendering** (``render_rgb``, the ``rgb-nir`` segmenter, named for what it does): the
paper's approximation of each band's colour for its synthetic split, the classic Bruton
mapping with γ = 0.8. Piecewise-linear ramps, λ in nm:

    380–440: R = (440−λ)/60, G = 0,            B = 1
    440–490: R = 0,          G = (λ−440)/50,   B = 1
    490–510: R = 0,          G = 1,            B = (510−λ)/20
    510–580: R = (λ−510)/70, G = 1,            B = 0
    580–645: R = 1,          G = (645−λ)/65,   B = 0
    645–780: R = 1,          G = 0,            B = 0

Intensity factor: 0.3 + 0.7·(λ−380)/40 below 420 nm, 0.3 + 0.7·(780−λ)/80 above
700 nm, 1 in between. Each channel = (factor·c)^γ (0 stays 0). Near infrared (820 and
877 nm, where Bruton returns black): ``nir="clamp"`` (default) gives them the colour of
780 nm, a dark red R = 0.3^γ ≈ 0.382 — this feeds near-infrared signal into the red channel,
which no IR-cut camera sees, hence the separate name ``rgb-nir``. ``nir="black"`` is
Bruton's original. Each channel is the colour-weighted mean of the bands
(``rgb_c = Σ_b w_bc·x_b / Σ_b w_bc``).

``RgbBaseline`` segments either rendering with any segmenter, making RGB vs multispectral a
comparison of inputs with the same segmenter family.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from m2s2hil.analysis.arrays import as_cube
from m2s2hil.analysis.cie1931 import XYZ_TO_LINEAR_SRGB, cmf_table
from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.config import CameraModel

if TYPE_CHECKING:  # the registry builds RgbBaseline, so it cannot be imported from here at run time
    from m2s2hil.analysis.segmenters.registry import Segmenter

NirRule = Literal["clamp", "black"]
Rendering = Literal["camera", "bruton"]
DEFAULT_GAMMA = 0.8
DEFAULT_IR_CUT_NM = 700.0
TOUCAN_BANDS_NM: tuple[float, ...] = tuple(CameraModel().bands_nm)


def _ramps(lam: float) -> tuple[float, float, float]:
    if lam < 440:
        return (440 - lam) / 60, 0.0, 1.0
    if lam < 490:
        return 0.0, (lam - 440) / 50, 1.0
    if lam < 510:
        return 0.0, 1.0, (510 - lam) / 20
    if lam < 580:
        return (lam - 510) / 70, 1.0, 0.0
    if lam < 645:
        return 1.0, (645 - lam) / 65, 0.0
    return 1.0, 0.0, 0.0


def _factor(lam: float) -> float:
    if lam < 420:
        return 0.3 + 0.7 * (lam - 380) / 40
    if lam > 700:
        return 0.3 + 0.7 * (780 - lam) / 80
    return 1.0


def wavelength_to_rgb(wavelength_nm: float, gamma: float = DEFAULT_GAMMA,
                      nir: NirRule = "clamp") -> tuple[float, float, float]:
    """(R, G, B) in [0, 1] of one wavelength (see module docstring for the rule outside 380–780 nm)."""
    lam = float(wavelength_nm)
    if not np.isfinite(lam) or lam <= 0:
        raise AnalysisInputError("wavelength_nm", f"must be a positive number of nm, got {wavelength_nm!r}")
    if gamma <= 0:
        raise AnalysisInputError("gamma", f"must be > 0, got {gamma!r}")
    if nir not in ("clamp", "black"):
        raise AnalysisInputError("nir", f"expected 'clamp' or 'black', got {nir!r}")
    if lam < 380 or lam > 780:
        if nir == "black":
            return 0.0, 0.0, 0.0
        lam = min(max(lam, 380.0), 780.0)
    f = _factor(lam)
    return tuple(float((f * c) ** gamma) if c > 0 else 0.0 for c in _ramps(lam))  # type: ignore[return-value]


def band_colours(bands_nm: Sequence[float] = TOUCAN_BANDS_NM, gamma: float = DEFAULT_GAMMA,
                 nir: NirRule = "clamp") -> np.ndarray:
    """``(bands, 3)`` array of each band's RGB colour."""
    return np.array([wavelength_to_rgb(b, gamma, nir) for b in bands_nm], dtype=np.float64)


def render_rgb(cube: object, bands_nm: Sequence[float] = TOUCAN_BANDS_NM, gamma: float = DEFAULT_GAMMA,
               nir: NirRule = "clamp") -> np.ndarray:
    """float32 ``(3, H, W)`` RGB rendering of a ``(bands, H, W)`` cube (weighted band means)."""
    arr = as_cube(cube)
    if arr.shape[0] != len(bands_nm):
        raise AnalysisInputError("cube", f"has {arr.shape[0]} bands but {len(bands_nm)} wavelengths given")
    w = band_colours(bands_nm, gamma, nir)  # (bands, 3)
    total = w.sum(axis=0)
    norm = np.divide(w, total, out=np.zeros_like(w), where=total > 0).astype(np.float32)
    bands, h, wd = arr.shape
    rgb = norm.T @ arr.reshape(bands, -1)  # (3, H·W)
    return rgb.reshape(3, h, wd)


def camera_weights(
    bands_nm: Sequence[float] = TOUCAN_BANDS_NM, ir_cut_nm: float = DEFAULT_IR_CUT_NM
) -> np.ndarray:
    """``(bands, 3)`` weights from band values to linear sRGB of an IR-cut camera (module docstring)."""
    nm = np.asarray(bands_nm, dtype=np.float64)
    if nm.ndim != 1 or nm.size == 0 or not np.all(np.isfinite(nm)) or np.any(nm <= 0):
        raise AnalysisInputError("bands_nm", f"expected positive band centres in nm, got {bands_nm!r}")
    if len(set(nm.tolist())) != nm.size:
        raise AnalysisInputError("bands_nm", f"band centres must differ, got {bands_nm!r}")
    if not 380.0 < ir_cut_nm <= 780.0:
        raise AnalysisInputError("ir_cut_nm", f"must lie in (380, 780] nm, got {ir_cut_nm!r}")
    table_nm, cmf = cmf_table()
    lam = np.arange(380.0, 781.0, 1.0)
    xyz_bar = np.stack([np.interp(lam, table_nm, cmf[:, i]) for i in range(3)], axis=1)
    xyz_bar[lam > ir_cut_nm] = 0.0
    order = np.argsort(nm)
    hats = np.zeros((nm.size, lam.size))
    for k, b in enumerate(order):  # hat k: 1 at its centre, 0 at the neighbouring centres
        unit = np.zeros(nm.size)
        unit[k] = 1.0
        hats[b] = np.interp(lam, nm[order], unit)  # np.interp holds the end values outside
    xyz_w = hats @ xyz_bar  # (bands, 3): XYZ per unit band value (1 nm steps)
    rgb_w = xyz_w @ XYZ_TO_LINEAR_SRGB.T
    total = rgb_w.sum(axis=0)
    if np.any(total <= 0):
        raise AnalysisInputError("bands_nm", f"bands {bands_nm!r} leave an sRGB channel without light")
    return rgb_w / total


@functools.lru_cache(maxsize=16)
def _weights32(bands_nm: tuple[float, ...], ir_cut_nm: float) -> np.ndarray:
    w = camera_weights(bands_nm, ir_cut_nm).astype(np.float32)
    w.flags.writeable = False
    return w


def camera_rgb(cube: object, bands_nm: Sequence[float] = TOUCAN_BANDS_NM,
               ir_cut_nm: float = DEFAULT_IR_CUT_NM) -> np.ndarray:
    """float32 ``(3, H, W)`` linear sRGB an IR-cut colour camera would record (module docstring)."""
    arr = as_cube(cube)
    if arr.shape[0] != len(bands_nm):
        raise AnalysisInputError("cube", f"has {arr.shape[0]} bands but {len(bands_nm)} wavelengths given")
    w = _weights32(tuple(float(b) for b in bands_nm), float(ir_cut_nm))
    bands, h, wd = arr.shape
    rgb = w.T @ arr.reshape(bands, -1)
    return np.maximum(rgb, 0.0).reshape(3, h, wd)


class RgbBaseline:
    """Render the cube to RGB (``rendering="camera"``: ``camera_rgb``; ``"bruton"``: ``render_rgb``)
    and segment that with ``segmenter``. ``gamma`` and ``nir`` belong to the Bruton rendering,
    ``ir_cut_nm`` to the camera one; giving one to the other rendering is an error."""

    def __init__(self, segmenter: Segmenter, bands_nm: Sequence[float] = TOUCAN_BANDS_NM,
                 gamma: float | None = None, nir: NirRule | None = None, *,
                 rendering: Rendering = "camera", ir_cut_nm: float | None = None) -> None:
        if not callable(getattr(segmenter, "segment", None)):
            raise AnalysisInputError("segmenter", f"{segmenter!r} has no segment(cube) method")
        if rendering not in ("camera", "bruton"):
            raise AnalysisInputError("rendering", f"expected 'camera' or 'bruton', got {rendering!r}")
        if rendering == "camera" and (gamma is not None or nir is not None):
            raise AnalysisInputError("rendering", "gamma and nir belong to the Bruton rendering "
                                     "(segmenter 'rgb-nir'); the camera rendering has neither")
        if rendering == "bruton" and ir_cut_nm is not None:
            raise AnalysisInputError("ir_cut_nm", "the Bruton rendering has no IR cut (use 'rgb')")
        self.segmenter = segmenter
        self.bands_nm = tuple(float(b) for b in bands_nm)
        self.rendering: Rendering = rendering
        self.gamma = DEFAULT_GAMMA if gamma is None else float(gamma)
        self.nir: NirRule = "clamp" if nir is None else nir
        self.ir_cut_nm = DEFAULT_IR_CUT_NM if ir_cut_nm is None else float(ir_cut_nm)
        # validate now, not at the first image (and cache the weights ``camera_rgb`` uses)
        if rendering == "camera":
            _weights32(self.bands_nm, self.ir_cut_nm)
        else:
            band_colours(self.bands_nm, self.gamma, self.nir)
        prefix = "rgb" if rendering == "camera" else "rgb-nir"
        self.name = f"{prefix}-{getattr(segmenter, 'name', type(segmenter).__name__)}"

    def render(self, cube: np.ndarray) -> np.ndarray:
        if self.rendering == "camera":
            return camera_rgb(cube, self.bands_nm, self.ir_cut_nm)
        return render_rgb(cube, self.bands_nm, self.gamma, self.nir)

    def segment(self, cube: np.ndarray) -> np.ndarray:
        """The inner segmenter on the rendering. It takes no clipping mask (``segmenters.masks``):
        an RGB value mixes the bands with weights of both signs, so a clipped band bounds it
        neither above nor below, and a per-pixel flag with no bound to test only takes pixels out
        of the fit (the saturation study's RGB Dice fell from 0.60 to 0.34 with it,
        docs/evaluation.md, eleventh pass). An RGB camera knows only its own channels' clipping,
        which the inner segmenter's plateau test finds on the rendering."""
        return self.segmenter.segment(self.render(cube))

    def fit(self, cubes: Iterable[object]) -> Any:
        """A sweep segmenter inside (``segmenters.sweep``): fitted on the sweep's RGB renderings."""
        fit = getattr(self.segmenter, "fit", None)
        if not callable(fit):
            raise AnalysisInputError("segmenter", f"{self.segmenter!r} is not fitted on a sweep")
        return fit(self.render(as_cube(c)) for c in cubes)

    def use(self, model: Any) -> None:
        """A sweep segmenter inside: label with the ``model`` its ``fit`` returned."""
        use = getattr(self.segmenter, "use", None)
        if not callable(use):
            raise AnalysisInputError("segmenter", f"{self.segmenter!r} is not fitted on a sweep")
        use(model)
