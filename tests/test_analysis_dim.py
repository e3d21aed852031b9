"""Issue 23, sixth pass: regions too dim for a per-pixel threshold (``segmenters.foreground``),
near-black judged on the denoised cube, and components merged by average linkage. Each test also
runs the behaviour before (or the rule without the step) where it failed, so it can fail."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from scipy import ndimage
from sim_frame import one_frame

from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.segmenters.foreground import DIM_MIN_PIXELS, dim_regions, foreground_mask
from m2s2hil.analysis.segmenters.spectral import (
    SpectralSegmenter,
    average_linkage_groups,
    single_linkage_groups,
)


def noisy_scene(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A 96² cube of 4 bands: a bright square, a dim square (1.2 noise SDs per band) and a line two
    pixels wide (3 SDs), each of their pixels within the backdrop's noise to the per-pixel rule
    (dark-subtracted, clipped at zero, like the processor's). The line stands for a rim of blends."""
    rng = np.random.default_rng(seed)
    signal = np.zeros((4, 96, 96))
    bright = np.zeros((96, 96), dtype=bool)
    bright[10:40, 10:40] = True
    dim = np.zeros_like(bright)
    dim[55:90, 50:85] = True
    line = np.zeros_like(bright)
    line[20:22, 50:90] = True
    signal[:, bright] = 200.0
    signal[:, dim] = 1.2
    signal[:, line] = 3.0
    cube = np.maximum(signal + rng.normal(0.0, 1.0, signal.shape), 0.0)
    return cube, bright, dim, line


def test_a_dim_region_is_found_on_window_means_and_a_thin_line_is_not():
    cube, bright, dim, line = noisy_scene()
    fg, _ = foreground_mask(cube, "backdrop")
    assert fg[bright].mean() > 0.99
    assert fg[dim].mean() < 0.5  # per pixel, most of the dim region is backdrop
    added = dim_regions(cube, fg)
    assert not np.any(added & fg)
    assert fg[line].mean() < 0.1
    # the region's interior is found (its edge, half in a window of backdrop, partly)
    assert (fg | added)[ndimage.binary_erosion(dim, iterations=3)].mean() > 0.9
    assert (fg | added)[dim].mean() > 0.75
    # the window means lift the thin line too, but it has no interior: the opening drops it
    assert dim_regions(cube, fg, opening=0)[line].mean() > 0.8
    assert added[line].mean() < 0.1
    backdrop = ~(bright | dim | line)
    assert added[backdrop].mean() < 0.01


def test_dim_regions_off_and_degenerate_masks():
    cube, _, _, _ = noisy_scene(1)
    fg, _ = foreground_mask(cube, "backdrop")
    assert not dim_regions(cube, fg, radius=0).any()
    assert not dim_regions(cube, np.ones_like(fg)).any()
    assert not dim_regions(cube, np.zeros_like(fg)).any()
    assert DIM_MIN_PIXELS > 1
    with pytest.raises(AnalysisInputError, match="dim_radius"):
        SpectralSegmenter(dim_radius=-1)


def hubble_b2(**conditions: Any) -> Any:
    """Hubble B2 at E1, 30°, 256² cube, under ``conditions`` (``simulated_frames`` keywords)."""
    return one_frame("hubble", "B2", size=1024, **conditions)


@pytest.fixture(scope="module")
def hubble_b2_at_5_percent():
    # Hubble B2 at 5 % of full scale: its dark part (2 514 pixels of a 256² cube) fell to the backdrop
    return hubble_b2(lightings=["weak"], peak_fraction=0.05)


def dark_part(cube: np.ndarray, gt: np.ndarray) -> int:
    """The material of the frame whose pixels are dimmest (the one the fifth pass lost)."""
    energy = np.linalg.norm(cube, axis=0)
    ids = [int(i) for i in np.unique(gt) if i > 0]
    return min(ids, key=lambda i: float(np.median(energy[gt == i])))


def majority(labels: np.ndarray, where: np.ndarray) -> int:
    return int(np.bincount(labels[where]).argmax())


