"""Exposure brackets: frames of one pose at several exposures merged into one cube.

Under the spotlight a face in its shadow gets the room bounce alone, about 1/65 of a lit face's
light, so at an exposure that keeps the lit faces below full scale the shadowed ones sit a few
noise SDs above the dark frame (docs/evaluation.md, "Twelfth pass"). A longer exposure of the
same pose lifts them; its lit faces clip. Merging keeps, per band and pixel, every exposure in
which that band did not clip, and estimates the signal as their total counts over their total
exposure time: the maximum-likelihood estimate of a rate from Poisson counts (shot noise), so a
long exposure weighs in proportion to the light it collected (Hasinoff, Durand and Freeman,
"Noise-optimal capture for high dynamic range photography", CVPR 2010, sec. 3: with read noise
the optimal weights differ a little, most at the shortest exposures). The result is on the first
frame's scale (DN at its exposure × gain), so a bracket's merged cube reads like that frame with
less noise, and its clipping mask is where every exposure clipped.

The cubes must be dark-subtracted cubes of one demosaicing method and one pose; the masks are
``stability.band_saturation`` of each frame's raw mosaic (which bands of each pixel hold a
clipped raw value). Sans-I/O: arrays in, arrays out.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from m2s2hil.processing.errors import BracketError


@dataclass(frozen=True)
class Merged:
    cube: np.ndarray  # float32 (bands, H, W): DN at the first frame's exposure × gain
    clipped: np.ndarray  # bool (bands, H, W): clipped in every frame of the bracket
    frames_used: np.ndarray  # uint8 (bands, H, W): how many frames each value was taken from


def merge_bracket(cubes: Sequence[np.ndarray], scales: Sequence[float],
                  clipped: Sequence[np.ndarray]) -> Merged:
    """Merge one pose's ``cubes`` taken at ``scales`` (exposure × gain of each) with their per-band
    clipping masks ``clipped`` (module docstring). A band clipped in every frame keeps the
    shortest frame's value, scaled, and stays flagged."""
    if not cubes or not (len(cubes) == len(scales) == len(clipped)):
        raise BracketError(f"a bracket needs as many cubes, scales and masks, got {len(cubes)}, "
                           f"{len(scales)}, {len(clipped)}")
    shape = np.shape(cubes[0])
    if len(shape) != 3:
        raise BracketError(f"cubes are (bands, H, W), got shape {shape}")
    for i, (c, m) in enumerate(zip(cubes, clipped, strict=True)):
        if np.shape(c) != shape or np.shape(m) != shape:
            raise BracketError(f"frame {i}: cube {np.shape(c)} and mask {np.shape(m)}, expected {shape}")
    t = np.asarray(scales, dtype=np.float64)
    if not (np.all(np.isfinite(t)) and np.all(t > 0)):
        raise BracketError(f"exposure × gain must be finite and > 0, got {list(scales)}")
    ref = float(t[0])
    # float32 throughout: a 10-bit value × a few frames is far inside its 24-bit mantissa
    cube = np.zeros(shape, np.float32)  # the counts, then (in place) their rate at ``ref``
    exposed = np.zeros(shape, np.float32)
    used = np.zeros(shape, np.uint8)
    for c, m, ti in zip(cubes, clipped, t, strict=True):
        ok = ~np.asarray(m, dtype=bool)
        np.add(cube, c, out=cube, where=ok)
        np.add(exposed, np.float32(ti), out=exposed, where=ok)
        used += ok
    everywhere = used == 0
    np.divide(cube, exposed, out=cube, where=~everywhere)
    cube *= np.float32(ref)
    if everywhere.any():  # clipped in every frame: the shortest frame's value, scaled
        shortest = int(np.argmin(t))
        fallback = np.asarray(cubes[shortest], dtype=np.float32) * np.float32(ref / t[shortest])
        cube[everywhere] = fallback[everywhere]
    return Merged(cube, everywhere, used)
