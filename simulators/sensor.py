"""The TOUCAN's image sensor: MSFA sampling, exposure, gain, noise, dark signal, 10-bit ADC.

Model per pixel (electrons ``e``, DN = digital numbers):

    e      = rate · t  +  dark(x, y) · t · 2^((T − T_ref) / doubling)        (mean)
    e_obs  = e + √(e + σ_read²) · N(0, 1)       (shot noise of signal and dark, Gaussian
                                                   approximation of Poisson, plus read noise)
    DN     = round(e_obs · gain / e_per_dn + offset(x, y)), clipped to 0 … full scale;
             a pixel whose mean charge reaches the full well reads full scale.

``rate`` is the signal in electrons per second at each pixel — the scene sampled
through that pixel's band (the MSFA) and converted with :attr:`Sensor.band_gain`.
``dark`` is a seeded fixed pattern (lognormal around the mean dark current, plus a
fixed set of hot pixels far above it); ``offset`` is the black level plus a seeded
fixed-pattern offset (DSNU). Defaults follow a CMV4000-class 5.5 µm global-shutter
sensor read out at 10 bits; they are assumptions, kept in :class:`SensorParams`.

Speed: a frame at 65 frames/s leaves 15 ms. Normal deviates come from a pool drawn
once and read at a random offset (and random sign) per frame; the whole per-pixel
chain is one compiled loop that releases the GIL and runs on row bands in parallel.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from m2s2hil.simulators.materials import GRID_NM, band_average
from m2s2hil.simulators.raster import split_rows
from numba import njit


@dataclass(frozen=True)
class SensorParams:
    """Sensor parameters. Electrons (e) and DN at gain 1 unless stated."""

    full_well_e: float = 13500.0
    e_per_dn: float = 13.2  # conversion: electrons per DN at gain 1 (full well ≈ 10-bit full scale)
    # Electrons per second per unit of relative radiance at QE 1 (optics, f-number, pixel
    # area folded in): a white diffuse part under the strong preset fills ~60 % of the
    # range at 5 ms.
    signal_e_per_s: float = 2.8e6
    # Quantum efficiency curve (CMV4000-like, with microlenses), averaged over each band.
    qe_nm: tuple[float, ...] = (350, 400, 450, 500, 550, 600, 650, 700, 750, 800, 850, 900, 950, 1050)
    qe: tuple[float, ...] = (
        0.10, 0.30, 0.45, 0.55, 0.60, 0.58, 0.52, 0.45, 0.37, 0.30, 0.22, 0.15, 0.09, 0.02
    )
    read_noise_e: float = 13.0
    black_level_dn: float = 12.0
    dsnu_dn: float = 1.0  # σ of the fixed-pattern offset around the black level
    dark_current_e_per_s: float = 125.0  # mean, at dark_ref_temp_c
    dark_ref_temp_c: float = 25.0
    dark_doubling_c: float = 6.5  # dark current doubles every this many °C
    dark_nonuniformity: float = 0.3  # σ of log(per-pixel dark current)
    hot_pixel_fraction: float = 2e-4
    hot_pixel_e_per_s: float = 2.0e4  # median dark current of a hot pixel at dark_ref_temp_c
    hot_pixel_spread: float = 0.8  # σ of log(hot-pixel dark current)
    noise_pool_extra: int = 1 << 20  # normal deviates beyond one frame: room for random offsets

    def __post_init__(self) -> None:
        for name in ("full_well_e", "e_per_dn", "signal_e_per_s", "dark_doubling_c"):
            if not getattr(self, name) > 0:
                raise ValueError(f"SensorParams.{name} must be > 0, got {getattr(self, name)}")
        for name in ("read_noise_e", "dsnu_dn", "dark_current_e_per_s", "dark_nonuniformity",
                     "hot_pixel_e_per_s", "hot_pixel_spread", "black_level_dn"):
            if getattr(self, name) < 0:
                raise ValueError(f"SensorParams.{name} must be >= 0, got {getattr(self, name)}")
        if not 0 <= self.hot_pixel_fraction < 1:
            raise ValueError(
                f"SensorParams.hot_pixel_fraction must be in [0, 1), got {self.hot_pixel_fraction}"
            )
        if len(self.qe_nm) != len(self.qe) or len(self.qe) < 2:
            raise ValueError("SensorParams.qe_nm and .qe must be curves of equal length (>= 2 points)")
        if self.noise_pool_extra < 1:
            raise ValueError("SensorParams.noise_pool_extra must be >= 1")


@njit(cache=True, nogil=True, fastmath=True)
def _expose_rows(
    rate, t_sig, has_signal, dark, t_dark, offset, pool, off, sgn, read_var, dn_per_e, full_well,
    full_scale, out, r0, r1,
):  # pragma: no cover
    w = out.shape[1]
    fs = np.float32(full_scale)
    for y in range(r0, r1):
        base = off + y * w
        for x in range(w):
            e = dark[y, x] * t_dark
            if has_signal:
                e += rate[y, x] * t_sig
            noise = sgn * pool[base + x] * math.sqrt(e + read_var)
            v = (e + noise) * dn_per_e + offset[y, x] + np.float32(0.5)
            v = min(max(v, np.float32(0.0)), fs)
            if e >= full_well:
                v = fs
            out[y, x] = np.uint16(v)


class Sensor:
    """A mosaic sensor of ``width`` × ``height`` with MSFA ``layout`` (n × n band indices)."""

    def __init__(
        self, width: int, height: int, layout: Sequence[Sequence[int]], bands_nm: Sequence[float],
        fwhm_nm: Sequence[float], full_scale: int, params: SensorParams | None = None, seed: int = 0,
        threads: int | None = None,
    ) -> None:
        self.width, self.height = int(width), int(height)
        self.layout = np.asarray(layout, dtype=np.int64)
        n = self.layout.shape[0]
        if self.layout.ndim != 2 or self.layout.shape != (n, n) or n == 0:
            raise ValueError(f"MSFA layout must be a square n x n array, got shape {self.layout.shape}")
        if self.width % n or self.height % n:
            raise ValueError(
                f"sensor {self.width}x{self.height} is not a multiple of the {n}x{n} MSFA period"
            )
        self.full_scale = int(full_scale)
        self.params = p = params or SensorParams()
        self.threads = threads
        qe_curve = np.interp(GRID_NM, np.asarray(p.qe_nm, float), np.asarray(p.qe, float), left=0, right=0)
        #: QE averaged over each band's Gaussian response
        self.band_qe = band_average(qe_curve, bands_nm, fwhm_nm)
        #: electrons/s per unit relative radiance, per band
        self.band_gain = self.band_qe * p.signal_e_per_s
        rng = np.random.default_rng(seed)
        h, w = self.height, self.width
        self.offset_dn = (p.black_level_dn + p.dsnu_dn * rng.standard_normal((h, w))).astype(np.float32)
        sig = p.dark_nonuniformity
        dark = p.dark_current_e_per_s * np.exp(sig * rng.standard_normal((h, w)) - 0.5 * sig * sig)
        n_hot = round(p.hot_pixel_fraction * h * w)
        self.hot_pixels = np.sort(rng.choice(h * w, size=n_hot, replace=False)) if n_hot else np.zeros(0, int)
        hot = p.hot_pixel_e_per_s * np.exp(p.hot_pixel_spread * rng.standard_normal(n_hot))
        dark.flat[self.hot_pixels] = hot
        self.dark_e_per_s = dark.astype(np.float32)  # at dark_ref_temp_c
        self._pool = rng.standard_normal(h * w + p.noise_pool_extra, dtype=np.float32)
        self._rng = rng
        self._zero = np.zeros((1, 1), dtype=np.float32)

    # -- conversions -------------------------------------------------------------------
    def band_map(self) -> np.ndarray:
        """(H, W) band index seen by each pixel."""
        n = self.layout.shape[0]
        return np.tile(self.layout, (self.height // n, self.width // n))

    def dn_per_e(self, gain: float) -> float:
        return gain / self.params.e_per_dn

    def dark_factor(self, temperature_c: float) -> float:
        p = self.params
        return 2.0 ** ((temperature_c - p.dark_ref_temp_c) / p.dark_doubling_c)

    def expected_dark_dn(self, exposure_s: float, gain: float, temperature_c: float) -> np.ndarray:
        """Mean dark frame (DN, float32, unclipped): offset + dark current over the exposure."""
        e = self.dark_e_per_s * np.float32(exposure_s * self.dark_factor(temperature_c))
        return self.offset_dn + e * np.float32(self.dn_per_e(gain))

    # -- exposure ----------------------------------------------------------------------
    def expose(
        self, rate_e_per_s: np.ndarray | None, exposure_s: float, gain: float = 1.0,
        temperature_c: float = 25.0, out: np.ndarray | None = None,
    ) -> np.ndarray:
        """One raw frame (uint16 H×W). ``rate_e_per_s`` None = no light (lens cap / dark frame)."""
        if not (math.isfinite(exposure_s) and exposure_s > 0):
            raise ValueError(f"exposure must be a positive number of seconds, got {exposure_s!r}")
        if not (math.isfinite(gain) and gain > 0):
            raise ValueError(f"gain must be a positive factor, got {gain!r}")
        if not math.isfinite(temperature_c):
            raise ValueError(f"sensor temperature must be finite, got {temperature_c!r}")
        h, w = self.height, self.width
        if rate_e_per_s is None:
            rate, has = self._zero, False
        else:
            if rate_e_per_s.shape != (h, w):
                raise ValueError(f"signal is {rate_e_per_s.shape}, sensor is {(h, w)}")
            rate, has = np.ascontiguousarray(rate_e_per_s, dtype=np.float32), True
        if rate.flags.writeable:  # read-only always (the kernel only reads it): one numba specialisation
            rate = rate.view()
            rate.flags.writeable = False
        if out is None:
            out = np.empty((h, w), dtype=np.uint16)
        p = self.params
        off = int(self._rng.integers(0, p.noise_pool_extra))
        sgn = np.float32(1.0 if self._rng.random() < 0.5 else -1.0)
        t_dark = np.float32(exposure_s * self.dark_factor(temperature_c))
        args = (
            np.float32(exposure_s), has, self.dark_e_per_s, t_dark, self.offset_dn, self._pool, off, sgn,
            np.float32(p.read_noise_e**2), np.float32(self.dn_per_e(gain)), np.float32(p.full_well_e),
            self.full_scale, out,
        )
        split_rows(lambda r0, r1: _expose_rows(rate, *args, r0, r1), h, self.threads)
        return out


def sensor_params_from(values: dict | None) -> SensorParams:
    """SensorParams from a plain mapping (e.g. a rig file's ``[simulation.sensor]`` table).

    Unknown keys raise KeyError naming the key; bad values raise ValueError.
    """
    if not values:
        return SensorParams()
    known = set(SensorParams.__dataclass_fields__)
    unknown = sorted(set(values) - known)
    if unknown:
        raise KeyError(f"unknown sensor parameter(s) {unknown}; known: {sorted(known)}")
    conv = {k: tuple(float(x) for x in v) if isinstance(v, list | tuple) else v for k, v in values.items()}
    return SensorParams(**conv)