def has_own_group(labels: np.ndarray, gt: np.ndarray, part: int) -> bool:
    """Whether the label most of material ``part`` carries is no other material's majority."""
    others = {majority(labels, gt == i) for i in np.unique(gt) if i > 0 and i != part}
    return majority(labels, gt == part) not in others


def test_a_dark_material_at_5_percent_peak_is_found_and_fitted(hubble_b2_at_5_percent):
    f = hubble_b2_at_5_percent
    dark = dark_part(f.cube, f.gt)
    part = f.gt == dark
    new = SpectralSegmenter().analyse(f.cube)
    assert new.fit is not None
    assert (new.labels[part] > 0).mean() > 0.7
    assert int(new.fit[part].sum()) > 0  # no longer near-black once denoised
    assert has_own_group(new.labels, f.gt, dark)
    # before: the per-pixel threshold handed it to the backdrop
    old = SpectralSegmenter(dim_radius=0, dark_after_denoise=False).analyse(f.cube)
    assert (old.labels[part] > 0).mean() < 0.3
    # found, but judged near-black per pixel: out of the fit, and labelled as a neighbour
    per_pixel = SpectralSegmenter(dark_after_denoise=False).analyse(f.cube)
    assert per_pixel.fit is not None and int(per_pixel.fit[part].sum()) == 0
    assert not has_own_group(per_pixel.labels, f.gt, dark)


def chain_angles(step_deg: float, n: int) -> np.ndarray:
    """Pairwise angles of n unit spectra ``step_deg`` apart along one great circle."""
    t = np.radians(step_deg) * np.arange(n)
    u = np.stack([np.cos(t), np.sin(t)], axis=1)
    return np.degrees(np.arccos(np.clip(u @ u.T, -1.0, 1.0)))


def test_average_linkage_does_not_chain_where_single_linkage_does():
    # seven components 0.5° apart: 3° end to end; each neighbour is under a 1.5° merge angle
    angle = chain_angles(0.5, 7)
    single = single_linkage_groups(angle, np.full(angle.shape, 1.5))
    average = average_linkage_groups(angle, 1.5)
    assert single.tolist() == [0] * 7  # one chain: both ends 3° apart in one group
    assert int(average.max()) + 1 >= 2
    for g in np.unique(average):  # within a group, the mean angle stays under the limit
        idx = np.flatnonzero(average == g)
        if idx.size > 1:
            assert angle[np.ix_(idx, idx)][np.triu_indices(idx.size, 1)].mean() < 1.5
    # groups numbered by their first component, as the union-find numbered them
    assert average[0] == 0 and all(np.diff(np.maximum.accumulate(average)) <= 1)
    # two tight pairs far apart: both rules agree
    pairs = chain_angles(0.3, 2)
    far = np.block([[pairs, np.full((2, 2), 20.0)], [np.full((2, 2), 20.0), pairs]])
    assert single_linkage_groups(far, np.full(far.shape, 1.5)).tolist() == [0, 0, 1, 1]
    assert average_linkage_groups(far, 1.5).tolist() == [0, 0, 1, 1]


@pytest.fixture(scope="module")
def hubble_b2_spotlight():
    # Hubble B2 under the spotlight at 0°: its body and dark part, 2.2° apart in shape, are fitted
    # as components a fraction of a degree apart along the shading, which chained
    return hubble_b2(lightings=["directional"], spot_angle_deg=0.0)


def test_the_dark_part_under_the_spotlight_keeps_its_own_group(hubble_b2_spotlight):
    f = hubble_b2_spotlight
    dark = dark_part(f.cube, f.gt)
    assert has_own_group(SpectralSegmenter().analyse(f.cube).labels, f.gt, dark)
    assert not has_own_group(SpectralSegmenter(merge_linkage="single").analyse(f.cube).labels, f.gt, dark)
    with pytest.raises(AnalysisInputError, match="merge_linkage"):
        SpectralSegmenter(merge_linkage="complete")  # type: ignore[arg-type]
