"""Lamps and shading: LED bars and the spotlight as directional sources, Lambert + Blinn-Phong.

Camera frame: x right, y up, z towards the camera (the view vector is +z). A lamp is
a direction (unit vector from the mockup towards the lamp) and an irradiance relative
to a surface facing it at full output. The LED bars are broad sources: no shadows,
a room-bounce ambient term, and a broadened specular lobe; the spotlight is a point
source far away: hard shadows from a shadow map and the full specular lobe.

The shader writes, per pixel, the diffuse irradiance ``D``, the specular factor ``S``
and, for the pixel's own mosaic band ``b``, the signal rate
``band_gain[b] · (rho[label, b] · D + spec[label, b] · S)``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from m2s2hil.simulators.raster import split_rows
from numba import njit


@dataclass(frozen=True)
class LightingParams:
    """Where the lamps are and how strong they are (assumptions; configurable).

    Directions are (azimuth from the camera axis about the vertical, positive to the
    camera's right; elevation), degrees. LED bar channels are placed on ``bar_dirs`` in
    ascending channel order, so the weak preset (3 bars) lights from left, right and
    above and the strong preset adds the two sides.
    """

    bar_dirs: tuple[tuple[float, float], ...] = (
        (-40.0, 15.0), (40.0, 15.0), (0.0, 50.0), (-75.0, 0.0), (75.0, 0.0)
    )
    bar_irradiance: float = 0.30  # per bar, on a surface facing it
    bar_ambient: float = 0.04  # room bounce per lit bar
    bar_gloss: float = 0.2  # a bar's highlight: shininess scaled by this (broad source)
    spot_elevation_deg: float = 15.0  # spotlight a little above the camera's height
    spot_irradiance: float = 1.3
    spot_ambient: float = 0.02
    backdrop_factor: float = 0.5  # irradiance on the backdrop relative to a surface facing the camera
    shadow_scale: float = 0.5  # shadow-map resolution relative to the frame


def direction(az_deg: float, el_deg: float) -> np.ndarray:
    a, e = math.radians(az_deg), math.radians(el_deg)
    return np.array([math.sin(a) * math.cos(e), math.sin(e), math.cos(a) * math.cos(e)])


@dataclass(frozen=True)
class Lights:
    dirs: np.ndarray  # (K, 3) float64 unit vectors towards the lamps
    irradiance: np.ndarray  # (K,)
    gloss: np.ndarray  # (K,) shininess multiplier per light
    shadowed: np.ndarray  # (K,) bool: use the shadow map
    ambient: float
    spot_dir: np.ndarray | None = None  # direction of the (shadow-casting) spotlight
    key: tuple = field(default=(), compare=False)


def lights_from_lamps(
    lamp_output: Mapping[int, float], lamp_info: Mapping[int, Any], spot_angle_deg: float,
    params: LightingParams,
) -> Lights:
    """Turn the world's lit relay channels into directional lights.

    ``lamp_info`` maps channel → object with ``kind`` ("led_bar" | "spotlight");
    channels without info are not lamps and are ignored.
    """
    dirs, irr, gloss, shad = [], [], [], []
    ambient = 0.0
    bar_channels = sorted(ch for ch, info in lamp_info.items() if info.kind == "led_bar")
    spot = direction(spot_angle_deg, params.spot_elevation_deg)
    have_spot = False
    for ch in sorted(lamp_output):
        out = float(lamp_output[ch])
        info = lamp_info.get(ch)
        if info is None or out <= 0:
            continue
        if info.kind == "led_bar":
            slot = bar_channels.index(ch) % len(params.bar_dirs)
            dirs.append(direction(*params.bar_dirs[slot]))
            irr.append(params.bar_irradiance * out)
            gloss.append(params.bar_gloss)
            shad.append(False)
            ambient += params.bar_ambient * out
        elif info.kind == "spotlight":
            dirs.append(spot)
            irr.append(params.spot_irradiance * out)
            gloss.append(1.0)
            shad.append(True)
            ambient += params.spot_ambient * out
            have_spot = True
    key = (tuple(sorted((ch, round(float(v), 3)) for ch, v in lamp_output.items())), round(spot_angle_deg, 3))
    return Lights(
        dirs=np.array(dirs, dtype=np.float64).reshape(-1, 3),
        irradiance=np.array(irr, dtype=np.float64),
        gloss=np.array(gloss, dtype=np.float64),
        shadowed=np.array(shad, dtype=np.bool_),
        ambient=ambient,
        spot_dir=spot if have_spot else None,
        key=key,
    )


def light_frame(l_dir: np.ndarray) -> np.ndarray:
    """Rows (u, v, l): a rotation from the camera frame into a frame looking down ``l``."""
    l_dir = l_dir / np.linalg.norm(l_dir)
    up = np.array([0.0, 1.0, 0.0]) if abs(l_dir[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(up, l_dir)
    u /= np.linalg.norm(u)
    v = np.cross(l_dir, u)
    return np.stack([u, v, l_dir])


@njit(cache=True, nogil=True, fastmath=True)
def _shade_rows(
    label, depth, nrm, cx, cy, scale,
    ldirs, lirr, lhalf, lshadow, lexp, lnorm, ambient, bg_irr,
    smap, lmat, scx, scy, sscale, has_shadow,
    rho, spec, band_gain, layout,
    out_d, out_s, out_rate, r0, r1,
):  # pragma: no cover
    _h, w = label.shape
    n = layout.shape[0]
    nl = ldirs.shape[0]
    sh, sw = smap.shape
    for y in range(r0, r1):
        by = y % n
        bx = -1  # x % n kept as a counter: an integer division per pixel cost more than the rest
        for x in range(w):
            bx += 1
            if bx == n:
                bx = 0
            lab = label[y, x]
            b = layout[by, bx]
            if lab == 0:
                out_d[y, x] = bg_irr
                out_s[y, x] = 0.0
                out_rate[y, x] = band_gain[b] * rho[0, b] * bg_irr
                continue
            px = nrm[0, y, x]
            py = nrm[1, y, x]
            pz = nrm[2, y, x]
            norm = math.sqrt(px * px + py * py + pz * pz) + 1e-12
            px /= norm
            py /= norm
            pz /= norm
            if pz < 0.0:  # two-sided surfaces: turn the normal towards the camera
                px = -px
                py = -py
                pz = -pz
            lit_by_spot = 1.0
            if has_shadow:
                # Camera-frame point of this pixel, projected into the shadow map.
                qx = (x + 0.5 - cx) / scale
                qy = (cy - (y + 0.5)) / scale
                qz = depth[y, x]
                lx = lmat[0, 0] * qx + lmat[0, 1] * qy + lmat[0, 2] * qz
                ly = lmat[1, 0] * qx + lmat[1, 1] * qy + lmat[1, 2] * qz
                lz = lmat[2, 0] * qx + lmat[2, 1] * qy + lmat[2, 2] * qz
                sxp = int(scx + lx * sscale)
                syp = int(scy - ly * sscale)
                if 0 <= sxp < sw and 0 <= syp < sh:
                    ndl = max(lmat[2, 0] * px + lmat[2, 1] * py + lmat[2, 2] * pz, 0.05)
                    bias = (1.5 + 2.0 * math.sqrt(max(0.0, 1.0 - ndl * ndl)) / ndl) / sscale
                    if lz < smap[syp, sxp] - bias:
                        lit_by_spot = 0.0
            d = ambient
            s = 0.0
            for k in range(nl):
                ndl = px * ldirs[k, 0] + py * ldirs[k, 1] + pz * ldirs[k, 2]
                if ndl <= 0.0:
                    continue
                vis = lit_by_spot if lshadow[k] else 1.0
                if vis == 0.0:
                    continue
                d += lirr[k] * ndl
                # Blinn-Phong: lhalf is the unit half vector of light k and the view (0, 0, 1).
                ndh = px * lhalf[k, 0] + py * lhalf[k, 1] + pz * lhalf[k, 2]
                if ndh > 0.0:
                    e = lexp[lab, k]
                    # Schlick's rational approximation of ndh**e (no transcendental); a broad
                    # source spreads the same highlight energy over a wider, lower lobe
                    # (lnorm = irradiance · (e + 2) / (shininess + 2)).
                    s += lnorm[lab, k] * ndh / (e - e * ndh + ndh)
            out_d[y, x] = d
            out_s[y, x] = s
            out_rate[y, x] = band_gain[b] * (rho[lab, b] * d + spec[lab, b] * s)


def shade(
    label: np.ndarray, depth: np.ndarray, nrm: np.ndarray, centre: tuple[float, float], scale: float,
    lights: Lights, shadow: tuple[np.ndarray, np.ndarray, float, float, float] | None,
    rho: np.ndarray, spec: np.ndarray, shin: np.ndarray, band_gain: np.ndarray, layout: np.ndarray,
    backdrop_factor: float, threads: int | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shade a rasterised frame; returns (D, S, rate) float32 (H, W).

    ``shadow`` = (shadow depth map, camera→light rotation, centre x, centre y, scale)
    for the spotlight, or None.
    """
    h, w = label.shape
    if label.flags.writeable:  # read-only always (the kernel only reads it): one numba specialisation
        label = label.view()
        label.flags.writeable = False
    out_d = np.empty((h, w), dtype=np.float32)
    out_s = np.empty((h, w), dtype=np.float32)
    out_rate = np.empty((h, w), dtype=np.float32)
    facing = lights.irradiance * np.maximum(lights.dirs[:, 2], 0.0) if len(lights.irradiance) else np.zeros(0)
    bg_irr = backdrop_factor * (lights.ambient + float(facing.sum()))
    if shadow is None:
        smap, lmat, scx, scy, sscale, has = np.zeros((1, 1), np.float32), np.eye(3), 0.0, 0.0, 1.0, False
    else:
        smap, lmat, scx, scy, sscale = shadow
        has = True
    layout = np.ascontiguousarray(layout, dtype=np.int64)
    cx, cy = centre
    # What depends only on the light (and the material) is worked out once, not per pixel.
    dirs = np.ascontiguousarray(lights.dirs, dtype=np.float64).reshape(-1, 3)
    half = dirs + np.array([0.0, 0.0, 1.0])
    half /= np.maximum(np.linalg.norm(half, axis=1, keepdims=True), 1e-300)
    shin64 = np.asarray(shin, dtype=np.float64)
    lexp = np.ascontiguousarray(shin64[:, None] * lights.gloss[None, :])
    lnorm = np.ascontiguousarray(lights.irradiance[None, :] * (lexp + 2.0) / (shin64[:, None] + 2.0))

    def run(r0: int, r1: int) -> None:
        _shade_rows(
            label, depth, nrm, float(cx), float(cy), float(scale),
            dirs, lights.irradiance, half, lights.shadowed, lexp, lnorm,
            float(lights.ambient), float(bg_irr),
            smap, np.ascontiguousarray(lmat, dtype=np.float64), float(scx), float(scy), float(sscale), has,
            rho, spec, band_gain, layout, out_d, out_s, out_rate, r0, r1,
        )

    split_rows(run, h, threads)
    return out_d, out_s, out_rate


def radiance_cube(
    label: np.ndarray, d: np.ndarray, s: np.ndarray, rho: np.ndarray, spec: np.ndarray,
    band_gain: Sequence[float] | np.ndarray, scale: float = 1.0,
) -> np.ndarray:
    """The full-resolution cube ``scale · band_gain[b] · (rho[label, b] · D + spec[label, b] · S)``.

    Same expression the shader evaluates for each pixel's own band, here for every band.
    """
    nb = rho.shape[1]
    h, w = label.shape
    cube = np.empty((nb, h, w), dtype=np.float32)
    g = np.asarray(band_gain, dtype=np.float64) * scale
    for b in range(nb):
        r = (rho[:, b] * np.float32(g[b])).astype(np.float32)
        sp = (spec[:, b] * np.float32(g[b])).astype(np.float32)
        np.multiply(r[label], d, out=cube[b])
        cube[b] += sp[label] * s
    return cube
